"""Web viewer mesh layer (services/viewer/src/gltf.ts, mesh.ts): binary glTF meshes drawn with the
points in a real headless Chromium (Playwright, Debian's chromium, WebGL2 on SwiftShader).

The scene: a scan from the origin of a grey ball (radius 0.97 R) before a blue-grey back wall,
tiled with ``shared.render.octree.build_tiles``; the mesh is an icosphere of radius R around the
ball, coloured by a red-to-green gradient along x (written with trimesh). What each pixel should
show is ray-cast in the test from the camera the page was given (position, look-at point, field
of view): the sphere's silhouette and, inside it, the gradient's value at the surface hit.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from fastapi import FastAPI, Header, HTTPException
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from fastapi.testclient import TestClient

from services.viewer import routes
from shared.formats.ply import write_ply
from shared.merge.meshing import ColouredMesh, write_mesh
from tests.support.viewer_browser import Page, Server, built_viewer, chromium, rays_through_pixels

pytestmark = pytest.mark.xdist_group("viewer")

API_KEY = "mesh-key-41d2"
SIZE = (640, 480)
CENTRE = np.array([0.0, 0.0, 700.0])
RADIUS = 150.0
#: The grey ball of points lies just inside the mesh: where the mesh is drawn it hides them.
BALL = 0.97 * RADIUS
WALL_Z = 1000.0
EYE = np.zeros(3)
FOV = 40.0
#: The mesh's colour at x: red (1 - t) and green t with t = (x - cx + R) / 2R, a little blue.
BLUE = 30


# --------------------------------------------------------------------------- scene


def scan_ball_and_wall(path: Path, width: int = 240, height: int = 180, focal: float = 200.0) -> int:
    """A scan from the origin (x right, y down, z forward) of the grey ball before the wall."""
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    rays = np.stack([u / focal, v / focal, np.ones_like(u)], axis=-1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    t = WALL_Z / rays[:, 2]
    colour = np.tile(np.array([[70, 90, 160]], np.uint8), (len(rays), 1))
    normal = np.tile(np.array([[0, 0, -1]], np.float32), (len(rays), 1))
    hit = sphere_hit(rays, np.zeros(3), BALL)
    ball = np.isfinite(hit)
    t[ball] = hit[ball]
    colour[ball] = (150, 150, 150)
    xyz = rays * t[:, None]
    normal[ball] = (xyz[ball] - CENTRE) / BALL
    write_ply(path, xyz.astype(np.float32), colour, normal, (xyz[:, 2] / focal).astype(np.float32))
    return len(xyz)


def sphere_hit(rays: np.ndarray, eye: np.ndarray, radius: float) -> np.ndarray:
    """Distance along each unit ray from ``eye`` to the sphere about CENTRE (inf on a miss)."""
    oc = CENTRE - eye
    b = rays @ oc
    disc = b * b - (oc @ oc - radius * radius)
    return np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)


def gradient(x: np.ndarray) -> np.ndarray:
    return np.clip((x - CENTRE[0] + RADIUS) / (2 * RADIUS), 0, 1)


def rewrite_glb(data: bytes, edit: Callable[[dict, bytearray], None]) -> bytes:
    """A GLB with its JSON and BIN chunks changed by ``edit`` (lengths and padding redone)."""
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + json_len])
    bin_at = 20 + json_len
    bin_len = struct.unpack_from("<I", data, bin_at)[0]
    binary = bytearray(data[bin_at + 8 : bin_at + 8 + bin_len])
    edit(doc, binary)
    return pack_glb(doc, bytes(binary))


def pack_glb(doc: dict, binary: bytes) -> bytes:
    """A GLB of a glTF document and its BIN chunk (both padded to 4 bytes)."""
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


def _index_past_vertices(doc: dict, binary: bytearray) -> None:
    prim = doc["meshes"][0]["primitives"][0]
    acc = doc["accessors"][prim["indices"]]
    view = doc["bufferViews"][acc["bufferView"]]
    at = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    vertices = doc["accessors"][prim["attributes"]["POSITION"]]["count"]
    width = {5121: "B", 5123: "H", 5125: "I"}[acc["componentType"]]
    struct.pack_into("<" + width, binary, at, vertices + 5)


def _draco(doc: dict, binary: bytearray) -> None:
    doc["extensionsRequired"] = doc["extensionsUsed"] = ["KHR_draco_mesh_compression"]


def _external(doc: dict, binary: bytearray) -> None:
    doc["buffers"][0]["uri"] = "mesh.bin"


def _no_triangles(doc: dict, binary: bytearray) -> None:
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            prim["mode"] = 1  # lines


def write_sphere_glb(path: Path, subdivisions: int, *, node_transform: bool = False, normals: bool = True) -> int:
    """A coloured icosphere of radius RADIUS about CENTRE as .glb; returns its triangle count.

    With ``node_transform`` the vertices are about the origin and the glTF node carries the
    translation (the viewer must apply node transforms)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)
    t = gradient(sphere.vertices[:, 0] + CENTRE[0])
    rgba = np.stack([255 * (1 - t), 255 * t, np.full_like(t, BLUE), np.full_like(t, 255)], axis=1)
    sphere.visual.vertex_colors = np.round(rgba).astype(np.uint8)
    scene = trimesh.Scene()
    if node_transform:
        scene.add_geometry(sphere, transform=trimesh.transformations.translation_matrix(CENTRE))
    else:
        sphere.apply_translation(CENTRE)
        scene.add_geometry(sphere)
    path.write_bytes(trimesh.exchange.gltf.export_glb(scene, include_normals=normals))
    return len(sphere.faces)


