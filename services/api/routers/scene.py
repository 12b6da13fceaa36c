"""A job's published scene for Smithsonian Voyager Explorer on any origin.

``GET /v1/jobs/{id}/scene`` (with the key, as every job route) answers where the scene folder is:
``/v1/jobs/{id}/scene/{token}/``, whose ``scene.svx.json`` and derivatives (the publish stage's
files) are served to anyone holding the URL until the token expires (shared.service.scene_tokens:
Voyager sends no Authorization header, so the grant is in the path), with CORS headers so a
viewer on another origin may read them. A wrong, foreign or expired token is a 403.
"""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import Response
from pydantic import BaseModel

from services.api.deps import Key, Svc, owned_job
from services.api.models import errors
from services.api.routers.artifacts import send_artifact
from shared.service.jobs import StageState
from shared.service.jobstore import Job
from shared.service.scene_tokens import (
    MAX_TOKEN_SECONDS,
    MIN_TOKEN_SECONDS,
    TokenError,
    check_scene_token,
    sign_scene_token,
)

router = APIRouter(tags=["scene"])

#: The publish stage's scene document, the file Voyager opens first.
SCENE_DOCUMENT = "scene.svx.json"
#: A token's life when the caller does not ask (a working day).
DEFAULT_TOKEN_SECONDS = 8 * 3600
#: Sent with every file and error of the token routes: any origin may read them (the token is the
#: grant; no cookie is involved, so credentials stay off).
CORS_HEADERS = {
    "Access-Control-Allow-Origin": "*",
    "Access-Control-Expose-Headers": "Content-Length, Content-Range, Accept-Ranges, ETag",
    "Vary": "Origin",
}


class SceneLink(BaseModel):
    """Where a job's scene folder is served, and until when."""

    job: str
    root: str  # the folder's absolute URL, ending in "/" (Voyager's ``root``)
    document: str  # the scene file in it (Voyager's ``document``)
    url: str  # root + document
    expires: int  # Unix time (s) the token stops working
    files: list[str]  # every file served under root


def _publish_files(svc: Svc, job: Job) -> tuple[str, dict]:
    st = next((s for s in job.stages if s.name == "publish"), None)
    m = svc.arts.manifest(st.output_key) if st is not None and st.state == StageState.SUCCEEDED and st.output_key \
        else None
    if m is None:
        return "", {}
    return st.output_key, {n: e for n, e in m.files.items() if not n.startswith(".") and "/" not in n}


@router.get("/v1/jobs/{job_id}/scene", response_model=SceneLink, responses=errors(401, 404, 422))
def scene_link(job_id: str, key: Key, svc: Svc, request: Request,
               seconds: Annotated[int, Query(ge=MIN_TOKEN_SECONDS, le=MAX_TOKEN_SECONDS,
                                             description="how long the link works")] = DEFAULT_TOKEN_SECONDS,
               ) -> SceneLink:
    """A link to the job's published scene folder that Voyager Explorer opens from any origin
    (``?root=ROOT&document=scene.svx.json``); 404 until the publish stage has succeeded."""
    job = owned_job(svc, job_id, key)
    _okey, files = _publish_files(svc, job)
    if SCENE_DOCUMENT not in files:
        raise HTTPException(404, f"job {job.id} has no published scene (yet)")
    expires = int(time.time()) + seconds
    token = sign_scene_token(svc.settings.signing_secret(), job.id, job.owner_id, expires)
    root = f"{str(request.base_url).rstrip('/')}/v1/jobs/{job.id}/scene/{token}/"
    return SceneLink(job=job.id, root=root, document=SCENE_DOCUMENT, url=root + SCENE_DOCUMENT, expires=expires,
                     files=sorted(files))


def _granted(svc: Svc, job_id: str, token: str) -> Job:
    """The job the token grants, or a 403 (the same for an unknown job, so ids cannot be probed)."""
    job = svc.store.get_job(job_id)
    try:
        if job is None:
            raise TokenError("scene token is not valid for this job")
        check_scene_token(svc.settings.signing_secret(), token, job.id, job.owner_id, time.time())
        if not svc.store.key_active(job.owner_id):
            raise TokenError("scene token's key has been revoked")
    except TokenError as exc:
        raise HTTPException(403, str(exc), headers=CORS_HEADERS) from None
    return job


@router.options("/v1/jobs/{job_id}/scene/{token}/{name:path}", include_in_schema=False)
def scene_preflight() -> Response:
    # A viewer asking for a byte range sends a preflight; the answer names what it may send.
    return Response(status_code=204, headers={**CORS_HEADERS, "Access-Control-Allow-Methods": "GET, HEAD, OPTIONS",
                                              "Access-Control-Allow-Headers": "Range", "Access-Control-Max-Age": "600"})


@router.get("/v1/jobs/{job_id}/scene/{token}/{name:path}", responses=errors(403, 404, 416))
def scene_file(job_id: str, token: str, name: str, svc: Svc, request: Request) -> Response:
    """A file of the job's scene folder (``scene.svx.json``, a derivative GLB, ``qa.html``), for
    whoever holds a link from ``GET /v1/jobs/{id}/scene``; with CORS headers."""
    job = _granted(svc, job_id, token)
    okey, files = _publish_files(svc, job)
    entry = files.get(name or SCENE_DOCUMENT)
    if entry is None:
        raise HTTPException(404, f"the scene of job {job.id} has no file {name!r}", headers=CORS_HEADERS)
    headers = {**CORS_HEADERS, "Cache-Control": "private, max-age=300"}
    return send_artifact(svc.arts, okey, name or SCENE_DOCUMENT, entry.size, entry.sha256, request, headers)
