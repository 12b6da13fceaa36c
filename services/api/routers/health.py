"""``GET /health``: liveness, without a key."""

from __future__ import annotations

from fastapi import APIRouter

from services.api.deps import Svc
from services.api.models import Health

router = APIRouter(tags=["service"])


@router.get("/health", response_model=Health)
def health(svc: Svc) -> Health:
    """Liveness; needs no key."""
    try:
        ok = svc.store.ping()
    except Exception:
        ok = False
    return Health(status="ok" if ok else "degraded", database=ok)
