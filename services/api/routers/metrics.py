"""``GET /metrics``: the service's Prometheus metrics (:mod:`shared.service.metrics`), without
a key (Prometheus scrapes it; it shows counts and sizes, no names or ids). Not part of the
OpenAPI document: it is for the operator's scraper, not for API clients."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from services.api.deps import Svc

router = APIRouter(tags=["service"])


@router.get("/metrics", include_in_schema=False)
def metrics(svc: Svc) -> Response:
    """Jobs by kind and state, stage durations, queue depths, store bytes, reconciler repairs."""
    return Response(generate_latest(svc.metrics), media_type=CONTENT_TYPE_LATEST)