def write_interleaved_glb(path: Path, subdivisions: int = 4) -> int:
    """The gradient icosphere as another writer might lay it out: POSITION and FLOAT COLOR_0
    (VEC3) interleaved in one strided buffer view, UNSIGNED_SHORT indices, and a node that
    rotates by 90 degrees about z (so the gradient runs along world y) and moves it to CENTRE."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)
    assert len(sphere.vertices) < 65536
    t = gradient(sphere.vertices[:, 0] + CENTRE[0])
    colour = np.stack([1 - t, t, np.full_like(t, BLUE / 255)], axis=1)
    interleaved = np.hstack([sphere.vertices, colour]).astype("<f4").tobytes()
    indices = sphere.faces.astype("<u2").tobytes()
    indices += b"\0" * (-len(indices) % 4)
    lo, hi = sphere.vertices.min(axis=0).tolist(), sphere.vertices.max(axis=0).tolist()
    n = len(sphere.vertices)
    doc = {
        "asset": {"version": "2.0", "generator": "graylight test"},
        "buffers": [{"byteLength": len(indices) + len(interleaved)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(indices), "target": 34963},
                        {"buffer": 0, "byteOffset": len(indices), "byteLength": len(interleaved), "byteStride": 24,
                         "target": 34962}],
        "accessors": [{"bufferView": 0, "componentType": 5123, "count": sphere.faces.size, "type": "SCALAR"},
                      {"bufferView": 1, "byteOffset": 0, "componentType": 5126, "count": n, "type": "VEC3",
                       "min": lo, "max": hi},
                      {"bufferView": 1, "byteOffset": 12, "componentType": 5126, "count": n, "type": "VEC3"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 1, "COLOR_0": 2}, "indices": 0}]}],
        "nodes": [{"children": [1], "translation": CENTRE.tolist()},
                  {"mesh": 0, "rotation": [0.0, 0.0, float(np.sin(np.pi / 4)), float(np.cos(np.pi / 4))]}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }  # fmt: skip
    path.write_bytes(pack_glb(doc, indices + interleaved))
    return len(sphere.faces)


# --------------------------------------------------------------------------- pixel classes


def mesh_like(img: np.ndarray) -> np.ndarray:
    """Pixels of the mesh's red-green gradient (little blue), whatever their shading."""
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return np.maximum(r, g) > 2 * b + 20


