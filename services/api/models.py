"""Response and request models of the job-service API (they make the OpenAPI document), the
shared error models, and the converters from job-store records to responses.

Every error answer has one of two shapes: :class:`ErrorOut` (``{"detail": "one line"}``) for
401, 404, 409, 413, 416, 429, 507 and 400, and FastAPI's validation list
:class:`ValidationErrorOut` (``{"detail": [{"loc": [...], "msg": ..., "type": ...}]}``) for
every 422, whether pydantic, an ``InputError`` from ``shared/`` or a route raised it.
:func:`errors` builds a route's ``responses=`` from the status codes it can answer.
"""

from __future__ import annotations

import time
from typing import Any
from urllib.parse import quote

from pydantic import BaseModel, Field

from services.api.schema import any_params_schema
from shared.service.jobs import StageState, job_fraction, stage_spec
from shared.service.jobstore import Batch, Job, Stage
from shared.service.rerenders import Rerender


# ---- errors ------------------------------------------------------------------------------------
class ErrorOut(BaseModel):
    """An error answer: one line saying what is wrong, naming the object or field."""

    detail: str


class ValidationItem(BaseModel):
    """One problem of a request: where (``["body", "params", "preview", "size"]``), what, and its kind."""

    loc: list[str | int]
    msg: str
    type: str


class ValidationErrorOut(BaseModel):
    """A 422 answer: the list of problems of the request (FastAPI's shape)."""

    detail: list[ValidationItem]


