"""Artifacts of a job: ``GET /v1/jobs/{id}/artifacts`` (every file of every finished stage)
and ``GET /v1/jobs/{id}/artifacts/{name}`` (one file, with byte ranges from S3)."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse, Response, StreamingResponse

from services.api.deps import Key, Svc, owned_job
from services.api.http import byte_range
from services.api.models import (
    ArtifactList,
    ArtifactOut,
    artifact_content,
    artifact_media_type,
    artifact_url,
    errors,
)
from shared.service.artifacts import ArtifactStore
from shared.service.jobs import StageState, stage_spec
from shared.service.jobstore import Job

router = APIRouter(tags=["artifacts"])


def job_files(arts: ArtifactStore, job: Job) -> list[ArtifactOut]:
    """Every file of the job's finished stages as ``STAGE/PATH``, and the published ones
    (``cloud.ply``) also under their short names and aliases (the first stage publishing a name
    wins). Each ``url`` is percent-encoded (a map stage's ``#`` is ``%23``)."""
    out: list[ArtifactOut] = []
    published: set[str] = set()
    for st in job.stages:
        if st.state != StageState.SUCCEEDED or not st.output_key:
            continue
        m = arts.manifest(st.output_key)
        if m is None:
            continue
        spec = stage_spec(job.kind, st.name)
        for name, entry in sorted(m.files.items()):
            if name.startswith("."):
                continue  # the stage's own bookkeeping (its summary)
            full = f"{st.name}/{name}"
            out.append(ArtifactOut(name=full, stage=st.name, size=entry.size, sha256=entry.sha256,
                                   url=artifact_url(job.id, full)))  # fmt: skip
            for short in spec.short_names:
                if spec.published_file(short) == name and short not in published:
                    published.add(short)
                    out.append(ArtifactOut(name=short, stage=st.name, size=entry.size, sha256=entry.sha256,
                                           url=artifact_url(job.id, short)))  # fmt: skip
    return out


@router.get("/v1/jobs/{job_id}/artifacts", response_model=ArtifactList, responses=errors(401, 404, 422))
def list_artifacts(job_id: str, key: Key, svc: Svc) -> ArtifactList:
    """Files of every finished stage: ``STAGE/PATH``, plus short names (``cloud.ply``)."""
    job = owned_job(svc, job_id, key)
    return ArtifactList(job=job.id, name=job.name, artifacts=job_files(svc.arts, job))


@router.get("/v1/jobs/{job_id}/artifacts/{name:path}",
            responses={200: {"content": artifact_content(), "description": "the file"},
                       206: {"content": artifact_content(), "description": "the requested byte range"},
                       **errors(401, 404, 416, 422)})  # fmt: skip
def get_artifact(job_id: str, name: str, key: Key, svc: Svc, request: Request) -> Response:
    """One file: a short name (``cloud.ply``, ``preview.mp4``) or ``STAGE/PATH``
    (``tiles/metadata.json``: the viewer fetches tiles this way, with its Bearer key)."""
    job = owned_job(svc, job_id, key)
    stage_name, _, inner = name.partition("/")
    target: tuple[str, str] | None = None
    if inner:
        st = next((s for s in job.stages if s.name == stage_name), None)
        if st is not None and st.state == StageState.SUCCEEDED and st.output_key:
            target = (st.output_key, inner)
    else:
        for st in job.stages:
            file = stage_spec(job.kind, st.name).published_file(name)
            if st.state == StageState.SUCCEEDED and st.output_key and file is not None:
                target = (st.output_key, file)
                break
    if target is None:
        raise HTTPException(404, f"job {job.id} has no artifact {name!r} (yet)")
    okey, fname = target
    m = svc.arts.manifest(okey)
    if m is None or fname not in m.files:
        raise HTTPException(404, f"job {job.id} has no artifact {name!r}")
    return send_artifact(svc.arts, okey, fname, m.files[fname].size, m.files[fname].sha256, request)


def send_artifact(arts: ArtifactStore, okey: str, fname: str, size: int, sha256: str, request: Request,
                  headers: dict[str, str] | None = None) -> Response:
    """File ``fname`` of stored object ``okey`` (``size`` bytes, ``sha256``), whole or the byte range the
    request asks for, with ``headers`` added (the scene route's CORS headers)."""
    media = artifact_media_type(fname)
    headers = {**(headers or {}), "ETag": f'"{sha256}"', "X-Checksum-SHA256": sha256}
    local = arts.local_file(okey, fname)
    if local is not None:
        byte_range(request.headers.get("range"), size)  # a range outside: the documented JSON 416
        return FileResponse(local, media_type=media, headers=headers, filename=Path(fname).name)
    headers["Accept-Ranges"] = "bytes"
    span = byte_range(request.headers.get("range"), size)
    if span is not None:
        start, end = span
        headers.update({"Content-Range": f"bytes {start}-{end}/{size}", "Content-Length": str(end - start + 1)})
        return StreamingResponse(arts.iter_range(okey, fname, start, end - start + 1), status_code=206,
                                 media_type=media, headers=headers)  # fmt: skip
    headers["Content-Length"] = str(size)
    return StreamingResponse(arts.iter_bytes(okey, fname), media_type=media, headers=headers)
