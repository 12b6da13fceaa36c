"""Batches (a collection's captures submitted together): ``POST /v1/batches``,
``GET /v1/batches`` and ``GET /v1/batches/{id}`` (job counts by state and progress)."""

from __future__ import annotations

from fastapi import APIRouter, Request

from services.api.deps import Key, Svc, owned_batch
from services.api.http import is_form, parse_body, read_form
from services.api.intake import BatchCreate
from services.api.models import BatchOut, batch_out, errors
from services.api.schema import batch_body

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
