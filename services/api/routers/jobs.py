"""Jobs: ``POST /v1/jobs`` (submit), ``GET /v1/jobs`` (list), ``GET /v1/jobs/{id}``,
``POST /v1/jobs/{id}/cancel``, ``POST /v1/jobs/{id}/retry`` and ``POST /v1/jobs/{id}/rerender``
(a new preview, rendered beside the finished job)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request

from services.api.deps import Key, Service, Svc, owned_job
from services.api.http import is_form, parse_body, read_form
from services.api.intake import JobCreate, check_params
from services.api.models import JobList, JobOut, RetryIn, errors, job_out
from services.api.schema import job_body
from shared.service.jobs import JobState, StageView, rows_to_rerun
from shared.service.jobstore import Job
from shared.service.queue import publish_stages
from shared.service.rerenders import RerenderStore, request_rerender

router = APIRouter(tags=["jobs"])


@router.post("/v1/jobs", response_model=JobOut, status_code=201, openapi_extra=job_body(),
             responses=errors(400, 401, 404, 409, 413, 422, 429, 507))  # fmt: skip
async def submit_job(request: Request, key: Key, svc: Svc) -> JobOut:
    """Submit a job: multipart (field ``capture``: zip or tar), or JSON (``upload_id`` of a
    finished upload session, or ``capture_ref`` into storage)."""
    if is_form(request):
        form = await read_form(request, max_files=4)
        try:
            return job_out(await svc.intake.job_from_form(form, key))
        finally:
            await form.close()
    return job_out(await svc.intake.job_from_json(await parse_body(request, JobCreate), key))


@router.get("/v1/jobs", response_model=JobList, responses=errors(401, 422))
def list_jobs(
    key: Key,
    svc: Svc,
    state: Annotated[JobState | None, Query()] = None,
    batch: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    offset: Annotated[int, Query(ge=0, le=10_000_000)] = 0,
) -> JobList:
    """Your jobs, newest first; filter by state and by batch (id or name)."""
    batch_id = None
    if batch:
        batch_id = svc.store.find_batch(key.id, batch)
        if batch_id is None:
            return JobList(jobs=[], total=0, limit=limit, offset=offset)
    jobs, total = svc.store.list_jobs(key.id, state.value if state else None, batch_id, limit, offset)
    nxt = offset + len(jobs) if offset + len(jobs) < total else None
    return JobList(jobs=[job_out(j) for j in jobs], total=total, limit=limit, offset=offset, next_offset=nxt)


@router.get("/v1/jobs/{job_id}", response_model=JobOut, responses=errors(401, 404, 422))
def get_job(job_id: str, key: Key, svc: Svc) -> JobOut:
    """A job: its state, and per stage its state, progress, timings and error; the links of
    its published files and of its viewer; its latest preview re-render (run beside it)."""
    job = owned_job(svc, job_id, key)
    return job_out(job, RerenderStore(svc.store).latest_rerender(job.id))


@router.post("/v1/jobs/{job_id}/rerender", response_model=JobOut, status_code=202, responses=errors(401, 404, 409, 422))
def rerender_job(job_id: str, key: Key, svc: Svc) -> JobOut:
    """Render a succeeded job's preview again, beside it: the job stays ``succeeded`` with its
    ``finished_at``; ``rerender`` follows the new render, and the new preview replaces the old
    one at once when it is stored (a failed re-render leaves the old one)."""
    job = owned_job(svc, job_id, key)
    if request_rerender(svc.store, job, "all", "manual", svc.settings) is None:
        latest = RerenderStore(svc.store).latest_rerender(job.id)
        if latest is not None and latest.state in ("queued", "running"):
            raise HTTPException(409, f"job {job.id}: a re-render is already {latest.state}")
        raise HTTPException(409, f"job {job.id} has no finished preview to re-render (it is {job.state})")
    return job_out(job, RerenderStore(svc.store).latest_rerender(job.id))


@router.post("/v1/jobs/{job_id}/cancel", response_model=JobOut, responses=errors(401, 404, 409, 422))
def cancel_job(job_id: str, key: Key, svc: Svc) -> JobOut:
    """Cancel a queued or running job. A running stage stops at its next progress report
    after its next heartbeat (decode, preview and calibration report often) and stores
    nothing."""
    job = owned_job(svc, job_id, key)
    if svc.store.cancel_job(job.id) is None:
        raise HTTPException(409, f"job {job.id} is already {job.state}")
    return job_out(owned_job(svc, job_id, key))


def rerun(svc: Service, job: Job, new_params: dict[str, Any] | None = None) -> bool:
    """Re-run the job's stages that failed or were cancelled, and those whose inputs changed
    (``new_params``, a new stage version); their outputs already stored are found, not redone.
    False when nothing would re-run; 409 when the job is not final."""
    if job.state in (JobState.QUEUED, JobState.RUNNING):
        raise HTTPException(409, f"job {job.id} is {job.state}; cancel it first")
    params = dict(job.params)
    if new_params is not None:
        new = check_params(new_params, job.kind)
        params = {**new, **({"rig": job.params["rig"]} if "rig" in job.params else {})}
    rows = [StageView(st.name, st.state, st.depends_on, st.output_key) for st in job.stages]  # graph order
    todo = rows_to_rerun(job.kind, rows, job.capture_key, params)
    if not todo:
        return False
    newly = svc.store.reset_stages(job.id, todo, params=params)
    publish_stages(newly, svc.settings)
    return True


@router.post("/v1/jobs/{job_id}/retry", response_model=JobOut, responses=errors(400, 401, 404, 409, 413, 422, 429, 507))
def retry_job(job_id: str, key: Key, svc: Svc, body: RetryIn | None = None) -> JobOut:
    """Re-run the stages that failed or were cancelled, and those whose inputs changed
    (new parameters, a new stage version); finished stages with unchanged inputs are kept."""
    job = owned_job(svc, job_id, key)
    svc.intake.quota.admit(key, jobs=1)
    if not rerun(svc, job, body.params if body is not None else None):
        raise HTTPException(409, f"job {job.id}: nothing to retry (every stage succeeded with unchanged inputs)")
    return job_out(owned_job(svc, job_id, key))
