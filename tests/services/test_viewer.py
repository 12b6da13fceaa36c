"""Web viewer (services/viewer): routes, and the page in a real headless Chromium.

The browser tests build Potree 2.0 tiles with ``shared.render.octree.build_tiles`` from synthetic
scans (analytic scenes ray-cast from a virtual scanner, so every point carries the scanner's
world sample size Z / f), serve them with the viewer's routes from a real uvicorn server on
127.0.0.1 and drive Debian's Chromium through Playwright (WebGL2 on SwiftShader).

The hole test quantifies the seed's Figures 2.1 and 2.2: a dense planar wall seen from close
by, the share of background pixels inside the wall's projected silhouette with seed splat
sizing against static 1-px splats.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi import FastAPI, Header, HTTPException
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi.testclient import TestClient

from services.viewer import routes
from shared.formats.ply import write_ply
from tests.support.viewer_browser import Page as BrowserPage
from tests.support.viewer_browser import Server, built_viewer, chromium

pytestmark = pytest.mark.xdist_group("viewer")

API_KEY = "test-key-6f1c"
VIEW_W, VIEW_H = 640, 480


# --------------------------------------------------------------------------- synthetic scans


def scan_rays(width: int, height: int, focal: float) -> np.ndarray:
    """Unit ray directions (H*W, 3) of a pinhole scanner at the origin (x right, y down, z forward)."""
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    d = np.stack([u / focal, v / focal, np.ones_like(u)], axis=-1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def scan_scene(path: Path, width: int = 240, height: int = 180, focal: float = 280.0) -> int:
    """A scan of a red and a green sphere before a blue-grey back wall; returns the point count."""
    rays = scan_rays(width, height, focal)
    t_best = np.full(len(rays), np.inf)
    colour = np.zeros((len(rays), 3), np.uint8)
    normal = np.zeros((len(rays), 3), np.float32)
    # Back wall z = 1000 mm.
    t_wall = 1000.0 / rays[:, 2]
    t_best[:] = t_wall
    colour[:] = (70, 90, 160)
    normal[:] = (0, 0, -1)
    for centre, radius, rgb in (((-60.0, 20.0, 700.0), 160.0, (220, 40, 40)), ((190.0, -90.0, 820.0), 110.0, (40, 200, 60))):
        c = np.array(centre)
        b = rays @ c
        disc = b * b - (c @ c - radius * radius)
        hit = disc > 0
        t = np.where(hit, b - np.sqrt(np.where(hit, disc, 0)), np.inf)
        closer = t < t_best
        t_best[closer] = t[closer]
        colour[closer] = rgb
        p = rays[closer] * t[closer, None]
        normal[closer] = (p - c) / radius
    xyz = (rays * t_best[:, None]).astype(np.float32)
    size = (xyz[:, 2] / focal).astype(np.float32)
    write_ply(path, xyz, colour, normal, size)
    return len(xyz)


#: Wall scan geometry (mm): a scanner with focal length WALL_F pixels at the origin sees the
#: plane z = WALL_Z over WALL_HALF (half extents), so samples are WALL_Z / WALL_F apart.
WALL_F = 1000.0
WALL_Z = 300.0
WALL_HALF = (24.0, 18.0)


def scan_wall(path: Path) -> int:
    step = WALL_Z / WALL_F
    xs = np.arange(-WALL_HALF[0], WALL_HALF[0] + 1e-9, step)
    ys = np.arange(-WALL_HALF[1], WALL_HALF[1] + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys)
    xyz = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, WALL_Z)], axis=1).astype(np.float32)
    # A red and blue checkerboard of samples: plain splats show one or the other in each pixel,
    # weighted blending mixes overlapping neighbours.
    checker = ((np.arange(len(ys))[:, None] + np.arange(len(xs))[None, :]) % 2).ravel().astype(bool)
    rgb = np.where(checker[:, None], np.array([[225, 30, 30]], np.uint8), np.array([[30, 30, 225]], np.uint8))
    normals = np.tile(np.array([[0, 0, -1]], np.float32), (len(xyz), 1))
    size = (xyz[:, 2] / WALL_F).astype(np.float32)
    write_ply(path, xyz, rgb, normals, size)
    return len(xyz)


def scan_blob(path: Path) -> int:
    """A small dense ball far inside a large cube (two outliers): a deep octree with hierarchy proxies."""
    rng = np.random.default_rng(7)
    d = rng.normal(size=(20_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    xyz = np.vstack([d * 2.0 + (0.0, 0.0, 500.0), [[-300, -300, 300], [300, 300, 900]]]).astype(np.float32)
    rgb = (np.abs(np.vstack([d, [[1, 1, 1], [1, 1, 1]]])) * 255).astype(np.uint8)
    write_ply(path, xyz, rgb, size=np.full(len(xyz), 0.02, np.float32))
    return len(xyz)


def project(points: np.ndarray, eye: np.ndarray, target: np.ndarray, fov_deg: float) -> np.ndarray:
    """Pixel coordinates (N, 2) of world points for the viewer's camera (up = -y, lookAt)."""
    up = np.array([0.0, -1.0, 0.0])
    z_axis = (eye - target) / np.linalg.norm(eye - target)
    x_axis = np.cross(up, z_axis)
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    rel = points - eye
    xc, yc, zc = rel @ x_axis, rel @ y_axis, rel @ z_axis
    f = VIEW_H / 2 / np.tan(np.radians(fov_deg) / 2)
    return np.stack([VIEW_W / 2 + f * xc / -zc, VIEW_H / 2 - f * yc / -zc], axis=1)


