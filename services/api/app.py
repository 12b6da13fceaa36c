"""The job service's HTTP API (FastAPI). ``create_app()`` builds it; ``graylight serve`` runs it.

Every route but ``GET /health`` needs ``Authorization: Bearer KEY`` (``graylight keys
create NAME``); a key sees only its own jobs, batches, uploads and artifacts (others' are
404). Captures arrive as a zip or tar in the multipart field ``capture``, as a resumable
upload session (``/v1/uploads``), or as a reference to an object already in storage;
archives are inspected (traversal, links, bombs, file count, image header dimensions)
before anything is stored. OpenAPI docs at ``/docs``.

Routes: ``POST/GET /v1/jobs``, ``GET /v1/jobs/{id}``, ``POST /v1/jobs/{id}/cancel``,
``POST /v1/jobs/{id}/retry``, ``GET /v1/jobs/{id}/artifacts[/{name}]`` (``cloud.ply``, or
``STAGE/PATH`` for any file of a stage's output such as ``tiles/metadata.json``),
``POST/GET /v1/batches``, ``GET /v1/batches/{id}``, ``POST /v1/uploads``,
``GET/PATCH /v1/uploads/{id}``; the viewer (``services.viewer.routes``) at ``/viewer/{job}``.
"""

from __future__ import annotations

import importlib
import logging
import mimetypes
import re
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, TypeVar

from fastapi import Depends, FastAPI, Header, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, Field
from starlette.datastructures import FormData
from starlette.types import ASGIApp, Receive, Scope, Send

from services.api.intake import ID, BatchCreate, Intake, JobCreate, check_params
from shared.core.errors import InputError
from shared.service.artifacts import ArtifactStore
from shared.service.config import Settings, get_settings
from shared.service.jobs import (
    JobState,
    StageState,
    fanout_index,
    stage_key,
    stage_spec,
)
from shared.service.jobstore import ApiKey, Batch, Job, JobStore, Stage

log = logging.getLogger(__name__)

_Body = TypeVar("_Body", bound=BaseModel)


# ---- response models (they make the OpenAPI schema) ---------------------------------------
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
    counts: dict[str, int]
    progress: float
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
    params: dict[str, Any] | None = Field(None, description="new job parameters (stages they affect re-run)")


