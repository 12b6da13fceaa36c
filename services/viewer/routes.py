"""HTTP routes of the web viewer: the page at ``/viewer/{job}`` and its static assets.

The API service includes :data:`router`. The page for a job loads that job's Potree 2.0 tiles
from the URL made by ``tiles_url_template`` (default ``/v1/jobs/{job}/artifacts/tiles/``,
under the app's root path); the browser sends the API key it was given in the page URL's
fragment (``/viewer/{job}#key=...``), the ``key`` query parameter or the ``graylight_key``
cookie as ``Authorization: Bearer`` to that same-origin URL, and lists the job's artifacts
(``artifacts_url_template``) for a ``mesh.glb`` to offer and the job's ``name`` to title the page. ``/viewer/?tiles=URL`` shows any
tiles folder (``&mesh=URL`` a mesh with it). Assets come from ``services/viewer/dist``
(``make viewer`` builds them with npm).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse

#: Where ``npm run build`` writes the page and its assets.
VIEWER_DIST = Path(__file__).resolve().parent / "dist"
#: Where the API serves a job's tiles folder; ``{job}`` is replaced by the job id.
TILES_URL_TEMPLATE = "/v1/jobs/{job}/artifacts/tiles/"
#: Where the API lists a job's artifacts (the viewer looks there for ``mesh.glb``, ``mesh_lod*.glb``).
ARTIFACTS_URL_TEMPLATE = "/v1/jobs/{job}/artifacts"
#: Marker in ``index.html`` replaced by the page configuration.
CONFIG_MARKER = "<!--graylight-config-->"

_JOB_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
_MEDIA_TYPES = {
    ".js": "text/javascript",
    ".css": "text/css",
    ".map": "application/json",
    ".html": "text/html",
}


def _config_script(config: dict[str, str]) -> str:
    # Escape "<" so no value can close the script element.
    text = json.dumps(config).replace("<", "\\u003c")
    return f'<script id="graylight-config" type="application/json">{text}</script>'


def render_page(dist: Path, config: dict[str, str] | None = None) -> str:
    """The viewer page with ``config`` (``tiles``, ``job``, ``artifacts``) embedded for the page's script.

    Raises HTTP 503 when the assets have not been built.
    """
    index = dist / "index.html"
    if not index.is_file():
        raise HTTPException(503, f"viewer assets not built: {index} is missing (run `make viewer`)")
    html = index.read_text(encoding="utf-8")
    return html.replace(CONFIG_MARKER, _config_script(config) if config else "", 1)


def create_router(dist: Path = VIEWER_DIST, tiles_url_template: str = TILES_URL_TEMPLATE,
                  artifacts_url_template: str = ARTIFACTS_URL_TEMPLATE) -> APIRouter:
    """Routes serving the viewer from ``dist``, pointing job pages at ``tiles_url_template``
    and ``artifacts_url_template`` (whose ``name``, the job's, titles the page)."""
    router = APIRouter(tags=["viewer"])
    assets = (dist / "assets").resolve()

    @router.get("/viewer", include_in_schema=False)
    def viewer_redirect(request: Request) -> RedirectResponse:
        # Relative asset URLs in the page need the trailing slash.
        query = f"?{request.url.query}" if request.url.query else ""
        return RedirectResponse(f"{request.scope.get('root_path', '')}/viewer/{query}", status_code=307)

    #: What the pages can answer besides 200 (the API's OpenAPI document lists them).
    errors = {503: {"description": "viewer assets not built"}}
    not_found = {404: {"description": "not a job id"}}

    @router.get("/viewer/", response_class=HTMLResponse, summary="Viewer for any tiles URL (?tiles=URL)",
                responses=errors)
    def viewer_any() -> HTMLResponse:
        return HTMLResponse(render_page(dist), headers={"Cache-Control": "no-cache"})

    @router.get("/viewer/assets/{name:path}", include_in_schema=False)
    def viewer_asset(name: str) -> FileResponse:
        path = (assets / name).resolve()
        if not path.is_relative_to(assets) or not path.is_file():
            raise HTTPException(404, f"viewer asset {name!r} not found")
        return FileResponse(path, media_type=_MEDIA_TYPES.get(path.suffix, "application/octet-stream"))

    @router.get("/viewer/{job}", response_class=HTMLResponse, summary="Fly through a finished job's scan",
                responses={**not_found, **errors})
    def viewer_job(job: str, request: Request) -> HTMLResponse:
        if not _JOB_ID.match(job):
            raise HTTPException(404, f"job id {job!r} is not valid")
        root = request.scope.get("root_path", "")
        config = {"tiles": root + tiles_url_template.format(job=job), "job": job,
                  "artifacts": root + artifacts_url_template.format(job=job)}  # fmt: skip
        return HTMLResponse(render_page(dist, config), headers={"Cache-Control": "no-cache"})

    return router


#: The router the API service includes.
router = create_router()