# --------------------------------------------------------------------------- server and browser


@pytest.fixture(scope="module")
def viewer_dist() -> Path:
    return built_viewer()


def make_app(tiles_root: Path, requests_log: list[tuple[str, str | None, str | None]]) -> FastAPI:
    """The viewer routes, a job-service-like tiles endpoint behind a Bearer key, and static files."""
    app = FastAPI()
    app.include_router(routes.create_router())

    @app.get("/v1/jobs/{job}/artifacts/tiles/{name}")
    def job_tiles(
        job: str, name: str, authorization: str | None = Header(None), range_: str | None = Header(None, alias="range")
    ) -> FileResponse:
        requests_log.append((name, authorization, range_))
        if authorization != f"Bearer {API_KEY}":
            raise HTTPException(401, "missing or wrong API key")
        path = tiles_root / job / name
        if name not in ("metadata.json", "hierarchy.bin", "octree.bin") or not path.is_file():
            raise HTTPException(404, f"{name} not found")
        return FileResponse(path)

    @app.get("/v1/jobs/{job}/artifacts")
    def job_artifacts(job: str, authorization: str | None = Header(None)) -> dict:
        # The job page lists the artifacts for a mesh to offer; these jobs have tiles only.
        if authorization != f"Bearer {API_KEY}":
            raise HTTPException(401, "missing or wrong API key")
        files = sorted((tiles_root / job).glob("*")) if (tiles_root / job).is_dir() else []
        return {"job": job, "artifacts": [{"name": f"tiles/{p.name}", "stage": "tiles", "size": p.stat().st_size} for p in files]}

    @app.get("/whole/{folder}/{name}")
    def whole_file(folder: str, name: str) -> Response:
        # Like a store that cannot serve byte ranges: the whole file, status 200, every time.
        requests_log.append((f"whole/{name}", None, None))
        path = tiles_root / folder / name
        if not path.is_file():
            raise HTTPException(404, f"{name} not found")
        return Response(path.read_bytes(), media_type="application/octet-stream")

    app.mount("/static", StaticFiles(directory=tiles_root), name="static")
    return app


@pytest.fixture(scope="module")
def tiles_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder the test server serves; tile sets are built into it on demand by ``build``."""
    return tmp_path_factory.mktemp("viewer-tiles")


def scan_bare(path: Path) -> int:
    """:func:`scan_scene`'s points with nothing but x, y, z (a cloud another scanner made)."""
    from shared.formats.ply import read_ply

    n = scan_scene(path)
    write_ply(path, read_ply(path).xyz)
    return n


#: Tile sets the tests use: folder name -> (synthetic scan writer, max points per leaf).
TILE_SETS = {"job-scene": (scan_scene, 4000), "wall": (scan_wall, 4000), "blob": (scan_blob, 1000),
             "bare": (scan_bare, 4000)}  # fmt: skip


@pytest.fixture(scope="module")
def build(tiles_root: Path) -> Callable[[str], Path]:
    """Build a tile set of :data:`TILE_SETS` once per test process (workers only build what they run)."""
    from shared.render.octree import build_tiles

    def make(name: str) -> Path:
        out = tiles_root / name
        if not out.is_dir():
            writer, max_leaf = TILE_SETS[name]
            writer(tiles_root / f"{name}.ply")
            build_tiles(tiles_root / f"{name}.ply", out, workers=1, max_leaf=max_leaf)
        return out

    return make


@pytest.fixture(scope="module")
def served(tiles_root: Path, viewer_dist: Path) -> Iterator[tuple[Server, list]]:
    log: list[tuple[str, str | None, str | None]] = []
    with Server(make_app(tiles_root, log)) as server:
        yield server, log


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with chromium() as b:
        yield b