# ---- the request-size limit ------------------------------------------------------------------
class BodyLimit:
    """ASGI middleware: refuse a request body larger than ``limit`` bytes with 413, whether
    it announces its length or streams chunks (counted as they arrive)."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for k, v in scope.get("headers", []):
            if k == b"content-length" and v.isdigit() and int(v) > self.limit:
                await JSONResponse({"detail": f"request body larger than the limit of {self.limit} bytes"}, 413)(
                    scope, receive, send
                )
                return
        seen = 0

        async def counted() -> Any:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise _TooLarge()
            return message

        try:
            await self.app(scope, counted, send)
        except _TooLarge:
            await JSONResponse({"detail": f"request body larger than the limit of {self.limit} bytes"}, 413)(
                scope, receive, send
            )


class _TooLarge(Exception):
    pass


# ---- helpers ---------------------------------------------------------------------------------
@dataclass
class Service:
    settings: Settings
    store: JobStore
    arts: ArtifactStore


def _stage_out(s: Stage) -> StageOut:
    seconds = (s.finished_at - s.started_at) if s.finished_at and s.started_at else None
    if s.state == StageState.RUNNING and s.started_at:
        seconds = time.time() - s.started_at
    return StageOut(
        name=s.name, state=s.state, queue=s.queue, progress=s.progress, attempts=s.attempts,
        started_at=s.started_at, finished_at=s.finished_at, seconds=seconds, error=s.error, reused=s.reused,
        summary=s.summary,
    )  # fmt: skip


def job_out(job: Job) -> JobOut:
    n = len(job.stages) or 1
    progress = sum(1.0 if s.state == StageState.SUCCEEDED else s.progress for s in job.stages) / n
    return JobOut(
        id=job.id, kind=job.kind, name=job.name, state=job.state, batch=job.batch_id, progress=progress,
        created_at=job.created_at, started_at=job.started_at, finished_at=job.finished_at, error=job.error,
        stages=[_stage_out(s) for s in job.stages], artifacts=f"/v1/jobs/{job.id}/artifacts",
    )  # fmt: skip


def _batch_out(b: Batch, jobs: list[str] | None = None, rejected: list[dict[str, str]] | None = None) -> BatchOut:
    return BatchOut(id=b.id, name=b.name, created_at=b.created_at, total=b.total, counts=b.counts,
                    progress=b.progress, jobs=jobs or [], rejected=rejected or [])  # fmt: skip


def _bad(exc: Exception, status: int = 422) -> HTTPException:
    return HTTPException(status, " ".join(str(exc).split())[:1000])


async def current_key(request: Request, authorization: Annotated[str | None, Header()] = None) -> ApiKey:
    """The API key of the request (``Authorization: Bearer KEY``); 401 otherwise."""
    if not authorization or not authorization.startswith("Bearer "):
        raise HTTPException(401, "missing 'Authorization: Bearer KEY' header", headers={"WWW-Authenticate": "Bearer"})
    svc: Service = request.app.state.service
    key = await run_in_threadpool(svc.store.authenticate, authorization[7:].strip())
    if key is None:
        raise HTTPException(401, "unknown or revoked API key", headers={"WWW-Authenticate": "Bearer"})
    return key


Key = Annotated[ApiKey, Depends(current_key)]


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API for ``settings`` (default: the environment's)."""
    settings = settings or get_settings()
    svc = Service(settings, JobStore(settings.database_url), ArtifactStore(settings.storage_url, settings.s3_endpoint))
    app = FastAPI(
        title="Graylight job service",
        version="1",
        description="Structured-light scan jobs: submit captures, follow their stages, fetch clouds, tiles and previews.",
    )
    app.state.service = svc

    @app.exception_handler(InputError)
    async def _input_error(_request: Request, exc: InputError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, 422)

    def owned_job(job_id: str, key: ApiKey) -> Job:
        job = svc.store.get_job(job_id, key.id) if ID.match(job_id) else None
        if job is None:
            raise HTTPException(404, f"job {job_id} not found")
        return job

    intake = Intake(settings, svc.store, svc.arts)

    async def read_form(request: Request, max_files: int) -> FormData:
        try:
            return await request.form(max_files=max_files, max_fields=16, max_part_size=64 << 10)
        except _TooLarge:
            raise
        except Exception as exc:
            raise _bad(exc, 400) from None

    # ---- routes ----------------------------------------------------------------------------
    @app.get("/health", response_model=Health, tags=["service"])
    def health() -> Health:
        """Liveness; needs no key."""
        try:
            ok = svc.store.ping()
        except Exception:
            ok = False
        return Health(status="ok" if ok else "degraded", database=ok)

    job_body = {
        "requestBody": {
            "required": True,
            "content": {
                "multipart/form-data": {
                    "schema": {
                        "type": "object",
                        "properties": {
                            "capture": {"type": "string", "format": "binary", "description": "zip or tar of a capture folder"},
                            "rig": {"type": "string", "format": "binary", "description": "rig.json to use instead of the capture's"},
                            "kind": {"type": "string", "default": "scan"},
                            "name": {"type": "string"},
                            "batch": {"type": "string"},
                            "params": {"type": "string", "description": "JSON object"},
                            "capture_ref": {"type": "string", "description": "instead of capture: a path in storage"},
                        },
                    }
                },
                "application/json": {"schema": JobCreate.model_json_schema()},
            },
        }
    }

    @app.post("/v1/jobs", response_model=JobOut, status_code=201, tags=["jobs"], openapi_extra=job_body)
    async def submit_job(request: Request, key: Key) -> JobOut:
        """Submit a job: multipart (field ``capture``: zip or tar), or JSON (``upload_id`` of a
        finished upload session, or ``capture_ref`` into storage)."""
        if _is_form(request):
            form = await read_form(request, max_files=4)
            try:
                return job_out(await intake.job_from_form(form, key))
            finally:
                await form.close()
        return job_out(await intake.job_from_json(await _body(request, JobCreate), key))

    @app.get("/v1/jobs", response_model=JobList, tags=["jobs"])
    def list_jobs(
        key: Key,
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

    @app.get("/v1/jobs/{job_id}", response_model=JobOut, tags=["jobs"])
    def get_job(job_id: str, key: Key) -> JobOut:
        """A job: its state, and per stage its state, progress, timings and error."""
        return job_out(owned_job(job_id, key))

    @app.post("/v1/jobs/{job_id}/cancel", response_model=JobOut, tags=["jobs"])
    def cancel_job(job_id: str, key: Key) -> JobOut:
        """Cancel a queued or running job. A running stage stops at its next progress report
        after its next heartbeat (decode, preview and calibration report often) and stores
        nothing."""
        job = owned_job(job_id, key)
        if svc.store.cancel_job(job.id) is None:
            raise HTTPException(409, f"job {job.id} is already {job.state}")
        return job_out(owned_job(job_id, key))

    @app.post("/v1/jobs/{job_id}/retry", response_model=JobOut, tags=["jobs"])
    def retry_job(job_id: str, key: Key, body: RetryIn | None = None) -> JobOut:
        """Re-run the stages that failed or were cancelled, and those whose inputs changed
        (new parameters, a new stage version); finished stages with unchanged inputs are kept."""
        from workers.dispatch import publish_stages

        job = owned_job(job_id, key)
        if job.state in (JobState.QUEUED, JobState.RUNNING):
            raise HTTPException(409, f"job {job.id} is {job.state}; cancel it first")
        params = dict(job.params)
        if body is not None and body.params is not None:
            new = check_params(body.params)
            params = {**new, **({"rig": job.params["rig"]} if "rig" in job.params else {})}
        rerun: set[str] = set()
        keys: dict[str, str] = {}
        for st in job.stages:  # in graph order, so upstream keys are known first
            spec = stage_spec(job.kind, st.name)
            upstream = {d: keys.get(d, "") for d in st.depends_on}
            keys[st.name] = stage_key(spec, job.capture_key, params, upstream, fanout_index(st.name))
            changed = st.output_key != keys[st.name]
            if st.state != StageState.SUCCEEDED or changed or any(d in rerun for d in st.depends_on):
                rerun.add(st.name)
        if not rerun:
            raise HTTPException(409, f"job {job.id}: nothing to retry (every stage succeeded with unchanged inputs)")
        newly = svc.store.reset_stages(job.id, rerun, params=params)
        publish_stages(newly, settings)
        return job_out(owned_job(job_id, key))

    def job_files(job: Job) -> list[ArtifactOut]:
        out: list[ArtifactOut] = []
        published: set[str] = set()
        for st in job.stages:
            if st.state != StageState.SUCCEEDED or not st.output_key:
                continue
            m = svc.arts.manifest(st.output_key)
            if m is None:
                continue
            spec = stage_spec(job.kind, st.name)
            for name, entry in sorted(m.files.items()):
                if name.startswith("."):
                    continue  # the stage's own bookkeeping (its summary)
                url = f"/v1/jobs/{job.id}/artifacts/{st.name}/{name}"
                out.append(ArtifactOut(name=f"{st.name}/{name}", stage=st.name, size=entry.size, sha256=entry.sha256, url=url))
                if name in spec.publish and name not in published:
                    published.add(name)
                    out.append(ArtifactOut(name=name, stage=st.name, size=entry.size, sha256=entry.sha256,
                                           url=f"/v1/jobs/{job.id}/artifacts/{name}"))  # fmt: skip
        return out

    @app.get("/v1/jobs/{job_id}/artifacts", response_model=ArtifactList, tags=["artifacts"])
    def list_artifacts(job_id: str, key: Key) -> ArtifactList:
        """Files of every finished stage: ``STAGE/PATH``, plus short names (``cloud.ply``)."""
        job = owned_job(job_id, key)
        return ArtifactList(job=job.id, artifacts=job_files(job))

    @app.get("/v1/jobs/{job_id}/artifacts/{name:path}", tags=["artifacts"],
             responses={200: {"content": {"application/octet-stream": {}}, "description": "the file"}})  # fmt: skip
    def get_artifact(job_id: str, name: str, key: Key, request: Request) -> Response:
        """One file: a short name (``cloud.ply``, ``preview.mp4``) or ``STAGE/PATH``
        (``tiles/metadata.json``: the viewer fetches tiles this way, with its Bearer key)."""
        job = owned_job(job_id, key)
        stage_name, _, inner = name.partition("/")
        target: tuple[str, str] | None = None
        if inner:
            st = next((s for s in job.stages if s.name == stage_name), None)
            if st is not None and st.state == StageState.SUCCEEDED and st.output_key:
                target = (st.output_key, inner)
        else:
            for st in job.stages:
                if st.state == StageState.SUCCEEDED and st.output_key and name in stage_spec(job.kind, st.name).publish:
                    target = (st.output_key, name)
                    break
        if target is None:
            raise HTTPException(404, f"job {job.id} has no artifact {name!r} (yet)")
        okey, fname = target
        m = svc.arts.manifest(okey)
        if m is None or fname not in m.files:
            raise HTTPException(404, f"job {job.id} has no artifact {name!r}")
        media = mimetypes.guess_type(fname)[0] or "application/octet-stream"
        headers = {"ETag": f'"{m.files[fname].sha256}"', "X-Checksum-SHA256": m.files[fname].sha256}
        local = svc.arts.local_file(okey, fname)
        if local is not None:
            return FileResponse(local, media_type=media, headers=headers, filename=Path(fname).name)
        size = m.files[fname].size
        headers["Accept-Ranges"] = "bytes"
        span = _byte_range(request.headers.get("range"), size)
        if span is not None:
            start, end = span
            headers.update({"Content-Range": f"bytes {start}-{end}/{size}", "Content-Length": str(end - start + 1)})
            return StreamingResponse(svc.arts.iter_range(okey, fname, start, end - start + 1), status_code=206,
                                     media_type=media, headers=headers)  # fmt: skip
        headers["Content-Length"] = str(size)
        return StreamingResponse(svc.arts.iter_bytes(okey, fname), media_type=media, headers=headers)

    # ---- batches ---------------------------------------------------------------------------
    batch_body = {
        "requestBody": {
            "required": True,
            "content": {
                "multipart/form-data": {
                    "schema": {
                        "type": "object",
                        "properties": {
                            "name": {"type": "string"},
                            "kind": {"type": "string", "default": "scan"},
                            "params": {"type": "string", "description": "JSON object applied to every job"},
                            "captures": {"type": "array", "items": {"type": "string", "format": "binary"}},
                        },
                        "required": ["name"],
                    }
                },
                "application/json": {"schema": BatchCreate.model_json_schema()},
            },
        }
    }

    @app.post("/v1/batches", response_model=BatchOut, status_code=201, tags=["batches"], openapi_extra=batch_body)
    async def submit_batch(request: Request, key: Key) -> BatchOut:
        """Many captures at once: multipart files in ``captures``, or JSON with storage
        references (``captures``) or a ``manifest`` file listing them. A capture refused at
        intake is listed in ``rejected``; the others become jobs of the batch."""
        if _is_form(request):
            form = await read_form(request, max_files=settings.max_archive_files)
            try:
                name, jobs, rejected = await intake.batch_from_form(form, key)
            finally:
                await form.close()
        else:
            name, jobs, rejected = await intake.batch_from_json(await _body(request, BatchCreate), key)
        b = svc.store.get_batch(svc.store.batch_for(key.id, name), key.id)
        assert b is not None
        return _batch_out(b, jobs, rejected)

    @app.get("/v1/batches", response_model=list[BatchOut], tags=["batches"])
    def list_batches(key: Key) -> list[BatchOut]:
        return [_batch_out(b) for b in svc.store.list_batches(key.id)]

    @app.get("/v1/batches/{batch_id}", response_model=BatchOut, tags=["batches"])
    def get_batch(batch_id: str, key: Key) -> BatchOut:
        """A batch's progress: job counts by state and the finished fraction."""
        b = svc.store.get_batch(batch_id, key.id) if ID.match(batch_id) else None
        if b is None:
            raise HTTPException(404, f"batch {batch_id} not found")
        return _batch_out(b)

    # ---- resumable uploads -----------------------------------------------------------------
    @app.post("/v1/uploads", response_model=UploadOut, status_code=201, tags=["uploads"])
    def create_upload(key: Key, body: UploadCreate | None = None) -> UploadOut:
        """Open an upload session; send the archive in chunks with ``PATCH`` and
        ``Upload-Offset``, resume from ``GET``'s offset, then ``POST /v1/jobs {"upload_id"}``."""
        up = svc.store.create_upload(key.id, (body or UploadCreate()).filename)
        return UploadOut(id=up.id, offset=0, finished=False, max_bytes=settings.max_upload_bytes)

    def owned_upload(upload_id: str, key: ApiKey) -> Any:
        up = svc.store.get_upload(upload_id, key.id) if ID.match(upload_id) else None
        if up is None:
            raise HTTPException(404, f"upload {upload_id} not found")
        return up

    @app.get("/v1/uploads/{upload_id}", response_model=UploadOut, tags=["uploads"])
    def get_upload(upload_id: str, key: Key) -> UploadOut:
        up = owned_upload(upload_id, key)
        return UploadOut(id=up.id, offset=up.offset, finished=up.finished, max_bytes=settings.max_upload_bytes)

    @app.patch("/v1/uploads/{upload_id}", response_model=UploadOut, tags=["uploads"],
               openapi_extra={"requestBody": {"content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})  # fmt: skip
    async def append_upload(
        upload_id: str, request: Request, key: Key, upload_offset: Annotated[int, Header(ge=0)]
    ) -> UploadOut:
        """Append the request body at ``Upload-Offset`` (must equal the current offset; 409 tells the right one)."""
        up = await run_in_threadpool(owned_upload, upload_id, key)
        if up.finished:
            raise HTTPException(409, f"upload {up.id} is finished")
        if upload_offset != up.offset:
            raise HTTPException(409, f"Upload-Offset is {upload_offset} but the upload is at {up.offset}")
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "chunk"
            size = 0
            with open(path, "wb") as out:
                async for block in request.stream():
                    size += len(block)
                    if up.offset + size > settings.max_upload_bytes:
                        raise HTTPException(413, f"upload exceeds the limit of {settings.max_upload_bytes} bytes")
                    out.write(block)
            if size == 0:
                raise HTTPException(422, "body: an empty chunk")
            await run_in_threadpool(svc.arts.put_chunk, up.id, up.chunks, path)
        if not await run_in_threadpool(svc.store.advance_upload, up.id, up.offset, up.offset + size):
            now = owned_upload(upload_id, key)
            raise HTTPException(409, f"upload moved on concurrently; it is at {now.offset}")
        return UploadOut(id=up.id, offset=up.offset + size, finished=False, max_bytes=settings.max_upload_bytes)

    # ---- the viewer hook -------------------------------------------------------------------
    try:
        viewer = importlib.import_module("services.viewer.routes")
    except ImportError:
        viewer = None
    if viewer is not None and hasattr(viewer, "router"):
        app.include_router(viewer.router)

    app.add_middleware(BodyLimit, limit=settings.max_upload_bytes + (1 << 20))
    return app


def _byte_range(header: str | None, size: int) -> tuple[int, int] | None:
    """The (first, last) byte of a single-range ``Range`` header, None for a whole-file
    answer; HTTP 416 when the range lies outside the file. Viewers read ``octree.bin`` so."""
    if not header:
        return None
    m = re.fullmatch(r"\s*bytes=(\d*)-(\d*)\s*", header)
    if m is None or (not m.group(1) and not m.group(2)):
        return None  # multi-range or malformed: answer with the whole file, as HTTP allows
    if m.group(1):
        start = int(m.group(1))
        end = min(int(m.group(2)), size - 1) if m.group(2) else size - 1
    else:
        start, end = max(size - int(m.group(2)), 0), size - 1
    if start >= size or start > end:
        raise HTTPException(416, f"range {header!r} is outside the file of {size} bytes",
                            headers={"Content-Range": f"bytes */{size}"})  # fmt: skip
    return start, end


def _is_form(request: Request) -> bool:
    return request.headers.get("content-type", "").startswith("multipart/form-data")


async def _body(request: Request, model: type[_Body]) -> _Body:
    """The JSON body as ``model``; 422 with the first line of the validation error."""
    try:
        return model.model_validate_json(await request.body())
    except Exception as exc:
        raise HTTPException(422, f"body: {exc}".splitlines()[0]) from None
