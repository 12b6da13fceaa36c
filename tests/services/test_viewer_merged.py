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
import time
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from fastapi import FastAPI, Header, HTTPException
from fastapi.responses import FileResponse

from services.viewer import routes
from tests.support.turntable_object import AXIS, write_cylinder_cloud, write_cylinder_glb
from tests.support.viewer_browser import Page, Server, built_viewer, chromium

pytestmark = pytest.mark.slow

KEY = "merged-key-5c1"
CENTRE = np.array([6.0, -5.0, 140.0])
SIZE = (480, 360)
BG = np.array([0.08, 0.09, 0.11]) * 255
#: The points' colours (top, bottom) and the derivatives' texture colours, told apart on screen.
POINTS = ((220, 30, 30), (30, 30, 220))
TEXTURE = ((220, 200, 40), (40, 200, 120))


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Server, list[str]]]:
    from shared.render.octree import build_tiles

    root = tmp_path_factory.mktemp("viewer-merged")
    write_cylinder_cloud(root / "merged.ply", CENTRE, *POINTS)
    job_dir = root / "job"
    build_tiles(root / "merged.ply", job_dir / "tiles", workers=1, max_leaf=8000)
    (job_dir / "registration.json").write_text(json.dumps(
        {"frame": "view 0 camera", "turntable_axis": {"direction": AXIS.tolist(), "point_mm": CENTRE.tolist()}}))
    for level, px in (("thumb", 16), ("low", 64), ("medium", 128)):
        write_cylinder_glb(job_dir / f"mesh_{level}.glb", CENTRE, *TEXTURE, texture_px=px)
    built_viewer()
    app = FastAPI()
    app.include_router(routes.create_router())
    log: list[str] = []

    @app.get("/v1/jobs/{job}/artifacts")
    def listing(job: str, authorization: str | None = Header(None)) -> dict:
        if authorization != f"Bearer {KEY}":
            raise HTTPException(401, "missing or wrong API key")
        arts = [{"name": f"tiles/{p.name}", "stage": "tiles"} for p in (job_dir / "tiles").iterdir()]
        arts.append({"name": "mv_merge/registration.json", "stage": "mv_merge"})
        if job == "textured":  # the derivatives stage's published files
            arts += [{"name": p.name, "stage": "derivatives", "size": p.stat().st_size} for p in job_dir.glob("mesh_*.glb")]
        return {"job": job, "name": "turntable", "artifacts": arts}

    @app.get("/v1/jobs/{job}/artifacts/{name:path}")
    def artifact(job: str, name: str, authorization: str | None = Header(None)) -> FileResponse:
        if authorization != f"Bearer {KEY}":
            raise HTTPException(401, "missing or wrong API key")
        log.append(name)
        path = (job_dir / name.removeprefix("mv_merge/")).resolve()
        if not path.is_relative_to(job_dir) or not path.is_file():
            raise HTTPException(404, f"{name} not found")
        return FileResponse(path)

    with Server(app) as server:
        yield server, log


def _halves(img: np.ndarray, top: tuple[int, int, int], bottom: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixels near each colour up to shading (the hue kept: the colour's direction in RGB)."""
    out = []
    for c in (top, bottom):
        c = np.asarray(c, float)
        v = img.astype(float)
        norm = np.linalg.norm(v, axis=2) + 1e-9
        out.append(((v @ (c / np.linalg.norm(c))) / norm > 0.985) & (norm > 60))
    return out[0], out[1]


def _check_upright_and_framed(img: np.ndarray, top, bottom) -> None:
    up_px, down_px = _halves(img, top, bottom)
    assert up_px.sum() > 1000 and down_px.sum() > 1000, (up_px.sum(), down_px.sum())
    assert np.nonzero(up_px)[0].mean() < np.nonzero(down_px)[0].mean() - 20, "the turntable's top is not up"
    obj = np.abs(img.astype(float) - BG).sum(axis=2) > 60
    rows, cols = np.nonzero(obj.any(axis=1))[0], np.nonzero(obj.any(axis=0))[0]
    # Framed: all of it inside the frame (no disc covering the screen), and not a speck.
    assert rows[0] > 2 and rows[-1] < SIZE[1] - 3 and cols[0] > 2 and cols[-1] < SIZE[0] - 3, (rows[[0, -1]], cols[[0, -1]])
    assert rows[-1] - rows[0] > 0.4 * SIZE[1] and obj.mean() < 0.6, (rows[-1] - rows[0], obj.mean())


def _open(server: Server, job: str, toggle: bool = False) -> tuple[list[dict], list[np.ndarray], list[str], float]:
    """States and frames of a job's page as it opens (and, with ``toggle``, with the mesh hidden),
    its console errors and the seconds it took to become idle."""
    with chromium() as browser:
        page = Page(browser, f"{server.url}/viewer/{job}?edl=0#key={KEY}", size=SIZE)
        try:
            t0 = time.perf_counter()
            states = [page.wait_idle()]
            seconds = time.perf_counter() - t0
            frames = [page.capture()]
            if toggle:
                states.append(page.set(mesh=False))
                frames.append(page.capture())
            return states, frames, list(page.errors), seconds
        finally:
            page.close()


def test_a_merged_job_opens_framed_with_the_turntable_axis_up(served) -> None:
    (state,), (img,), errors, _ = _open(served[0], "plain")
    cv2.imwrite("/tmp/graylight-viewer-merged.png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    assert errors == [] and state["error"] is None and state["notice"] is None, (errors, state)
    assert state["merged"] is not None and state["settings"]["grazing"] is False
    cam = state["camera"]
    assert cam["fov"] <= 60, cam  # not a field of view widened until a cloud around the origin fits
    up = np.asarray(state["up"], float)
    assert float(up @ -AXIS) / np.linalg.norm(up) > 0.999, up
    # The camera stands beside the object, not at the origin under it.
    eye = np.asarray(cam["position"], float)
    assert np.linalg.norm(eye) > 50 and abs(float((eye - CENTRE) @ -AXIS)) < np.linalg.norm(eye - CENTRE) * 0.5
    _check_upright_and_framed(img, *POINTS)


def test_a_job_with_derivatives_opens_on_the_textured_low_level_and_the_points_are_one_toggle_away(served) -> None:
    server, log = served
    (state, points_state), (mesh_img, points_img), errors, seconds = _open(server, "textured", toggle=True)
    cv2.imwrite("/tmp/graylight-viewer-textured.png", cv2.cvtColor(mesh_img, cv2.COLOR_RGB2BGR))
    cv2.imwrite("/tmp/graylight-viewer-textured-points.png", cv2.cvtColor(points_img, cv2.COLOR_RGB2BGR))
    assert errors == [] and state["error"] is None and state["notice"] is None, (errors, state)
    mesh = state["mesh"]
    # Low, Medium (finest first); Thumb left out; Low loaded first and, at this size, kept.
    assert [lv["name"] for lv in mesh["levels"]] == ["mesh_medium.glb", "mesh_low.glb"], mesh["levels"]
    assert mesh["shown"] and mesh["drawn"] == "mesh_low.glb", mesh
    assert [n for n in log if n.endswith(".glb")][0] == "mesh_low.glb", log
    _check_upright_and_framed(mesh_img, *TEXTURE)  # drawn by its texture: the points' colours are others
    assert _halves(mesh_img, *POINTS)[0].sum() < 50
    assert points_state["mesh"]["shown"] is False
    _check_upright_and_framed(points_img, *POINTS)
    print(f"textured job page idle in {seconds:.1f} s")
