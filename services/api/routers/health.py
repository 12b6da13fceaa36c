"""``GET /health``: readiness, without a key: the database answers and the data folder has
room (its free space at least ``GRAYLIGHT_MIN_FREE_BYTES``); 503 otherwise, with the reasons."""

from __future__ import annotations

import os

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from services.api.deps import Svc
from services.api.models import Health

router = APIRouter(tags=["service"])


def free_bytes(path: os.PathLike[str] | str) -> int | None:
    """Bytes an unprivileged writer may still use on ``path``'s filesystem (its nearest
    existing ancestor's), None when unreadable."""
    p = os.path.abspath(path)
    while not os.path.exists(p) and os.path.dirname(p) != p:
        p = os.path.dirname(p)
    try:
        st = os.statvfs(p)
    except OSError:
        return None
    return st.f_bavail * st.f_frsize


@router.get("/health", response_model=Health,
            responses={503: {"model": Health, "description": "degraded: the database does not answer or the data "
                                                               "folder is below its free-space floor"}})  # fmt: skip
def health(svc: Svc) -> Health | JSONResponse:
    """Readiness; needs no key. 503 when degraded (``problems`` says why)."""
    try:
        ok = svc.store.ping()
    except Exception:
        ok = False
    floor = svc.settings.min_free_bytes
    free = free_bytes(svc.settings.data_dir)
    problems = [] if ok else ["the job database does not answer"]
    if free is not None and free < floor:
        problems.append(f"the data folder has {free} bytes free, below the floor of {floor} (GRAYLIGHT_MIN_FREE_BYTES)")
    out = Health(status="degraded" if problems else "ok", database=ok, free_bytes=free, min_free_bytes=floor,
                 problems=problems)  # fmt: skip
    return JSONResponse(out.model_dump(), 503) if problems else out