def grey_points(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return (np.abs(r - g) < 25) & (np.abs(g - b) < 25) & (r > 50)


def wall(img: np.ndarray) -> np.ndarray:
    r, b = img[..., 0].astype(int), img[..., 2].astype(int)
    return (b > r + 40) & (b > 100)


def regions(eye: np.ndarray, target: np.ndarray, fov: float) -> dict[str, np.ndarray]:
    """Ray-cast masks: inside the mesh's silhouette (2 px margin), well outside it, inside the
    ball of points, and the gradient value t expected at each pixel's surface hit."""
    rays = rays_through_pixels(eye, target, fov, SIZE).reshape(-1, 3)
    hit = sphere_hit(rays, eye, RADIUS)
    disc = np.isfinite(hit).reshape(SIZE[1], SIZE[0]).astype(np.uint8)
    ball = np.isfinite(sphere_hit(rays, eye, BALL)).reshape(SIZE[1], SIZE[0]).astype(np.uint8)
    x = (eye + rays * np.where(np.isfinite(hit), hit, 0)[:, None])[:, 0]
    return {
        "inside": cv2.erode(disc, np.ones((5, 5), np.uint8)).astype(bool),
        "outside": ~cv2.dilate(disc, np.ones((9, 9), np.uint8)).astype(bool),
        "ball": cv2.erode(ball, np.ones((9, 9), np.uint8)).astype(bool),
        "t": gradient(x).reshape(SIZE[1], SIZE[0]),
    }


# --------------------------------------------------------------------------- server


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path | int]:
    """Tiles of the scan, meshes (a job's three levels of detail as the mesh stage writes them,
    others laid out differently) and bad GLBs."""
    from shared.render.octree import build_tiles

    root = tmp_path_factory.mktemp("viewer-mesh")
    scan_ball_and_wall(root / "scan.ply")
    build_tiles(root / "scan.ply", root / "job" / "tiles", workers=1, max_leaf=4000)
    out: dict[str, Path | int] = {"root": root}
    # Levels of a job, written by the mesh stage's own writer; the finest needs 32-bit indices
    # (more than 65,535 vertices).
    for name, subdivisions in (("mesh.glb", 7), ("mesh_lod1.glb", 5), ("mesh_lod2.glb", 3)):
        sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)
        vertices = sphere.vertices + CENTRE
        t = gradient(vertices[:, 0])
        colours = np.round(np.stack([255 * (1 - t), 255 * t, np.full_like(t, BLUE)], axis=1)).astype(np.uint8)
        write_mesh(root / "job" / name, ColouredMesh(vertices, np.asarray(sphere.faces, np.int64), colours))
        out[name] = len(sphere.faces)
    out["node"] = write_sphere_glb(root / "node.glb", 5, node_transform=True, normals=False)
    out["interleaved"] = write_interleaved_glb(root / "interleaved.glb")
    (root / "garbage.glb").write_bytes(b"this is not a mesh at all" * 10)
    good = (root / "job" / "mesh_lod1.glb").read_bytes()
    (root / "truncated.glb").write_bytes(good[: len(good) // 2])
    for name, edit in (("index.glb", _index_past_vertices), ("draco.glb", _draco), ("external.glb", _external),
                       ("lines.glb", _no_triangles)):  # fmt: skip
        (root / name).write_bytes(rewrite_glb(good, edit))
    (root / "same.glb").write_bytes(rewrite_glb(good, lambda doc, binary: None))
    return out


def make_app(root: Path, log: list[str]) -> FastAPI:
    """The viewer routes, a job-service-like artifact list and files behind a Bearer key, static files."""
    app = FastAPI()
    app.include_router(routes.create_router())
    job_dir = root / "job"

    def check(authorization: str | None) -> None:
        if authorization != f"Bearer {API_KEY}":
            raise HTTPException(401, "missing or wrong API key")

    @app.get("/v1/jobs/{job}/artifacts")
    def list_artifacts(job: str, authorization: str | None = Header(None)) -> dict:
        # Like the API's list: every file as STAGE/PATH, and the stage's published names
        # also short: here only mesh.glb, so the levels are found by the stage's own paths too.
        check(authorization)
        arts = [{"name": f"tiles/{p.name}", "stage": "tiles", "size": p.stat().st_size} for p in (job_dir / "tiles").iterdir()]
        for p in sorted(job_dir.glob("*.glb")):
            arts.append({"name": f"mv_merge/{p.name}", "stage": "mv_merge", "size": p.stat().st_size})
            if p.name == "mesh.glb":
                arts.append({"name": p.name, "stage": "mv_merge", "size": p.stat().st_size})
        arts += [{"name": "preview/mesh_lod1.glb", "stage": "preview", "size": 1}]  # another stage's file
        return {"job": job, "artifacts": arts}

    @app.get("/v1/jobs/{job}/artifacts/{name:path}")
    def artifact(job: str, name: str, authorization: str | None = Header(None)) -> FileResponse:
        check(authorization)
        if name.startswith(("mv_merge/", "tiles/")) and name.endswith(".glb"):
            name = name.split("/", 1)[1]
        log.append(name)
        path = (job_dir / name).resolve()
        if not path.is_relative_to(job_dir) or not path.is_file():
            raise HTTPException(404, f"{name} not found")
        return FileResponse(path)

    app.mount("/static", StaticFiles(directory=root), name="static")
    return app


@pytest.fixture(scope="module")
def served(scene: dict) -> Iterator[tuple[Server, list[str]]]:
    built_viewer()
    log: list[str] = []
    with Server(make_app(scene["root"], log)) as server:
        yield server, log


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with chromium() as b:
        yield b


def view_url(server: Server, **extra: str) -> str:
    query = {"tiles": "/static/job/tiles/", "ui": "1", "edl": "0", "grazing": "0", "fov": str(FOV),
             "pos": ",".join(map(str, EYE)), "look": ",".join(map(str, CENTRE)), **extra}  # fmt: skip
    return f"{server.url}/viewer/?" + "&".join(f"{k}={v}" for k, v in query.items())


def state_drawn(page: Page) -> str | None:
    return page.page.evaluate("() => window.graylight.state().mesh.drawn")


def save(img: np.ndarray, path: Path) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


# --------------------------------------------------------------------------- tests


@pytest.mark.slow
def test_rewritten_glb_without_changes_still_draws(served, browser, scene) -> None:
    """The bad-GLB cases are edits of a good file: the same rewrite with no edit must draw."""
    server, _ = served
    page = Page(browser, view_url(server, mesh="/static/same.glb", showmesh="1"), size=SIZE)
    try:
        state = page.wait_idle()
        assert state["notice"] is None and state["mesh"]["drawnTriangles"] == scene["mesh_lod1.glb"]
        assert mesh_like(page.capture())[regions(EYE, CENTRE, FOV)["inside"]].mean() > 0.99
    finally:
        page.close()


@pytest.mark.slow
def test_interleaved_float_colours_short_indices_and_a_rotated_node(served, browser, scene) -> None:
    server, _ = served
    page = Page(browser, view_url(server, mesh="/static/interleaved.glb", showmesh="1"), size=SIZE)
    try:
        state = page.wait_idle()
        assert state["notice"] is None and state["mesh"]["drawnTriangles"] == scene["interleaved"], state["mesh"]
        assert state["mesh"]["drawnIndexBits"] == [16]
        img = page.capture()
        m = regions(EYE, CENTRE, FOV)
        assert mesh_like(img)[m["inside"]].mean() > 0.99 and mesh_like(img)[m["outside"]].mean() < 0.002
        # The node turned local +x onto world +y: the gradient's t follows world y (image rows).
        rays = rays_through_pixels(EYE, CENTRE, FOV, SIZE).reshape(-1, 3)
        hit = sphere_hit(rays, EYE, RADIUS)
        y = (EYE + rays * np.where(np.isfinite(hit), hit, 0)[:, None])[:, 1].reshape(SIZE[1], SIZE[0])
        expected = np.clip((y - CENTRE[1] + RADIUS) / (2 * RADIUS), 0, 1)
        rg = img[..., :2].astype(float)
        share = rg[..., 1] / np.maximum(rg.sum(axis=2), 1)
        err = np.abs(share - expected)[m["inside"]]
        assert np.median(err) < 0.02 and np.percentile(err, 99) < 0.08, (np.median(err), np.percentile(err, 99))
        assert page.errors == [], page.errors
    finally:
        page.close()


def test_job_page_config_names_the_artifact_list() -> None:
    app = FastAPI()
    app.include_router(routes.create_router(artifacts_url_template="/api/jobs/{job}/files"))
    page = TestClient(app).get("/viewer/job-7")
    assert page.status_code == 200 and '"artifacts": "/api/jobs/job-7/files"' in page.text


@pytest.mark.slow
def test_mesh_toggle_draws_the_coloured_mesh_over_the_points(served, browser, scene, tmp_path: Path) -> None:
    server, _ = served
    page = Page(browser, view_url(server, mesh="/static/node.glb"), size=SIZE)
    try:
        state = page.wait_idle()
        assert state["error"] is None and state["notice"] is None, state
        assert page.page.locator("#mesh-controls").is_visible()
        # Nothing is fetched until the mesh is shown.
        assert state["mesh"]["levels"][0]["state"] == "unloaded"
        m = regions(EYE, CENTRE, FOV)
        assert m["inside"].sum() > 40_000 and m["outside"].sum() > 100_000
        off = page.capture()
        save(off, tmp_path / "mesh_off.png")

        page.page.locator("#mesh").check()
        state = page.wait_idle()
        assert state["mesh"]["drawn"] == "node.glb" and state["mesh"]["drawnTriangles"] == scene["node"]
        assert state["drawnPoints"] == 0  # the mesh alone by default
        on = page.capture()
        save(on, tmp_path / "mesh_on.png")
        print(f"\nscreenshots: {tmp_path / 'mesh_off.png'} {tmp_path / 'mesh_on.png'}")

        # Toggle on: the mesh's colours fill its ray-cast silhouette and nothing outside it.
        inside, outside = m["inside"], m["outside"]
        assert mesh_like(on)[inside].mean() > 0.99, mesh_like(on)[inside].mean()
        assert mesh_like(on)[outside].mean() < 0.002 and not wall(on)[outside].any()  # points hidden
        # ... in the gradient the vertex colours carry: green share g / (r + g) against the t
        # ray-cast at each pixel's surface point (Lambert shading scales r and g alike).
        rg = on[..., :2].astype(float)
        share = rg[..., 1] / np.maximum(rg.sum(axis=2), 1)
        err = np.abs(share - m["t"])[inside]
        print(f"gradient: median |error| {np.median(err):.4f}, 99th percentile {np.percentile(err, 99):.4f}")
        assert np.median(err) < 0.02 and np.percentile(err, 99) < 0.08
        # Headlight Lambert: brightest where the surface faces the eye, darker at the rim.
        brightness = rg.sum(axis=2)
        centre_px = np.array(SIZE[::-1]) // 2
        yy, xx = np.mgrid[: SIZE[1], : SIZE[0]]
        rim = inside & ~cv2.erode(inside.astype(np.uint8), np.ones((25, 25), np.uint8)).astype(bool)
        core = inside & (np.hypot(yy - centre_px[0], xx - centre_px[1]) < 30)
        assert brightness[core].mean() > 1.5 * brightness[rim].mean()

        # Toggle off: the same region shows the grey points again, the wall around them.
        assert mesh_like(off)[inside].mean() < 0.01
        assert grey_points(off)[m["ball"]].mean() > 0.95 and wall(off)[outside].mean() > 0.95

        # Points with the mesh: depth-tested together, the mesh hides the ball inside it and the
        # wall shows around it.
        page.page.locator("#mesh-points").check()
        state = page.wait_idle()
        both = page.capture()
        save(both, tmp_path / "mesh_and_points.png")
        assert state["drawnPoints"] > 0
        assert mesh_like(both)[inside].mean() > 0.99 and wall(both)[outside].mean() > 0.95

        # High-quality blending and eye-dome lighting keep the mesh in place.
        page.set(hq=True, edl=True)
        hq = page.capture()
        assert mesh_like(hq)[inside].mean() > 0.97 and wall(hq)[outside].mean() > 0.9

        page.page.locator("#mesh").uncheck()
        state = page.wait_idle()
        assert state["mesh"]["shown"] is False and mesh_like(page.capture())[inside].mean() < 0.01
        # The M key toggles it too, and the panel's box follows (as it follows graylight.set).
        page.page.locator("#view").focus()
        page.page.keyboard.press("m")
        state = page.wait_idle()
        assert state["mesh"]["shown"] is True and page.page.locator("#mesh").is_checked()
        assert mesh_like(page.capture())[inside].mean() > 0.99
        page.set(mesh=False)
        assert not page.page.locator("#mesh").is_checked()
        assert page.errors == [], page.errors
    finally:
        page.close()


@pytest.mark.slow
def test_job_page_lists_levels_loads_coarsest_first_and_picks_by_screen_size(served, browser, scene, tmp_path) -> None:
    server, log = served
    url = f"{server.url}/viewer/job?edl=0&grazing=0&fov={FOV}&pos=0,0,0&look={','.join(map(str, CENTRE))}#key={API_KEY}"
    page = Page(browser, url, size=SIZE)
    try:
        state = page.wait_idle()
        assert state["error"] is None and state["notice"] is None, state
        levels = state["mesh"]["levels"]
        assert [lv["name"] for lv in levels] == ["mesh.glb", "mesh_lod1.glb", "mesh_lod2.glb"]
        # The published short name where there is one, else the mesh stage's own path.
        paths = [lv["url"].split("/artifacts/", 1)[1] for lv in levels]
        assert paths == ["mesh.glb", "mv_merge/mesh_lod1.glb", "mv_merge/mesh_lod2.glb"], paths
        triangles = [scene[lv["name"]] for lv in levels]

        def expected(eye: np.ndarray) -> str:
            # The layer's rule: the finest level with at most one triangle per pixel of the
            # bounding sphere's projected disc (the icosphere's box sphere is sqrt(3) R).
            focal = SIZE[1] / 2 / np.tan(np.radians(FOV) / 2)
            r = np.sqrt(3) * RADIUS
            d = np.linalg.norm(CENTRE - eye)
            pixels = np.pi * (focal * r / np.sqrt(d * d - r * r)) ** 2
            return next((lv["name"] for lv, n in zip(levels, triangles, strict=True) if n <= pixels), levels[-1]["name"])

        log.clear()
        page.page.locator("#mesh").check()
        page.wait_idle()
        fetched = [n for n in log if n.endswith(".glb")]
        assert fetched[0] == "mesh_lod2.glb", fetched  # the coarsest first, to show something at once
        assert state_drawn(page) == expected(EYE) and fetched == ["mesh_lod2.glb", expected(EYE)]

        drawn = {}
        for distance in (420.0, 700.0, 4000.0, 30000.0):
            eye = CENTRE - [0, 0, distance]
            state = page.look_at(eye, CENTRE)
            drawn[distance] = state["mesh"]["drawn"]
            assert drawn[distance] == expected(eye), (distance, state["mesh"])
            assert state["mesh"]["drawnTriangles"] == scene[drawn[distance]]
            img = page.capture()
            if distance == 420.0:
                save(img, tmp_path / "finest.png")
                m = regions(eye, CENTRE, FOV)
                assert mesh_like(img)[m["inside"]].mean() > 0.99
        print(f"\nlevel drawn by camera distance (mm): {drawn}; files fetched: {log}")
        # Coarser levels stay loaded: zooming out fetched nothing again.
        assert sorted(log) == ["mesh.glb", "mesh_lod1.glb", "mesh_lod2.glb"], log
        assert len(set(drawn.values())) == 3  # every level was used
        assert drawn[420.0] == "mesh.glb"  # 327,680 triangles, 32-bit indices, one buffer

        # The download link carries the key (a blob of the fetched file) and saves mesh.glb.
        link = page.page.locator("#mesh-download")
        assert "mesh.glb" in link.inner_text()
        with page.page.expect_download() as info:
            link.click()
        download = info.value
        assert download.suggested_filename == "mesh.glb"
        assert Path(download.path()).read_bytes() == (scene["root"] / "job" / "mesh.glb").read_bytes()
        assert page.errors == [], page.errors
    finally:
        page.close()


@pytest.mark.slow
@pytest.mark.parametrize(("name", "reason"), [
    ("garbage.glb", "not a binary glTF file"), ("truncated.glb", "truncated"), ("missing.glb", "HTTP 404"),
    ("index.glb", "index"), ("draco.glb", "KHR_draco_mesh_compression"), ("external.glb", "external buffers"),
    ("lines.glb", "no triangles"),
])  # fmt: skip
def test_bad_glb_shows_a_one_line_message_and_the_points_stay(served, browser, name: str, reason: str) -> None:
    server, _ = served
    page = Page(browser, view_url(server, mesh=f"/static/{name}", showmesh="1"), size=SIZE)
    try:
        state = page.wait_idle()
        assert state["error"] is None, state["error"]
        notice = page.page.locator("#notice")
        assert notice.is_visible()
        text = notice.inner_text()
        assert name in text and reason in text and "\n" not in text, text
        assert state["mesh"]["levels"][0]["state"] == "failed" and state["mesh"]["drawn"] is None
        img = page.capture()
        m = regions(EYE, CENTRE, FOV)
        assert state["drawnPoints"] == state["totalPoints"]
        assert grey_points(img)[m["ball"]].mean() > 0.95 and wall(img)[m["outside"]].mean() > 0.95
        # The browser itself logs the 404 response; nothing else may go wrong.
        errors = [e for e in page.errors if not (name == "missing.glb" and "404 (Not Found)" in e)]
        assert errors == [], page.errors
    finally:
        page.close()


@pytest.mark.slow
def test_two_million_triangles_upload_in_one_buffer_with_32_bit_indices(served, browser, scene) -> None:
    """A 1001 x 1001 vertex height field (2,000,000 triangles, 1,002,001 vertices: 32-bit indices)
    at z = 700 mm: one vertex and one index buffer, drawn where its ray-cast footprint lies."""
    server, _ = served
    n, half, z0 = 1001, 150.0, 700.0
    u, v = np.meshgrid(np.linspace(-half, half, n), np.linspace(-half, half, n))
    z = z0 + 2.0 * np.sin(u / 9.0) * np.cos(v / 11.0)  # a ripple, so the shading varies
    verts = np.stack([u.ravel(), v.ravel(), z.ravel()], axis=1)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = (q.ravel() for q in (i[:-1, :-1], i[:-1, 1:], i[1:, :-1], i[1:, 1:]))
    faces = np.concatenate([np.stack([a, b, c], axis=1), np.stack([b, d, c], axis=1)])
    t = (verts[:, 0] + half) / (2 * half)
    rgba = np.stack([255 * (1 - t), 255 * t, np.full_like(t, BLUE), np.full_like(t, 255)], axis=1)
    big = trimesh.Trimesh(verts, faces, vertex_colors=np.round(rgba).astype(np.uint8), process=False)
    (scene["root"] / "big.glb").write_bytes(big.export(file_type="glb"))

    page = Page(browser, view_url(server, mesh="/static/big.glb"), size=SIZE)
    try:
        page.wait_idle()
        state = page.set(mesh=True)
        assert state["notice"] is None and state["error"] is None, state
        mesh = state["mesh"]
        assert mesh["drawnTriangles"] == len(faces) == 2_000_000
        assert mesh["drawnBuffers"] == 2 and mesh["drawnIndexBits"] == [32]
        img = page.capture()
        rays = rays_through_pixels(EYE, CENTRE, FOV, SIZE)
        hit = EYE + rays * ((z0 - EYE[2]) / rays[..., 2])[..., None]
        footprint = ((np.abs(hit[..., 0]) < half) & (np.abs(hit[..., 1]) < half)).astype(np.uint8)
        inside = cv2.erode(footprint, np.ones((9, 9), np.uint8)).astype(bool)
        outside = ~cv2.dilate(footprint, np.ones((9, 9), np.uint8)).astype(bool)
        assert mesh_like(img)[inside].mean() > 0.99 and mesh_like(img)[outside].mean() < 0.002
        rg = img[..., :2].astype(float)
        share = rg[..., 1] / np.maximum(rg.sum(axis=2), 1)
        expected = np.clip((hit[..., 0] + half) / (2 * half), 0, 1)
        assert np.median(np.abs(share - expected)[inside]) < 0.02
        assert page.errors == [], page.errors
    finally:
        page.close()