class Page(BrowserPage):
    """A viewer page at this module's viewport size."""

    def __init__(self, browser, url: str, size: tuple[int, int] = (VIEW_W, VIEW_H)) -> None:
        super().__init__(browser, url, size)


# --------------------------------------------------------------------------- tests


def test_routes_serve_page_assets_and_job_config(viewer_dist: Path) -> None:
    app = FastAPI()
    app.include_router(routes.create_router(tiles_url_template="/api/jobs/{job}/tiles/"))
    client = TestClient(app)
    page = client.get("/viewer/job-42")
    assert page.status_code == 200
    assert '"tiles": "/api/jobs/job-42/tiles/"' in page.text and '"job": "job-42"' in page.text
    assert 'src="assets/viewer.js"' in page.text
    any_page = client.get("/viewer/")
    assert any_page.status_code == 200
    assert 'id="graylight-config"' not in any_page.text
    js = client.get("/viewer/assets/viewer.js")
    assert js.status_code == 200 and js.headers["content-type"].startswith("text/javascript") and len(js.content) > 1000
    assert client.get("/viewer/assets/..%2F..%2Froutes.py").status_code == 404
    assert client.get("/viewer/assets/nothing.js").status_code == 404
    assert client.get("/viewer/bad%20id%3Cscript%3E").status_code == 404
    redirect = client.get("/viewer?tiles=/x/", follow_redirects=False)
    assert redirect.status_code == 307 and redirect.headers["location"] == "/viewer/?tiles=/x/"


def test_routes_without_built_assets_say_how_to_build(tmp_path: Path) -> None:
    app = FastAPI()
    app.include_router(routes.create_router(dist=tmp_path / "dist"))
    response = TestClient(app).get("/viewer/job1")
    assert response.status_code == 503 and "make viewer" in response.text


