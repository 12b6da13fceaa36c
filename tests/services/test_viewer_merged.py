"""A merged cloud in the web viewer (services/viewer/src/main.ts, ``Viewer.setMerged``): it has no
single scanner position, so the viewer neither starts at the origin (view 0's camera) nor widens
splats by a scanner's incidence angle; it frames the object with the turntable axis up.

The cloud is a tilted cylinder's surface in a merge's frame (view 0's camera, y down), close to
the origin as a turntable object is to view 0's camera, so that a scan's rule (start where the
scanner stood, widen the field of view until the cloud fits) would open it from below with a
wide lens: its top half (away from the table) red, its bottom half blue. The job's artifact list
holds the merge's ``registration.json`` with the turntable axis, as a multi-view job's does.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi import FastAPI, Header, HTTPException
from fastapi.responses import FileResponse

from services.viewer import routes
from shared.formats.ply import write_ply
from tests.support.viewer_browser import Page, Server, built_viewer, chromium

pytestmark = pytest.mark.slow

KEY = "merged-key-5c1"
#: The turntable axis as registration.json gives it (down the image and a little away, the bunny's).
AXIS = np.array([0.0, 0.9445, 0.3284]) / np.linalg.norm([0.0, 0.9445, 0.3284])
CENTRE = np.array([6.0, -5.0, 140.0])
RADIUS, HEIGHT = 30.0, 90.0
SIZE = (480, 360)
BG = np.array([0.08, 0.09, 0.11]) * 255


def _merged_cloud(path: Path, n: int = 120_000) -> None:
    rng = np.random.default_rng(3)
    ang = rng.uniform(0, 2 * np.pi, n)
    h = rng.uniform(-HEIGHT / 2, HEIGHT / 2, n)
    up = -AXIS
    x = np.cross(up, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    radial = np.cos(ang)[:, None] * x + np.sin(ang)[:, None] * y
    xyz = CENTRE + RADIUS * radial + h[:, None] * up
    colour = np.where((h > 0)[:, None], [[220, 30, 30]], [[30, 30, 220]]).astype(np.uint8)
    # Splat sizes as a merge writes them: the sample spacing, not a scanner's depth ratio.
    write_ply(path, xyz.astype(np.float32), colour, radial.astype(np.float32), np.full(n, 0.9, np.float32))


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    from shared.render.octree import build_tiles

    root = tmp_path_factory.mktemp("viewer-merged")
    _merged_cloud(root / "merged.ply")
    build_tiles(root / "merged.ply", root / "job" / "tiles", workers=1, max_leaf=8000)
    (root / "job" / "registration.json").write_text(json.dumps(
        {"frame": "view 0 camera", "turntable_axis": {"direction": AXIS.tolist(), "point_mm": CENTRE.tolist()}}))
    built_viewer()
    app = FastAPI()
    app.include_router(routes.create_router())
    job_dir = root / "job"

    @app.get("/v1/jobs/{job}/artifacts")
    def listing(job: str, authorization: str | None = Header(None)) -> dict:
        if authorization != f"Bearer {KEY}":
            raise HTTPException(401, "missing or wrong API key")
        arts = [{"name": f"tiles/{p.name}", "stage": "tiles"} for p in (job_dir / "tiles").iterdir()]
        return {"job": job, "name": "turntable", "artifacts": [*arts, {"name": "mv_merge/registration.json",
                                                                        "stage": "mv_merge"}]}  # fmt: skip

    @app.get("/v1/jobs/{job}/artifacts/{name:path}")
    def artifact(job: str, name: str, authorization: str | None = Header(None)) -> FileResponse:
        if authorization != f"Bearer {KEY}":
            raise HTTPException(401, "missing or wrong API key")
        path = (job_dir / name.removeprefix("mv_merge/")).resolve()
        if not path.is_relative_to(job_dir) or not path.is_file():
            raise HTTPException(404, f"{name} not found")
        return FileResponse(path)

    with Server(app) as server:
        yield server


def test_a_merged_job_opens_framed_with_the_turntable_axis_up(served: Server, tmp_path: Path) -> None:
    with chromium() as browser:
        page = Page(browser, f"{served.url}/viewer/job1?edl=0#key={KEY}", size=SIZE)
        try:
            state = page.wait_idle()
            img = page.capture()
            errors = list(page.errors)
        finally:
            page.close()
    out = Path("/tmp/graylight-viewer-merged.png")
    cv2.imwrite(str(out), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    assert errors == [] and state["error"] is None and state["notice"] is None, (errors, state)
    assert state["merged"] is not None and state["settings"]["grazing"] is False
    cam = state["camera"]
    assert cam["fov"] <= 60, cam  # not a field of view widened until a cloud around the origin fits
    up = np.asarray(state["up"], float)
    assert float(up @ -AXIS) / np.linalg.norm(up) > 0.999, up
    # The camera stands beside the object, not at the origin under it.
    eye = np.asarray(cam["position"], float)
    assert np.linalg.norm(eye) > 50 and abs(float((eye - CENTRE) @ -AXIS)) < np.linalg.norm(eye - CENTRE) * 0.5
    red = (img[..., 0] > 120) & (img[..., 2] < 100)
    blue = (img[..., 2] > 120) & (img[..., 0] < 100)
    assert red.sum() > 1000 and blue.sum() > 1000, (red.sum(), blue.sum())
    assert np.nonzero(red)[0].mean() < np.nonzero(blue)[0].mean() - 20, "the turntable's top is not up"
    obj = np.abs(img.astype(float) - BG).sum(axis=2) > 60
    rows, cols = np.nonzero(obj.any(axis=1))[0], np.nonzero(obj.any(axis=0))[0]
    # Framed: all of it inside the frame (no disc covering the screen), and not a speck.
    assert rows[0] > 2 and rows[-1] < SIZE[1] - 3 and cols[0] > 2 and cols[-1] < SIZE[0] - 3, (rows[[0, -1]], cols[[0, -1]])
    assert rows[-1] - rows[0] > 0.4 * SIZE[1] and obj.mean() < 0.6, (rows[-1] - rows[0], obj.mean())
