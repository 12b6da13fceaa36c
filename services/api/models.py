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

from pydantic import BaseModel, Field

from services.api.schema import any_params_schema
from shared.service.jobs import StageState
from shared.service.jobstore import Batch, Job, Stage


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
    404: "no such object, or it belongs to another key",
    409: "the object's state does not allow this (already final, already used, wrong offset)",
    413: "the request body is larger than the upload limit",
    416: "the requested byte range lies outside the file",
    422: "the request is invalid: every problem with its field",
    429: "the key's limit of concurrently running jobs is reached (the limit is named)",
    507: "the key's limit of stored bytes is reached (the limit is named)",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` documenting the error statuses ``codes`` with their shared models."""
    return {c: {"model": ValidationErrorOut if c == 422 else ErrorOut, "description": _DESCRIPTIONS[c]} for c in codes}


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


class JobOut(BaseModel):
    id: str
    kind: str
    name: str
    state: str = Field(description="queued, running, succeeded, failed or cancelled")
    batch: str | None = None
    progress: float
    created_at: float
    started_at: float | None = None
    finished_at: float | None = None
    error: str | None = Field(None, description="the failed stage and its one-line reason")
    stages: list[StageOut]
    artifacts: str


class JobList(BaseModel):
    jobs: list[JobOut]
    total: int
    limit: int
    offset: int
    next_offset: int | None = None


class BatchOut(BaseModel):
    id: str
    name: str
    created_at: float
    total: int
    counts: dict[str, int] = Field(description="jobs by state (queued, running, succeeded, failed, cancelled)")
    progress: float = Field(description="fraction of the batch's jobs that are final")
    jobs: list[str] = Field(default_factory=list, description="ids of jobs created by this request")
    rejected: list[dict[str, str]] = Field(default_factory=list, description="captures refused at intake")


class ArtifactOut(BaseModel):
    name: str
    stage: str
    size: int
    sha256: str
    url: str


class ArtifactList(BaseModel):
    job: str
    artifacts: list[ArtifactOut]


class UploadOut(BaseModel):
    id: str
    offset: int
    finished: bool
    max_bytes: int


class Health(BaseModel):
    status: str
    database: bool


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
    """The finished fraction of a job's stages (a running stage counts its own progress)."""
    n = len(job.stages) or 1
    return sum(1.0 if s.state == StageState.SUCCEEDED else s.progress for s in job.stages) / n


def job_out(job: Job) -> JobOut:
    return JobOut(
        id=job.id, kind=job.kind, name=job.name, state=job.state, batch=job.batch_id, progress=job_progress(job),
        created_at=job.created_at, started_at=job.started_at, finished_at=job.finished_at, error=job.error,
        stages=[stage_out(s) for s in job.stages], artifacts=f"/v1/jobs/{job.id}/artifacts",
    )  # fmt: skip


def batch_out(b: Batch, jobs: list[str] | None = None, rejected: list[dict[str, str]] | None = None) -> BatchOut:
    return BatchOut(id=b.id, name=b.name, created_at=b.created_at, total=b.total, counts=b.counts,
                    progress=b.progress, jobs=jobs or [], rejected=rejected or [])  # fmt: skip


class ArtifactLink(BaseModel):
    name: str
    url: str


class ReportRow(BaseModel):
    """One capture of a batch, as a registrar files it."""

    capture: str = Field(description="the capture's name as submitted (file name or storage reference)")
    job: str
    state: str
    points: int | None = Field(None, description="points of its cloud (after triangulation)")
    error: str | None = Field(None, description="the failure reason, one line")
    artifacts: list[ArtifactLink]
    verdict: str | None = Field(None, description="the quality report's verdict: 'publishable' or why not")


class BatchReport(BaseModel):
    batch: BatchOut
    rows: list[ReportRow]


class BatchRetryOut(BaseModel):
    batch: BatchOut
    retried: list[str] = Field(description="ids of the jobs that run again (those that failed or were cancelled)")