@pytest.mark.slow
def test_page_loads_job_tiles_and_renders(served, browser, build) -> None:
    server, log = served
    from shared.formats.potree import open_tiles

    tiles = open_tiles(build("job-scene"))
    total = tiles.points
    # A budget below the cloud's size (the root node is always drawn): the viewer stops there.
    budget = (tiles.nodes["r"].num_points + total) // 2
    assert budget < total
    url = f"{server.url}/viewer/job-scene?budget={budget}&edl=0&grazing=0#key={API_KEY}"
    page = Page(browser, url, size=(480, 360))
    try:
        state = page.wait_idle()
        assert state["error"] is None, state["error"]
        assert state["hasSize"] and state["hasColor"]
        assert state["decoderWorkers"] == 2  # nodes decode off the main thread
        assert 0 < state["drawnPoints"] <= budget
        assert state["loadedNodes"] >= 2
        # The API key went to the tiles endpoint as a Bearer header, and nodes came by Range requests.
        assert log and all(auth == f"Bearer {API_KEY}" for _, auth, _ in log)
        assert any(name == "octree.bin" and rng and rng.startswith("bytes=") for name, _, rng in log)
        img_budget = page.capture()

        # Whole cloud under a large budget: every point drawn exactly once (additive octree).
        state = page.set(budget=10 * total)
        assert state["drawnPoints"] == total
        img = page.capture()
        bg = np.array([0.08, 0.09, 0.11]) * 255
        fg = np.abs(img.astype(float) - bg).sum(axis=2) > 30
        # The first view is the scanner's own, framing the scan (the scanner saw 36 degrees
        # vertically; the view is centred on the scan's box, so it needs a little more).
        assert state["camera"]["position"] == [0, 0, 0]
        assert 2 * np.degrees(np.arctan(90 / 280)) <= state["camera"]["fov"] < 50
        assert fg.mean() > 0.75, f"only {fg.mean():.1%} of the frame shows points"
        r, g, b = (img[..., i].astype(int) for i in range(3))
        red = (r > 150) & (g < 90) & (b < 90)
        green = (g > 140) & (r < 90) & (b < 110)
        wall = (b > 120) & (r < 110) & (b > r + 40)
        for name, mask in (("red sphere", red), ("green sphere", green), ("blue wall", wall)):
            assert mask.mean() > 0.02, f"{name} covers only {mask.mean():.2%} of the frame"
        # The red sphere is nearer the scanner's left: its pixels lie left of the green ones.
        assert np.nonzero(red)[1].mean() < np.nonzero(green)[1].mean()
        assert (np.abs(img.astype(int) - img_budget.astype(int)).sum(axis=2) > 0).mean() > 0.001

        # Eye-dome lighting only darkens, and darkens the spheres' rims against the wall.
        page.set(edl=True)
        img_edl = page.capture()
        diff = img.astype(int) - img_edl.astype(int)
        assert diff.min() >= -2 and (diff.sum(axis=2) > 30).mean() > 0.002

        # High-quality blending keeps the same scene (colour classes in place).
        page.set(edl=False, hq=True)
        img_hq = page.capture()
        rh, gh, bh = (img_hq[..., i].astype(int) for i in range(3))
        red_hq = (rh > 150) & (gh < 90) & (bh < 90)
        assert (red_hq & red).sum() > 0.9 * red.sum()

        # Seen from the side, the spheres' rims were sampled at grazing angles: the seed's size
        # (across the scanner's ray) leaves gaps there that widening by 1 / cos(incidence) closes.
        page.page.evaluate("() => window.graylight.lookAt([-400, -300, 200], [0, 0, 750])")
        red_share = {}
        for grazing in (False, True):
            page.set(hq=False, grazing=grazing)
            side = page.capture().astype(int)
            red_share[grazing] = ((side[..., 0] > 120) & (side[..., 1] < 80) & (side[..., 2] < 80)).mean()
        assert red_share[True] > 1.05 * red_share[False], red_share

        # Fly-through: W moves the eye along the view direction, dragging the mouse turns it.
        before = page.page.evaluate("() => window.graylight.state().camera")
        page.page.locator("#view").focus()
        page.page.keyboard.down("w")
        page.page.wait_for_timeout(300)
        page.page.keyboard.up("w")
        after = page.page.evaluate("() => window.graylight.state().camera")
        step = np.subtract(after["position"], before["position"])
        assert np.linalg.norm(step) > 0 and np.dot(step, before["forward"]) > 0.99 * np.linalg.norm(step)
        page.page.mouse.move(400, 180)
        page.page.mouse.down()
        page.page.mouse.move(460, 180, steps=4)
        page.page.mouse.up()
        turned = page.page.evaluate("() => window.graylight.state().camera")
        assert np.dot(turned["forward"], after["forward"]) < 0.999
        assert turned["position"] == after["position"]

        # The panel's controls drive the settings.
        page.page.locator("#budget").fill("5")
        page.page.locator("#fov").fill("75")
        page.page.locator("#hq").check()
        page.page.locator("#mode").select_option("orbit")
        settings = page.page.evaluate("() => window.graylight.state()")
        assert settings["settings"]["budget"] == 100_000 and settings["settings"]["fov"] == 75
        assert settings["settings"]["hq"] is True and settings["camera"]["mode"] == "orbit"
        assert page.errors == [], page.errors
    finally:
        page.close()

    # A wrong key: the page says what failed instead of drawing nothing silently.
    page = Page(browser, f"{server.url}/viewer/job-scene#key=wrong")
    try:
        state = page.wait_idle()
        assert state["error"] and "401" in state["error"] and "metadata.json" in state["error"]
        assert page.page.locator("#error").is_visible()
    finally:
        page.close()


