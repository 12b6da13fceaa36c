"""Batches (a collection's captures submitted together): ``POST /v1/batches``,
``GET /v1/batches``, ``GET /v1/batches/{id}`` (job counts by state and progress),
``GET /v1/batches/{id}/report.csv`` and ``report.json`` (one row per capture: its name as
submitted, state, points, failure reason, artifact links) and ``POST /v1/batches/{id}/retry``
(re-runs what failed, nothing else)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import Response

from services.api.deps import Key, Service, Svc, owned_batch
from services.api.http import is_form, parse_body, read_form
from services.api.intake import BatchCreate
from services.api.models import (
    ArtifactLink,
    BatchOut,
    BatchReport,
    BatchRetryOut,
    ReportRow,
    batch_out,
    errors,
)
from services.api.routers.jobs import rerun
from services.api.schema import batch_body
from shared.service.jobs import JobState
from shared.service.jobstore import ApiKey, Batch, Job
from shared.service.report import CaptureRow, report_csv, report_rows

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
    b = svc.store.get_batch(svc.store.batch_for(key.id, name), key.id)
    assert b is not None
    return batch_out(b, jobs, rejected)


@router.get("/v1/batches", response_model=list[BatchOut], responses=errors(401, 422))
def list_batches(key: Key, svc: Svc) -> list[BatchOut]:
    """Your batches, oldest first, each with its counts by state."""
    return [batch_out(b) for b in svc.store.list_batches(key.id)]


@router.get("/v1/batches/{batch_id}", response_model=BatchOut, responses=errors(401, 404, 422))
def get_batch(batch_id: str, key: Key, svc: Svc) -> BatchOut:
    """A batch's progress: job counts by state and the finished fraction."""
    return batch_out(owned_batch(svc, batch_id, key))


#: Most jobs one batch report lists.
MAX_REPORT_ROWS = 100_000


def batch_jobs(svc: Service, key: ApiKey, b: Batch) -> list[Job]:
    return svc.store.list_jobs(key.id, batch_id=b.id, limit=MAX_REPORT_ROWS)[0]


def _link(request: Request, row: CaptureRow, name: str) -> str:
    return f"{str(request.base_url).rstrip('/')}/v1/jobs/{row.job}/artifacts/{name}"


@router.get("/v1/batches/{batch_id}/report.json", response_model=BatchReport, responses=errors(401, 404, 422))
def batch_report_json(batch_id: str, key: Key, svc: Svc, request: Request) -> BatchReport:
    """The batch's report: one row per capture, oldest first."""
    b = owned_batch(svc, batch_id, key)
    rows = [
        ReportRow(capture=r.capture, job=r.job, state=r.state, points=r.points, error=r.error, verdict=r.verdict,
                  artifacts=[ArtifactLink(name=a, url=_link(request, r, a)) for a in r.artifacts])  # fmt: skip
        for r in report_rows(batch_jobs(svc, key, b))
    ]
    return BatchReport(batch=batch_out(b), rows=rows)


@router.get("/v1/batches/{batch_id}/report.csv", response_class=Response,
            responses={200: {"content": {"text/csv": {"schema": {"type": "string"}}},
                             "description": "columns capture, job, state, points, error, artifacts (space-separated URLs)"},
                       **errors(401, 404, 422)})  # fmt: skip
def batch_report_csv(batch_id: str, key: Key, svc: Svc, request: Request) -> Response:
    """The batch's report as CSV (UTF-8, a header row, one row per capture)."""
    b = owned_batch(svc, batch_id, key)
    text = report_csv(report_rows(batch_jobs(svc, key, b)), lambda r, a: _link(request, r, a))
    filename = f"batch-{b.id}.csv"
    return Response(text, media_type="text/csv; charset=utf-8",
                    headers={"Content-Disposition": f'attachment; filename="{filename}"'})  # fmt: skip


@router.post("/v1/batches/{batch_id}/retry", response_model=BatchRetryOut,
             responses=errors(401, 404, 409, 422, 429, 507))  # fmt: skip
def retry_batch(batch_id: str, key: Key, svc: Svc) -> BatchRetryOut:
    """Re-run the batch's failed and cancelled jobs, each from the stages that did not
    succeed (what succeeded is kept); succeeded, queued and running jobs are left alone."""
    b = owned_batch(svc, batch_id, key)
    todo = [j for j in batch_jobs(svc, key, b) if j.state in (JobState.FAILED, JobState.CANCELLED)]
    if not todo:
        raise HTTPException(409, f"batch {b.id}: nothing to retry (no job failed or was cancelled)")
    svc.intake.quota.admit(key, jobs=len(todo))
    retried = [j.id for j in todo if rerun(svc, j)]
    return BatchRetryOut(batch=batch_out(owned_batch(svc, batch_id, key)), retried=retried)
