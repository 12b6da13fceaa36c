"""Intake of the job service: a submission (multipart form or JSON body) -> validated, stored
captures -> queued jobs.

In: the parsed form or body of ``POST /v1/jobs`` and ``POST /v1/batches`` and the caller's
API key. Out: :class:`~shared.service.jobstore.Job` records whose ready stages are published, and for
batches the captures refused at intake with their one-line reasons. Captures are zip or tar
archives (inspected by :func:`shared.service.archive.inspect_archive` before anything is stored, then
kept as content-addressed objects), finished upload sessions, or references to files already
in storage. Errors name the field or file: ``HTTPException`` 404/409, or
:class:`~shared.core.errors.InputError` (422, its field as the location) here and from the
checks in ``shared/``.

The routers in :mod:`services.api.routers` only pick the form or the body and hand it here.
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from fastapi import HTTPException
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field
from sqlalchemy import String, cast, select
from starlette.datastructures import FormData, UploadFile

from services.api.http import excerpt
from shared.core.errors import InputError
from shared.core.jsonsafe import MAX_DOCUMENT_BYTES, loads_bounded
from shared.formats.rig import parse_rig_bytes
from shared.service.admission import Admission, UploadTaken
from shared.service.archive import ArchiveLimits, inspect_archive
from shared.service.artifacts import ArtifactError, ArtifactStore, sha256_file
from shared.service.config import Settings
from shared.service.jobs import GRAPHS, graph_for, root_file
from shared.service.jobstore import ApiKey, Job, JobRow, JobStore, NewJob
from shared.service.params import check_job_params
from shared.service.queue import publish_stages

#: Ids of jobs, batches and uploads (UUIDs); anything else is 404 without a database query.
ID = re.compile(r"^[0-9a-f-]{36}$")
#: Names of jobs and batches: 1-200 ASCII letters, digits, spaces or ``.,:+@()[]-_``, or
#: characters beyond ASCII but for its control characters (letters of every script). Written
#: without ``\w``, which Python and the JSON Schema dialect of the OpenAPI document read
#: differently, so the document states exactly what is accepted.
NAME_PATTERN = r"^(?:[A-Za-z0-9_ .,:+@()\[\]-]|[^\x00-\x9f]){1,200}$"
_NAME = re.compile(NAME_PATTERN)
#: Internal prefixes of the store that a storage reference may not point into.
_PRIVATE_PREFIXES = ("objects/", "uploads/")
#: Most storage references in one batch.
MAX_BATCH_REFS = 10000
#: Longest storage reference (a path relative to the store root).
MAX_REF_CHARS = 1024

log = logging.getLogger(__name__)


class JobCreate(BaseModel):
    """A job from an upload session or from a reference into storage (JSON instead of multipart)."""

    kind: str = Field("scan", description="scan, calibrate or probe")
    name: str | None = Field(None, max_length=200, pattern=NAME_PATTERN)
    batch: str | None = Field(None, max_length=200, pattern=NAME_PATTERN)
    upload_id: str | None = Field(None, max_length=MAX_REF_CHARS, description="a finished upload session")
    capture_ref: str | None = Field(None, max_length=MAX_REF_CHARS,
                                    description="path of an archive or capture folder, relative to the storage root")
    params: dict[str, Any] = Field(default_factory=dict)


class BatchCreate(BaseModel):
    name: str = Field(..., min_length=1, max_length=200, pattern=NAME_PATTERN)
    kind: str = Field("scan", description="scan, calibrate or probe")
    captures: list[Annotated[str, Field(max_length=MAX_REF_CHARS)]] = Field(default_factory=list, max_length=MAX_BATCH_REFS,
                                description="storage references, one capture each")
    manifest: str | None = Field(None, max_length=MAX_REF_CHARS,
                                 description="storage reference of a text file listing one reference per line")
    params: dict[str, Any] = Field(default_factory=dict)


class NotInStorage(InputError):
    """A storage reference (``capture_ref``, ``manifest``) that names nothing in storage: 404."""


# ---- field checks -------------------------------------------------------------------------
def check_kind(kind: str) -> str:
    if kind not in GRAPHS:
        raise InputError("kind", f"unknown job kind {kind!r} (one of {', '.join(sorted(GRAPHS))})")
    if not graph_for(kind):
        raise InputError("kind", f"{kind} jobs cannot run in this installation (their stages are not installed)")
    return kind


def check_name(value: str | None, field: str) -> str | None:
    if value is None or value == "":
        return None
    if not _NAME.match(value):
        raise InputError(field, "must be 1-200 letters, digits, spaces or .,:+@()[]-_")
    return value


def check_params(params: Any, kind: str) -> dict[str, Any]:
    """A client's job parameters for a ``kind`` job (:func:`shared.service.params.check_job_params`);
    :class:`InputError` (422) names the field. A number with no fraction (``163.0``) is the
    integer it equals, as in JSON Schema."""
    return check_job_params(kind, _integral(params))


def _integral(value: Any) -> Any:
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, dict):
        return {k: _integral(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_integral(v) for v in value]
    return value


def form_text(value: Any) -> str | None:
    """A text field of a form; 422 when a file came in its place."""
    if value is None:
        return None
    if isinstance(value, UploadFile):
        raise InputError(value.filename or "field", "expected text, got a file")
    return str(value)


def _form_kind(form: FormData) -> str:
    """The multipart ``kind`` field: ``scan`` when absent; an empty or unknown one is refused
    (never read as the default: the OpenAPI document lists the kinds)."""
    kind = form.get("kind")
    return "scan" if kind is None else str(form_text(kind))


def _form_params(form: FormData, kind: str) -> dict[str, Any]:
    return check_params(loads_bounded(form_text(form.get("params")) or "{}", "params"), kind)


def _label(f: UploadFile) -> str:
    return Path(f.filename or "capture").name or "capture"


def _ref_name(ref: str) -> str:
    return ref.strip().strip("/").rsplit("/", 1)[-1]


async def _save(f: UploadFile, dest: Path) -> None:
    with open(dest, "wb") as out:
        while block := await f.read(1 << 20):
            out.write(block)


@dataclass
class _Stored:
    """What one request put into the store: object key -> whether this request created it,
    and capture key -> bytes its archive unpacks to."""

    objects: dict[str, bool] = field(default_factory=dict)
    unpacked: dict[str, int] = field(default_factory=dict)


class Intake:
    """Turns submissions into stored captures and queued jobs, for one service."""

    def __init__(self, settings: Settings, store: JobStore, arts: ArtifactStore) -> None:
        self.settings = settings
        self.store = store
        self.arts = arts
        self.limits = ArchiveLimits.from_settings(settings)
        self.quota = Admission(settings, store, arts)

    # ---- captures (blocking: run in the thread pool) ------------------------------------
    def _put(self, key: str, files: dict[str, Path], stored: _Stored) -> None:
        existed = self.arts.exists(key)
        self.arts.put_files(key, files)
        stored.objects.setdefault(key, not existed)

    def store_archive(self, path: Path, label: str, kind: str, stored: _Stored) -> tuple[str, str]:
        """Inspect an archive, then store it as a capture object: (capture_ref, capture_key)."""
        report = inspect_archive(path, self.limits, label=label, require=root_file(kind))
        key = sha256_file(path)
        suffix = ".zip" if report.kind == "zip" else ".tar"
        self._put(key, {f"capture{suffix}": path}, stored)
        stored.unpacked[key] = report.total_bytes
        return f"object:{key}", key

    def store_rig(self, data: bytes, label: str, stored: _Stored) -> str:
        parse_rig_bytes(data, label)  # bounded: size, depth, numbers, strict keys
        with tempfile.TemporaryDirectory() as tmp:
            p = Path(tmp) / "rig.json"
            p.write_bytes(data)
            key = sha256_file(p)
            self._put(key, {"rig.json": p}, stored)
        return key

    def _referenced(self, key: str) -> bool:
        """Whether any job holds object ``key`` (as its capture or its rig)."""
        with self.store.session() as s:
            q = select(JobRow.id).where(
                (JobRow.capture_ref == f"object:{key}") | cast(JobRow.params, String).contains(key)
            ).limit(1)
            return s.scalar(q) is not None

    def forget(self, stored: _Stored) -> None:
        """Take back the objects a refused request created (those no job holds meanwhile)."""
        for key, created in stored.objects.items():
            if created and not self._referenced(key):
                try:
                    self.arts.delete(key)
                except Exception as exc:  # the refusal is what the client must hear
                    log.warning("could not remove object %s of a refused request: %s", key[:12], exc)

    def resolve_ref(self, ref: str, kind: str, stored: _Stored) -> tuple[str, str]:
        """A reference to a capture already in storage: (capture_ref, capture_key). What a worker
        will unpack of it counts against the key's stored bytes while its job runs (issue 21),
        as an uploaded archive's does: a folder's bytes, or a local archive's inflated total read
        from its headers (which also refuses a bomb here, before any worker unpacks it). An
        archive on a remote store is bounded by the worker's limits as it inflates, uncounted."""
        clean = ref.strip().strip("/")
        if not clean or any(clean.startswith(p) for p in _PRIVATE_PREFIXES) or clean in ("objects", "uploads"):
            raise InputError("capture_ref", f"{excerpt(repr(ref))} is not a reference to a capture in storage")
        try:
            key, is_folder, size = self.arts.ref_stat(clean)  # one listing of the reference
            if is_folder:
                stored.unpacked[key] = size
            elif self.arts.is_local:
                local = Path(self.arts.fs._strip_protocol(self.arts.ref_path(clean)))
                stored.unpacked[key] = inspect_archive(local, self.limits, label=clean, require=root_file(kind)).total_bytes
        except ArtifactError as exc:
            raise InputError("capture_ref", str(exc)) from None
        except FileNotFoundError:
            raise NotInStorage("capture_ref", f"{excerpt(repr(ref))}: no such file or folder in storage") from None
        return f"ref:{clean}", key

    def read_manifest(self, ref: str) -> list[str]:
        """The storage references listed in a manifest file (one a line, ``#`` comments)."""
        clean = ref.strip().strip("/")
        if not clean or any(clean.startswith(p) for p in _PRIVATE_PREFIXES):
            raise InputError("manifest", f"{excerpt(repr(ref))} is not a reference to a file in storage")
        try:
            with self.arts.fs.open(self.arts.ref_path(clean), "rb") as f:
                data = f.read(4 << 20)
        except (FileNotFoundError, ArtifactError, IsADirectoryError):
            raise NotInStorage("manifest", f"{excerpt(repr(ref))}: no such file in storage") from None
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError("manifest", "manifest is not UTF-8 text") from None
        return [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]

    def make_jobs(self, key: ApiKey, news: list[NewJob], batch: str | None, stored: _Stored,
                  upload_id: str | None = None) -> list[Job]:  # fmt: skip
        """Admit and record the jobs (one transaction under the key's limits; the upload
        session ``upload_id`` is used up in it), then publish their ready stages. A refusal
        takes back what the request stored."""
        try:
            made = self.quota.create_jobs(key, news, batch, objects=stored.objects, unpacked=stored.unpacked,
                                          upload_id=upload_id)  # fmt: skip
        except BaseException:
            self.forget(stored)
            raise
        for _job, ready in made:
            publish_stages(ready, self.settings)
        return [job for job, _ready in made]

    @staticmethod
    def new_job(kind: str, capture_ref: str, capture_key: str, name: str, params: dict[str, Any]) -> NewJob:
        return NewJob(kind=kind, capture_ref=capture_ref, capture_key=capture_key, graph=graph_for(kind, params),
                      name=name, params=params)  # fmt: skip

    # ---- submissions --------------------------------------------------------------------
    async def _archive(self, f: UploadFile, kind: str, stored: _Stored) -> tuple[str, str]:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "upload"
            await _save(f, path)
            return await run_in_threadpool(self.store_archive, path, _label(f), kind, stored)

    async def _finished_upload(self, upload_id: str, key: ApiKey, kind: str, stored: _Stored) -> tuple[str, str, str]:
        """The capture of an upload session, stored as an object: (capture_ref, capture_key, label)."""
        up = self.store.get_upload(upload_id, key.id) if ID.match(upload_id) else None
        if up is None:
            raise HTTPException(404, f"upload {excerpt(upload_id)} not found")
        if up.finished:
            raise HTTPException(409, f"upload {up.id} was already used")
        label = Path(up.filename).name or "upload"
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "upload"
            await run_in_threadpool(self.arts.assemble_upload, up.id, up.chunks, path)
            cref, ckey = await run_in_threadpool(self.store_archive, path, label, kind, stored)
        return cref, ckey, label

    async def job_from_form(self, form: FormData, key: ApiKey) -> Job:
        """``POST /v1/jobs`` as multipart: ``capture`` (zip or tar) or ``capture_ref``, optional
        ``rig`` file, ``kind``, ``name``, ``batch`` and ``params`` (JSON)."""
        kind = check_kind(_form_kind(form))
        name = check_name(form_text(form.get("name")), "name")
        batch = check_name(form_text(form.get("batch")), "batch")
        params = _form_params(form, kind)
        capture, rig = form.get("capture"), form.get("rig")
        ref = None if isinstance(capture, UploadFile) else form_text(form.get("capture_ref"))
        incoming = sum(f.size or 0 for f in (capture, rig) if isinstance(f, UploadFile))
        await run_in_threadpool(self.quota.admit, key, 1, incoming)  # early: before anything is stored
        stored = _Stored()
        try:
            if isinstance(rig, UploadFile):
                # One byte past the bound, so an over-long rig is refused as such, never cut.
                data = await rig.read(MAX_DOCUMENT_BYTES + 1)
                if len(data) > MAX_DOCUMENT_BYTES:
                    size = rig.size if rig.size is not None else f"more than {MAX_DOCUMENT_BYTES}"
                    raise InputError(rig.filename or "rig", f"rig file of {size} bytes is too large "
                                                           f"(at most {MAX_DOCUMENT_BYTES})")  # fmt: skip
                params["rig"] = await run_in_threadpool(self.store_rig, data, rig.filename or "rig", stored)
            elif rig is not None:
                raise InputError("rig", "must be a file")
            if kind == "probe":
                cref, ckey = "none:", os.urandom(32).hex()
                name = name or "probe"
            elif isinstance(capture, UploadFile):
                cref, ckey = await self._archive(capture, kind, stored)
                name = name or _label(capture)
            elif ref:
                if len(ref) > MAX_REF_CHARS:
                    raise InputError("capture_ref", f"longer than {MAX_REF_CHARS} characters")
                cref, ckey = await run_in_threadpool(self.resolve_ref, ref, kind, stored)
                name = name or _ref_name(ref)
            else:
                raise InputError("capture", "a zip or tar file is required in this multipart field")
        except BaseException:
            await run_in_threadpool(self.forget, stored)
            raise
        new = self.new_job(kind, cref, ckey, name or "", params)
        return (await run_in_threadpool(self.make_jobs, key, [new], batch, stored))[0]

    async def job_from_json(self, body: JobCreate, key: ApiKey) -> Job:
        """``POST /v1/jobs`` as JSON: ``upload_id`` of an upload session, or ``capture_ref``."""
        kind = check_kind(body.kind)
        name = check_name(body.name, "name")
        batch = check_name(body.batch, "batch")
        params = check_params(body.params, kind)
        await run_in_threadpool(self.quota.admit, key, 1, 0)  # an upload's bytes are counted as it arrives
        stored = _Stored()
        upload = None
        try:
            if kind == "probe":
                cref, ckey = "none:", os.urandom(32).hex()
                name = name or "probe"
            elif body.upload_id:
                upload = body.upload_id
                cref, ckey, label = await self._finished_upload(body.upload_id, key, kind, stored)
                name = name or label
            elif body.capture_ref:
                cref, ckey = await run_in_threadpool(self.resolve_ref, body.capture_ref, kind, stored)
                name = name or _ref_name(body.capture_ref)
            else:
                raise InputError("body", "give upload_id or capture_ref (or send multipart with a capture file)")
        except BaseException:
            await run_in_threadpool(self.forget, stored)
            raise
        new = self.new_job(kind, cref, ckey, name or "", params)
        try:
            job = (await run_in_threadpool(self.make_jobs, key, [new], batch, stored, upload))[0]
        except UploadTaken:
            raise HTTPException(409, f"upload {upload} was already used") from None
        if upload is not None:
            await run_in_threadpool(self.arts.drop_upload, upload)
        return job

    async def batch_from_form(self, form: FormData, key: ApiKey) -> tuple[str, list[str], list[dict[str, str]]]:
        """``POST /v1/batches`` as multipart: files in ``captures``, ``name``, ``kind``, ``params``.
        Returns the batch name, the ids of the jobs made and the captures refused."""
        name = check_name(form_text(form.get("name")), "name")
        if not name:
            raise InputError("name", "a batch needs a name")
        kind = check_kind(_form_kind(form))
        params = _form_params(form, kind)
        files = form.getlist("captures")
        if any(not isinstance(f, UploadFile) for f in files):
            raise InputError("captures", "must be files")
        # The whole batch is admitted, or none of it.
        await run_in_threadpool(self.quota.admit, key, len(files), sum(f.size or 0 for f in files))
        news: list[NewJob] = []
        rejected: list[dict[str, str]] = []
        stored = _Stored()
        try:
            for f in files:
                try:
                    cref, ckey = await self._archive(f, kind, stored)
                except InputError as exc:
                    rejected.append({"capture": excerpt(_label(f)), "error": excerpt(str(exc), 400)})
                    continue
                news.append(self.new_job(kind, cref, ckey, _label(f), params))
        except BaseException:
            await run_in_threadpool(self.forget, stored)
            raise
        jobs = await run_in_threadpool(self.make_jobs, key, news, name, stored)
        return name, [j.id for j in jobs], rejected

    async def batch_from_json(self, body: BatchCreate, key: ApiKey) -> tuple[str, list[str], list[dict[str, str]]]:
        """``POST /v1/batches`` as JSON: storage references in ``captures`` and/or a ``manifest``."""
        name = check_name(body.name, "name")
        if not name:
            raise InputError("name", "a batch needs a name")
        kind = check_kind(body.kind)
        params = check_params(body.params, kind)
        refs = list(body.captures)
        if body.manifest:
            refs += await run_in_threadpool(self.read_manifest, body.manifest)
        if len(refs) > MAX_BATCH_REFS:
            raise InputError("captures", f"more than {MAX_BATCH_REFS} in one batch")
        await run_in_threadpool(self.quota.admit, key, len(refs), 0)  # early refusal
        news: list[NewJob] = []
        rejected: list[dict[str, str]] = []
        stored = _Stored()
        for ref in refs:
            try:
                if len(ref) > MAX_REF_CHARS:
                    raise InputError("capture_ref", f"longer than {MAX_REF_CHARS} characters")
                cref, ckey = await run_in_threadpool(self.resolve_ref, ref, kind, stored)
            except InputError as exc:
                # The reference is quoted once, as an excerpt; the error says what is wrong with it.
                rejected.append({"capture": excerpt(ref), "error": excerpt(exc.problem, 400)})
                continue
            news.append(self.new_job(kind, cref, ckey, ref.strip()[:300], params))
        jobs = await run_in_threadpool(self.make_jobs, key, news, name, stored)
        return name, [j.id for j in jobs], rejected