@pytest.mark.slow
def test_seed_sizing_closes_holes_on_a_close_wall(served, browser, build) -> None:
    server, _ = served
    build("wall")
    eye = np.array([6.0, -4.0, WALL_Z - 38.0])
    target = np.array([0.0, 0.0, WALL_Z])
    fov = 60.0
    corners = np.array([[sx * WALL_HALF[0], sy * WALL_HALF[1], WALL_Z] for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    poly = project(corners, eye, target, fov)
    assert poly.min() > 0 and poly[:, 0].max() < VIEW_W and poly[:, 1].max() < VIEW_H  # silhouette in view
    silhouette = np.zeros((VIEW_H, VIEW_W), np.uint8)
    cv2.fillConvexPoly(silhouette, np.round(poly * 16).astype(np.int32), 1, shift=4)
    inside = cv2.erode(silhouette, np.ones((7, 7), np.uint8)).astype(bool)  # 3 px margin
    pos = ",".join(map(str, eye))
    look = ",".join(map(str, target))
    url = f"{server.url}/viewer/?tiles=/static/wall/&ui=0&edl=0&bg=000000&fov={fov}&pos={pos}&look={look}"
    page = Page(browser, url)
    try:
        holes: dict[str, float] = {}
        mixed: dict[str, float] = {}
        state = page.wait_idle()
        assert state["error"] is None, state["error"]
        assert state["drawnPoints"] == state["totalPoints"]
        for label, settings in (
            ("seed sizing", {"sizing": "seed", "hq": False, "grazing": False}),
            ("seed sizing, high quality", {"sizing": "seed", "hq": True, "grazing": False}),
            ("seed sizing, discs 1 sample wide", {"sizing": "seed", "splatScale": 1.0, "hq": False, "grazing": False}),
            ("static 1-px splats", {"sizing": "fixed", "fixedPx": 1, "splatScale": 1.5, "hq": False}),
        ):
            page.set(**settings)
            img = page.capture()
            background = img.max(axis=2) < 40
            if settings["sizing"] == "fixed":
                # Each 1-px splat lights exactly its own pixel: every point of the wall arrived.
                assert (~background).sum() == state["totalPoints"]
            holes[label] = float(background[inside].mean())
            r, b = img[..., 0].astype(int), img[..., 2].astype(int)
            mixed[label] = float(((r > 70) & (b > 70))[inside].mean())
            # Outside the silhouette (beyond the splats' reach) the background must stay.
            far_out = ~cv2.dilate(silhouette, np.ones((25, 25), np.uint8)).astype(bool)
            assert background[far_out].mean() > 0.99
        spacing_px = (WALL_Z / WALL_F) * (VIEW_H / 2 / np.tan(np.radians(fov) / 2)) / np.linalg.norm(target - eye)
        print(f"\nwall inside its silhouette ({inside.sum()} px, samples {spacing_px:.1f} px apart):")
        print(f"  {'':34s} {'holes':>8s} {'blended':>8s}")
        for label, share in holes.items():
            print(f"  {label:34s} {share:8.2%} {mixed[label]:8.2%}")
        assert holes["seed sizing"] < 0.01
        assert holes["seed sizing, high quality"] < 0.01
        assert holes["static 1-px splats"] > 0.5  # the seed's Figure 2.1: the wall falls apart
        # Round discs exactly one sample wide leave the grid's corners open (ideally 1 - pi/4).
        assert holes["seed sizing, discs 1 sample wide"] > 0.05
        # High quality blends overlapping red and blue splats (c = sum w c / sum w); plain splats do not.
        assert mixed["seed sizing, high quality"] > 0.3 and mixed["seed sizing"] < 0.05
        assert page.errors == [], page.errors
    finally:
        page.close()


@pytest.mark.slow
def test_deep_hierarchy_with_proxy_chunks_loads_every_node_without_ranges(served, browser, build) -> None:
    from shared.formats.potree import open_tiles

    tiles = open_tiles(build("blob"))
    depth = max(n.level for n in tiles.nodes.values())
    assert depth > 4, "the fixture must need more than one hierarchy chunk (stepSize 4)"
    server, log = served
    # Served without Range support: the viewer must fetch each file once and slice nodes from it.
    url = f"{server.url}/viewer/?tiles=/whole/blob/metadata.json&pos=0,0,493&look=0,0,500&budget=1000000"
    page = Page(browser, url, size=(320, 240))
    try:
        state = page.wait_idle()
        assert state["error"] is None, state["error"]
        assert state["loadedNodes"] == len(tiles.nodes)
        assert state["drawnPoints"] == state["totalPoints"] == sum(n.num_points for n in tiles.nodes.values())
        assert tiles.points == state["totalPoints"]
        fetched = [name for name, _, _ in log if name.startswith("whole/")]
        assert sorted(fetched) == ["whole/hierarchy.bin", "whole/metadata.json", "whole/octree.bin"]
        assert page.errors == [], page.errors
    finally:
        page.close()


def test_cloud_with_only_positions_renders(served, browser, build) -> None:
    """Tiles of an x, y, z cloud carry position and the derived size only: the viewer draws
    them (default grey, splats sized by the derived spacing) with no error."""
    from shared.formats.potree import open_tiles

    tiles = open_tiles(build("bare"))
    assert tiles.point_dtype.names == ("position", "size")
    server, _log = served
    url = f"{server.url}/static/bare/metadata.json"
    page = Page(browser, f"{server.url}/viewer/?tiles={url}&budget=10000000&edl=0&grazing=0", size=(320, 240))
    try:
        state = page.wait_idle()
        assert state["error"] is None, state["error"]
        assert state["hasSize"] and not state["hasColor"] and not state["hasNormal"]
        assert state["drawnPoints"] == tiles.points
        img = page.capture()
        fg = np.abs(img.astype(float) - np.array([0.08, 0.09, 0.11]) * 255).sum(axis=2) > 30
        assert fg.mean() > 0.6, f"only {fg.mean():.1%} of the frame shows points (holes?)"
        assert page.errors == [], page.errors
    finally:
        page.close()
