"""Batches (a collection's captures submitted together): ``POST /v1/batches``,
``GET /v1/batches``, ``GET /v1/batches/{id}`` (counts by state, rejected files, progress, a
page of its jobs), ``GET /v1/batches/{id}/report.csv`` and ``report.json`` (one row per file
sent: its name as submitted, state or ``rejected``, points, failure reason, artifact links),
``POST /v1/batches/{id}/retry`` (re-runs what failed, nothing else) and
``POST /v1/batches/{id}/rerender`` (new previews of its finished jobs, beside them).
``{id}`` is the batch's id or its name (unique per key)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import Response

from services.api.deps import Key, Service, Svc, owned_batch
from services.api.http import is_form, parse_body, read_form
from services.api.intake import BatchCreate
from services.api.models import (
    ArtifactLink,
    BatchOut,
    BatchReport,
    BatchRerenderOut,
    BatchRetryOut,
    ReportRow,
    artifact_url,
    batch_out,
    errors,
)
from services.api.routers.jobs import rerun, rerun_plan
from services.api.schema import batch_body
from shared.service.jobs import JobState
from shared.service.jobstore import ApiKey, Batch, Job
from shared.service.report import QA_REPORT, CaptureRow, report_csv, report_rows, scene_url
from shared.service.rerenders import epoch_now, request_rerender

router = APIRouter(tags=["batches"])


@router.post("/v1/batches", response_model=BatchOut, status_code=201, openapi_extra=batch_body(),
             responses=errors(400, 401, 404, 413, 422, 429, 507))  # fmt: skip
async def submit_batch(request: Request, key: Key, svc: Svc) -> BatchOut:
    """Many captures at once: multipart files in ``captures``, or JSON with storage
    references (``captures``) or a ``manifest`` file listing them. A capture refused at
    intake is listed in ``rejected``; the others become jobs of the batch."""
    if is_form(request):
        form = await read_form(request, max_files=svc.settings.max_archive_files)
        try:
            name, jobs, rejected = await svc.intake.batch_from_form(form, key)
        finally:
            await form.close()
    else:
        name, jobs, rejected = await svc.intake.batch_from_json(await parse_body(request, BatchCreate), key)
    bid = svc.store.batch_for(key.id, name)
    # Every file sent is accounted for: the refused ones are kept with the batch.
    svc.store.add_rejects(bid, [(r["capture"], r["error"]) for r in rejected])
    b = svc.store.get_batch(bid, key.id)
    assert b is not None
    return batch_out(b, jobs, rejected, jobs_total=b.job_count)


@router.get("/v1/batches", response_model=list[BatchOut], responses=errors(401, 422))
def list_batches(key: Key, svc: Svc) -> list[BatchOut]:
    """Your batches, oldest first, each with its counts by state and its rejected files."""
    return [batch_out(b, jobs_total=b.job_count) for b in svc.store.list_batches(key.id)]


def batch_by_ref(svc: Service, ref: str, key: ApiKey) -> Batch:
    """The caller's batch with id or name ``ref``; 404 when there is none."""
    bid = svc.store.find_batch(key.id, ref) if 0 < len(ref) <= 200 else None
    return owned_batch(svc, bid or ref, key)


@router.get("/v1/batches/{batch_id}", response_model=BatchOut, responses=errors(401, 404, 422))
def get_batch(
    batch_id: str,
    key: Key,
    svc: Svc,
    jobs_limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    jobs_offset: Annotated[int, Query(ge=0, le=10_000_000)] = 0,
) -> BatchOut:
    """A batch (by id or name): counts by state (``rejected``: files refused at intake, listed
    with their reasons), the finished fraction, and a page of its jobs, oldest first."""
    b = batch_by_ref(svc, batch_id, key)
    ids, total = svc.store.batch_job_ids(b.id, jobs_limit, jobs_offset)
    nxt = jobs_offset + len(ids) if jobs_offset + len(ids) < total else None
    return batch_out(b, ids, jobs_total=total, jobs_next_offset=nxt)


#: Most jobs one batch report lists.
MAX_REPORT_ROWS = 100_000


