"""Dependencies the routers share: the service (:class:`Service`, built once by
``create_app`` and kept in ``app.state``), the caller's API key (:data:`Key`), and lookups of
the caller's own jobs, batches and uploads (another key's are 404, exactly like absent ones)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Header, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from prometheus_client import CollectorRegistry

from services.api.intake import ID, Intake
from shared.service.artifacts import ArtifactStore
from shared.service.config import Settings
from shared.service.jobstore import ApiKey, Batch, Job, JobStore, Upload
from shared.service.metrics import service_registry

__all__ = ["ID", "Key", "Service", "Svc", "current_key", "get_service", "owned_batch", "owned_job", "owned_upload"]

@dataclass
class Service:
    """What every route works with: the configuration, the job store, the artifact store,
    the intake (submissions -> stored captures -> queued jobs) and the metrics registry."""

    settings: Settings
    store: JobStore
    arts: ArtifactStore
    intake: Intake
    metrics: CollectorRegistry

    @classmethod
    def build(cls, settings: Settings) -> Service:
        store = JobStore(settings.database_url)
        arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
        return cls(settings, store, arts, Intake(settings, store, arts), service_registry(settings, store, arts))


def get_service(request: Request) -> Service:
    return request.app.state.service


Svc = Annotated[Service, Depends(get_service)]


async def current_key(request: Request, authorization: Annotated[str | None, Header()] = None) -> ApiKey:
    """The API key of the request (``Authorization: Bearer KEY``); 401 otherwise."""
    if not authorization or not authorization.startswith("Bearer "):
        raise HTTPException(401, "missing 'Authorization: Bearer KEY' header", headers={"WWW-Authenticate": "Bearer"})
    svc = get_service(request)
    key = await run_in_threadpool(svc.store.authenticate, authorization[7:].strip())
    if key is None:
        raise HTTPException(401, "unknown or revoked API key", headers={"WWW-Authenticate": "Bearer"})
    return key


Key = Annotated[ApiKey, Depends(current_key)]


def owned_job(svc: Service, job_id: str, key: ApiKey) -> Job:
    """The caller's job ``job_id``; 404 when absent or another key's."""
    job = svc.store.get_job(job_id, key.id) if ID.match(job_id) else None
    if job is None:
        raise HTTPException(404, f"job {job_id} not found")
    return job


def owned_batch(svc: Service, batch_id: str, key: ApiKey) -> Batch:
    """The caller's batch ``batch_id``; 404 when absent or another key's."""
    b = svc.store.get_batch(batch_id, key.id) if ID.match(batch_id) else None
    if b is None:
        raise HTTPException(404, f"batch {batch_id} not found")
    return b


def owned_upload(svc: Service, upload_id: str, key: ApiKey) -> Upload:
    """The caller's upload session ``upload_id``; 404 when absent or another key's."""
    up = svc.store.get_upload(upload_id, key.id) if ID.match(upload_id) else None
    if up is None:
        raise HTTPException(404, f"upload {upload_id} not found")
    return up