_DESCRIPTIONS = {
    400: "the request body cannot be parsed (a malformed multipart form)",
    401: "no valid ``Authorization: Bearer KEY``",
    403: "the link's token is malformed, for another job, expired or its key revoked",
    404: "no such object, or it belongs to another key",
    409: "the object's state does not allow this (already final, already used, wrong offset)",
    413: "the request body is larger than the upload limit (archives, chunks) or the JSON body limit",
    416: "the requested byte range lies outside the file",
    422: "the request is invalid: every problem with its field",
    429: "the key's limit of concurrently running jobs is reached (the limit is named)",
    507: "the key's limit of stored bytes is reached (the limit is named), or the service's storage is full "
         "(with Retry-After)",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` documenting the error statuses ``codes`` with their shared models."""
    return {c: {"model": ValidationErrorOut if c == 422 else ErrorOut, "description": _DESCRIPTIONS[c]} for c in codes}


# ---- artifact media types ----------------------------------------------------------------------
#: The media type each artifact is served with, by file suffix; any other file is
#: ``application/octet-stream``. A closed list, so the OpenAPI document names every type the
#: API serves (:func:`artifact_content`).
ARTIFACT_MEDIA_TYPES = {
    ".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".webp": "image/webp",
    ".mp4": "video/mp4", ".json": "application/json", ".csv": "text/csv", ".txt": "text/plain",
    ".glb": "model/gltf-binary", ".gltf": "model/gltf+json", ".html": "text/html",
}  # fmt: skip
OCTET_STREAM = "application/octet-stream"


def artifact_media_type(name: str) -> str:
    """The media type an artifact file ``name`` is served with."""
    suffix = name[name.rfind(".") :].lower() if "." in name.rsplit("/", 1)[-1] else ""
    return ARTIFACT_MEDIA_TYPES.get(suffix, OCTET_STREAM)


def artifact_content() -> dict[str, Any]:
    """The ``content`` of an artifact answer in the OpenAPI document: every media type served."""
    return {t: {"schema": {"type": "string", "format": "binary"}} for t in sorted({OCTET_STREAM, *ARTIFACT_MEDIA_TYPES.values()})}


# ---- resources ------------------------------------------------------------------------------
class StageOut(BaseModel):
    name: str
    state: str
    queue: str
    progress: float
    attempts: int
    started_at: float | None = None
    finished_at: float | None = None
    seconds: float | None = Field(None, description="run time of the last attempt")
    error: str | None = None
    reused: bool = Field(False, description="output found in the store (identical inputs), nothing re-run")
    summary: dict[str, Any] | None = None


class ArtifactLink(BaseModel):
    name: str
    url: str = Field(description="percent-encoded URL path of the file (a map stage's # is %23)")


class RerenderOut(BaseModel):
    """The job's latest preview re-render, run beside the finished job (its state is its own)."""

    id: str
    state: str = Field(description="queued, running, succeeded or failed")
    reason: str = Field(description="nightly-changed, nightly-all or manual")
    progress: float
    requested_at: float
    started_at: float | None = None
    finished_at: float | None = None
    error: str | None = Field(None, description="why it failed (the job and its preview are unchanged)")


class JobOut(BaseModel):
    id: str
    kind: str
    name: str
    state: str = Field(description="queued, running, succeeded, failed or cancelled")
    batch: str | None = None
    progress: float = Field(description="finished fraction of the job's work: each stage's own fraction, weighed by its typical share")
    created_at: float
    started_at: float | None = None
    finished_at: float | None = None
    error: str | None = Field(None, description="the failed stage and its one-line reason")
    stages: list[StageOut]
    artifacts: str = Field(description="URL path of the job's artifact list")
    links: list[ArtifactLink] = Field(default_factory=list, description="the published files of its finished stages")
    viewer: str | None = Field(None, description="URL path of the web viewer of its tiles (once they are built)")
    rerender: RerenderOut | None = None


class JobList(BaseModel):
    jobs: list[JobOut]
    total: int
    limit: int
    offset: int
    next_offset: int | None = None


class RejectedOut(BaseModel):
    capture: str = Field(description="the file's name as sent")
    error: str = Field(description="why it was refused, one line")


class BatchOut(BaseModel):
    id: str
    name: str
    created_at: float
    total: int = Field(description="every file sent with the batch: its jobs and its rejected files")
    counts: dict[str, int] = Field(description="jobs by state (queued, running, succeeded, failed, cancelled) and "
                                               "rejected: files refused at intake")
    progress: float = Field(description="fraction of the batch's files that are final (rejected ones are)")
    jobs: list[str] = Field(default_factory=list, description="ids of the batch's jobs, oldest first: a page of "
                                                             "them (jobs_limit, jobs_offset); from POST, those it made")
    jobs_total: int = Field(0, description="how many jobs the batch has")
    jobs_next_offset: int | None = Field(None, description="jobs_offset of the next page, if any")
    rejected: list[RejectedOut] = Field(default_factory=list, description="files refused at intake, with their reasons "
                                                                          "(from POST, those of this request)")


class ArtifactOut(BaseModel):
    name: str
    stage: str
    size: int
    sha256: str
    url: str


class ArtifactList(BaseModel):
    job: str
    name: str = Field("", description="the job's name (the viewer titles its page with it)")
    artifacts: list[ArtifactOut]


class UploadOut(BaseModel):
    id: str
    offset: int
    finished: bool
    max_bytes: int


class Health(BaseModel):
    """Whether the service can take work: ``ok``, or ``degraded`` (answered 503) when the
    database does not answer or the data folder's free space is below the configured floor."""

    status: str = Field(description="ok or degraded")
    database: bool = Field(description="the job database answers")
    free_bytes: int | None = Field(None, description="free bytes of the data folder's filesystem (None: unreadable)")
    min_free_bytes: int = Field(description="the floor below which the service is degraded (GRAYLIGHT_MIN_FREE_BYTES)")
    problems: list[str] = Field(default_factory=list, description="what makes the service degraded, one line each")


class UploadCreate(BaseModel):
    filename: str = Field("capture.zip", max_length=300)


class RetryIn(BaseModel):
    params: dict[str, Any] | None = Field(
        None, description="new job parameters (stages they affect re-run); those of the job's kind",
        json_schema_extra={"anyOf": [*any_params_schema()["anyOf"], {"type": "null"}]},
    )


# ---- converters --------------------------------------------------------------------------------
def stage_out(s: Stage) -> StageOut:
    seconds = (s.finished_at - s.started_at) if s.finished_at and s.started_at else None
    if s.state == StageState.RUNNING and s.started_at:
        seconds = time.time() - s.started_at
    return StageOut(
        name=s.name, state=s.state, queue=s.queue, progress=s.progress, attempts=s.attempts,
        started_at=s.started_at, finished_at=s.finished_at, seconds=seconds, error=s.error, reused=s.reused,
        summary=s.summary,
    )  # fmt: skip


def job_progress(job: Job) -> float:
    """The finished fraction of a job's work (:func:`shared.service.jobs.job_fraction`)."""
    return job_fraction(job.kind, ((s.name, s.state, s.progress) for s in job.stages))


def artifact_url(job_id: str, name: str) -> str:
    """The percent-encoded URL path of artifact ``name`` (``STAGE/PATH`` or a short name) of a job."""
    return f"/v1/jobs/{job_id}/artifacts/{quote(name, safe='/')}"


def published_names(job: Job) -> list[str]:
    """The short names the job's succeeded stages publish (and their aliases), in graph order."""
    out: list[str] = []
    for st in job.stages:
        if st.state == StageState.SUCCEEDED:
            out.extend(n for n in stage_spec(job.kind, st.name).published_names(st.summary) if n not in out)
    return out


def viewer_path(job: Job) -> str | None:
    """The viewer page of a job whose tiles are built, else None."""
    tiles = next((s for s in job.stages if s.name == "tiles"), None)
    return f"/viewer/{job.id}" if tiles is not None and tiles.state == StageState.SUCCEEDED else None


def rerender_out(r: Rerender | None) -> RerenderOut | None:
    if r is None:
        return None
    return RerenderOut(id=r.id, state=r.state, reason=r.reason, progress=r.progress, requested_at=r.requested_at,
                       started_at=r.started_at, finished_at=r.finished_at, error=r.error)  # fmt: skip


def job_out(job: Job, rerender: Rerender | None = None) -> JobOut:
    return JobOut(
        id=job.id, kind=job.kind, name=job.name, state=job.state, batch=job.batch_id, progress=job_progress(job),
        created_at=job.created_at, started_at=job.started_at, finished_at=job.finished_at, error=job.error,
        stages=[stage_out(s) for s in job.stages], artifacts=f"/v1/jobs/{job.id}/artifacts",
        links=[ArtifactLink(name=n, url=artifact_url(job.id, n)) for n in published_names(job)],
        viewer=viewer_path(job), rerender=rerender_out(rerender),
    )  # fmt: skip


def batch_out(b: Batch, jobs: list[str] | None = None, rejected: list[dict[str, str]] | None = None,
              jobs_total: int | None = None, jobs_next_offset: int | None = None) -> BatchOut:  # fmt: skip
    """A batch's answer: ``rejected`` defaults to every file it refused."""
    if rejected is None:
        rejected = [{"capture": r.capture, "error": r.error} for r in b.rejects]
    return BatchOut(id=b.id, name=b.name, created_at=b.created_at, total=b.total, counts=b.counts,
                    progress=b.progress, jobs=jobs or [], jobs_total=len(jobs or []) if jobs_total is None else jobs_total,
                    jobs_next_offset=jobs_next_offset, rejected=[RejectedOut(**r) for r in rejected])  # fmt: skip


class ReportRow(BaseModel):
    """One capture of a batch, as a registrar files it."""

    capture: str = Field(description="the capture's name as submitted (file name or storage reference)")
    job: str | None = Field(description="its job; null for a file refused at intake (state rejected)")
    state: str = Field(description="its job's state, or rejected")
    points: int | None = Field(None, description="points of its cloud (after triangulation)")
    error: str | None = Field(None, description="the failure reason, one line")
    artifacts: list[ArtifactLink]
    verdict: str | None = Field(None, description="the quality report's verdict: 'publishable' or why not")
    scene: str | None = Field(None, description="URL that gives a published object's Voyager link (GET with the key)")
    qa_report: str | None = Field(None, description="URL of a published object's quality report (qa.html)")


class BatchReport(BaseModel):
    batch: BatchOut
    rows: list[ReportRow]


class BatchRetryOut(BaseModel):
    batch: BatchOut
    retried: list[str] = Field(description="ids of the jobs that run again (those that failed or were cancelled)")


class BatchRerenderOut(BaseModel):
    batch: BatchOut
    rerendering: list[str] = Field(description="ids of the jobs whose preview is being rendered again")