def batch_jobs(svc: Service, key: ApiKey, b: Batch) -> list[Job]:
    return svc.store.list_jobs(key.id, batch_id=b.id, limit=MAX_REPORT_ROWS)[0]


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def _link(request: Request, row: CaptureRow, name: str) -> str:
    assert row.job is not None  # a rejected file publishes nothing
    return f"{_base(request)}{artifact_url(row.job, name)}"


@router.get("/v1/batches/{batch_id}/report.json", response_model=BatchReport, responses=errors(401, 404, 422))
def batch_report_json(batch_id: str, key: Key, svc: Svc, request: Request) -> BatchReport:
    """The batch's report: one row per file sent (rejected ones too), oldest first."""
    b = batch_by_ref(svc, batch_id, key)
    rows = [
        ReportRow(capture=r.capture, job=r.job, state=r.state, points=r.points, error=r.error, verdict=r.verdict,
                  artifacts=[ArtifactLink(name=a, url=_link(request, r, a)) for a in r.artifacts],
                  scene=scene_url(r, _base(request)),
                  qa_report=_link(request, r, QA_REPORT) if r.published else None)  # fmt: skip
        for r in report_rows(batch_jobs(svc, key, b), b.rejects)
    ]
    return BatchReport(batch=batch_out(b, jobs_total=b.job_count), rows=rows)


@router.get("/v1/batches/{batch_id}/report.csv", response_class=Response,
            responses={200: {"content": {"text/csv": {"schema": {"type": "string"}}},
                             "description": "columns capture, job, state, points, error, artifacts (space-separated URLs), "
                                            "verdict, scene (the URL giving its Voyager link), qa_report"},
                       **errors(401, 404, 422)})  # fmt: skip
def batch_report_csv(batch_id: str, key: Key, svc: Svc, request: Request) -> Response:
    """The batch's report as CSV (UTF-8, a header row, one row per file sent, rejected ones too)."""
    b = batch_by_ref(svc, batch_id, key)
    text = report_csv(report_rows(batch_jobs(svc, key, b), b.rejects), lambda r, a: _link(request, r, a),
                      _base(request))
    filename = f"batch-{b.id}.csv"
    return Response(text, media_type="text/csv; charset=utf-8",
                    headers={"Content-Disposition": f'attachment; filename="{filename}"'})  # fmt: skip


@router.post("/v1/batches/{batch_id}/retry", response_model=BatchRetryOut,
             responses=errors(401, 404, 409, 422, 429, 507))  # fmt: skip
def retry_batch(batch_id: str, key: Key, svc: Svc) -> BatchRetryOut:
    """Re-run the batch's failed and cancelled jobs, each from the stages that did not
    succeed (what succeeded is kept); succeeded, queued and running jobs are left alone."""
    b = batch_by_ref(svc, batch_id, key)
    todo = [j for j in batch_jobs(svc, key, b) if j.state in (JobState.FAILED, JobState.CANCELLED)]
    if not todo:
        raise HTTPException(409, f"batch {b.id}: nothing to retry (no job failed or was cancelled)")
    plans = [p for j in todo if (p := rerun_plan(j)) is not None]
    if plans:
        rerun(svc, key, plans)  # all or none, under the key's limits
    retried = [p[0] for p in plans]
    return BatchRetryOut(batch=batch_out(owned_batch(svc, b.id, key)), retried=retried)


@router.post("/v1/batches/{batch_id}/rerender", response_model=BatchRerenderOut, status_code=202,
             responses=errors(401, 404, 409, 422))  # fmt: skip
def rerender_batch(batch_id: str, key: Key, svc: Svc) -> BatchRerenderOut:
    """Render the previews of the batch's succeeded jobs again, each beside its job (the jobs
    stay succeeded; each new preview replaces the old one when it is done). Jobs without a
    preview, or already re-rendering, are left out."""
    b = batch_by_ref(svc, batch_id, key)
    epoch = epoch_now()
    done = [r.job_id for j in batch_jobs(svc, key, b) if j.state == JobState.SUCCEEDED
            if (r := request_rerender(svc.store, j, "all", "manual", svc.settings, epoch)) is not None]  # fmt: skip
    if not done:
        raise HTTPException(409, f"batch {b.id}: no succeeded job with a preview to re-render (or all are under way)")
    return BatchRerenderOut(batch=batch_out(b, jobs_total=b.job_count), rerendering=done)
