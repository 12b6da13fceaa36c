"""Resumable uploads: ``POST /v1/uploads`` opens a session, ``PATCH /v1/uploads/{id}``
appends a chunk at ``Upload-Offset``, ``GET /v1/uploads/{id}`` tells where to resume."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Header, HTTPException, Request
from fastapi.concurrency import run_in_threadpool

from services.api.deps import Key, Svc, owned_upload
from services.api.models import UploadCreate, UploadOut, errors
from shared.core.errors import InputError

router = APIRouter(tags=["uploads"])


@router.post("/v1/uploads", response_model=UploadOut, status_code=201, responses=errors(400, 401, 413, 422, 507))
def create_upload(key: Key, svc: Svc, body: UploadCreate | None = None) -> UploadOut:
    """Open an upload session; send the archive in chunks with ``PATCH`` and
    ``Upload-Offset``, resume from ``GET``'s offset, then ``POST /v1/jobs {"upload_id"}``."""
    up = svc.store.create_upload(key.id, (body or UploadCreate()).filename)
    return UploadOut(id=up.id, offset=0, finished=False, max_bytes=svc.settings.max_upload_bytes)


@router.get("/v1/uploads/{upload_id}", response_model=UploadOut, responses=errors(401, 404, 422))
def get_upload(upload_id: str, key: Key, svc: Svc) -> UploadOut:
    up = owned_upload(svc, upload_id, key)
    return UploadOut(id=up.id, offset=up.offset, finished=up.finished, max_bytes=svc.settings.max_upload_bytes)


_CHUNK_BODY = {
    "requestBody": {
        "required": True,
        "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary", "minLength": 1}}},
    }
}


@router.patch("/v1/uploads/{upload_id}", response_model=UploadOut, openapi_extra=_CHUNK_BODY,
              responses=errors(401, 404, 409, 413, 422, 507))  # fmt: skip
async def append_upload(
    upload_id: str, request: Request, key: Key, svc: Svc, upload_offset: Annotated[int, Header(ge=0)]
) -> UploadOut:
    """Append the request body at ``Upload-Offset`` (must equal the current offset; 409 tells the right one)."""
    settings = svc.settings
    up = await run_in_threadpool(owned_upload, svc, upload_id, key)
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
            raise InputError("body", "an empty chunk")
        await run_in_threadpool(svc.intake.quota.admit, key, 0, size)  # early: before it is stored
        await run_in_threadpool(svc.arts.put_chunk, up.id, up.chunks, path)
    try:
        # The key's stored-bytes limit and the offset's compare-and-set, in one transaction.
        moved = await run_in_threadpool(svc.intake.quota.advance_upload, key, up.id, up.offset, up.offset + size)
    except BaseException:
        await run_in_threadpool(svc.arts.drop_chunk, up.id, up.chunks)
        raise
    if not moved:
        now = owned_upload(svc, upload_id, key)
        raise HTTPException(409, f"upload moved on concurrently; it is at {now.offset}")
    return UploadOut(id=up.id, offset=up.offset + size, finished=False, max_bytes=settings.max_upload_bytes)
