"""The job service's HTTP API (FastAPI). ``create_app()`` builds it; ``graylight serve`` runs it.

Every route but ``GET /health`` needs ``Authorization: Bearer KEY`` (``graylight keys
create NAME``); a key sees only its own jobs, batches, uploads and artifacts (others' are
404). Captures arrive as a zip or tar in the multipart field ``capture``, as a resumable
upload session (``/v1/uploads``), or as a reference to an object already in storage;
archives are inspected (traversal, links, bombs, file count, image header dimensions)
before anything is stored. OpenAPI docs at ``/docs``; the document lists every status each
route can answer (errors: :mod:`services.api.errors`).

Layout: one router per resource in ``services/api/routers/`` (``health``, ``jobs``,
``artifacts``, ``batches`` with their reports and retries, ``uploads``, ``metrics`` for
Prometheus), the dependencies they share in
:mod:`services.api.deps`, response models in :mod:`services.api.models`, HTTP plumbing
(body limit, byte ranges, body parsing) in :mod:`services.api.http`, the documented request
bodies in :mod:`services.api.schema`, the limits per key in :mod:`shared.service.admission`, and
intake (forms and bodies -> stored captures -> queued jobs) in :mod:`services.api.intake`. The viewer
(``services.viewer.routes``) is mounted at ``/viewer/{job}``.
"""

from __future__ import annotations

import importlib

from fastapi import FastAPI

from services.api.deps import Service
from services.api.errors import install_error_handlers
from services.api.http import BodyLimit, IgnoreOtherRanges
from services.api.routers import ROUTERS
from shared.service.config import Settings, get_settings

__all__ = ["create_app"]


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API for ``settings`` (default: the environment's)."""
    settings = settings or get_settings()
    app = FastAPI(
        title="Graylight job service",
        version="1",
        description="Structured-light scan jobs: submit captures, follow their stages, fetch clouds, tiles and previews.",
    )
    app.state.service = Service.build(settings)
    install_error_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    # The viewer is optional in an installation without its package.
    try:
        viewer = importlib.import_module("services.viewer.routes")
    except ImportError:
        viewer = None
    if viewer is not None and hasattr(viewer, "router"):
        app.include_router(viewer.router)
    app.add_middleware(IgnoreOtherRanges)
    app.add_middleware(BodyLimit, upload_limit=settings.max_upload_bytes + (1 << 20), json_limit=settings.max_json_bytes)
    return app
