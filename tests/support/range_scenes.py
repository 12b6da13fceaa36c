"""Range images of the virtual rig for the codec bench: detailed meshes and a relief scanned by a
2048x1536 camera over a projector of 1:1, 2:1 or 4:1 sampling (camera pixels per projector pixel
along a side), as ``graylight simulate`` + ``graylight scan`` would make them.

:func:`relief_scene` is a carved panel (about 500 x 380 mm at about 1 m, tilted) whose height
field holds lettering-like ridges, rounded bosses, a chiselled grid and fine tool marks (0.1 to
6 mm of relief): the kind of detail the thesis's rig scans. :func:`bench_range` renders and
scans one image once and keeps only its ``range.npz`` in a cache folder for later runs.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

CACHE = Path(tempfile.gettempdir()) / "graylight-bench-sim-ranges"
CAMERA = (2048, 1536)
#: Bench images: (name, scene, camera pixels per projector pixel along a side).
BENCH_IMAGES: list[tuple[str, str, int]] = [
    ("relief 1:1", "relief", 1), ("relief 2:1", "relief", 2), ("relief 4:1", "relief", 4),
    ("bunny 1:1", "bunny", 1), ("bunny 2:1", "bunny", 2), ("bunny 4:1", "bunny", 4),
    ("fandisk 2:1", "fandisk", 2), ("spot 4:1", "spot", 4),
]


def relief_heights(n: int = 900, m: int = 680, seed: int = 0) -> np.ndarray:
    """(m, n) height field in mm over a 500 x 380 mm panel: smooth bosses, raised ridges with
    rounded profiles, a chiselled groove grid and fine tool marks."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 500, n), np.linspace(0, 380, m))
    h = np.zeros((m, n))
    for _ in range(14):  # bosses
        cx, cy, r, a = rng.uniform(0, 500), rng.uniform(0, 380), rng.uniform(15, 60), rng.uniform(2, 6)
        h += a * np.exp(-((u - cx) ** 2 + (v - cy) ** 2) / (2 * r * r))
    for _ in range(40):  # lettering-like ridges: short strokes with a rounded 2-4 mm wide profile
        x0, y0, ang, ln = rng.uniform(0, 500), rng.uniform(0, 380), rng.uniform(0, np.pi), rng.uniform(10, 60)
        dx, dy = np.cos(ang), np.sin(ang)
        s = np.clip((u - x0) * dx + (v - y0) * dy, 0, ln)
        d2 = (u - x0 - s * dx) ** 2 + (v - y0 - s * dy) ** 2
        h += rng.uniform(0.8, 2.5) * np.exp(-d2 / (2 * rng.uniform(1.0, 2.0) ** 2))
    groove = np.minimum(np.abs(((u + 7) % 62.5) - 31.25), np.abs(((v + 5) % 47.5) - 23.75))
    h -= 1.5 * np.exp(-(groove**2) / (2 * 0.8**2))
    h += 0.15 * np.sin(u * 2 * np.pi / 3.1 + 0.3 * np.sin(v / 9)) + 0.1 * np.sin(v * 2 * np.pi / 4.3)
    return h


def relief_scene(seed: int = 0):  # -> shared.sim.scenes.Scene
    """The relief panel as a mesh facing the camera at about 1 m, tilted 20 degrees about the
    vertical and 10 about the horizontal, with a slightly marbled stone albedo."""
    from shared.formats.mesh import TriangleMesh
    from shared.sim.scenes import Material, MeshObject, Scene, rotation_about

    n, m = 900, 680
    h = relief_heights(n, m, seed)
    u, v = np.meshgrid(np.linspace(-250, 250, n), np.linspace(-190, 190, m))
    verts = np.stack([u.ravel(), v.ravel(), -h.ravel()], 1)  # relief towards the camera (-z)
    idx = np.arange(n * m).reshape(m, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)]).astype(np.int32)
    R = rotation_about([0, 1, 0], 20.0) @ rotation_about([1, 0, 0], 10.0)
    obj = MeshObject(mesh=TriangleMesh(verts, faces), R=R, t=np.array([0.0, 0.0, 1000.0]),
                     material=Material(albedo=(0.7, 0.68, 0.62), variation=0.2, wavelength=30.0), seed=seed)
    return Scene(name="relief", surfaces=[obj], description="a carved relief panel (0.1-6 mm detail)")


def render_bench_range(scene: str, ratio: int, out: Path, seed: int = 0) -> Path:
    """Render and scan ``scene`` (``relief`` or a named scene) with a 2048x1536 camera over a
    projector of (2048 / ratio) x (1536 / ratio), as ``graylight simulate`` + ``graylight scan``
    would; its ``range.npz`` written to ``out`` (a temporary name renamed), the capture and the
    scan's other files removed. Returns ``out``."""
    from shared.scan.pipeline import scan
    from shared.sim.rigs import make_rig
    from shared.sim.scenes import build_scene
    from shared.sim.simulate import simulate_capture

    out.parent.mkdir(parents=True, exist_ok=True)
    sc = relief_scene(seed) if scene == "relief" else build_scene(scene, seed=seed)
    rig = make_rig(camera_size=CAMERA, projector_size=(CAMERA[0] // ratio, CAMERA[1] // ratio), seed=seed)
    work = Path(tempfile.mkdtemp(prefix=f"{scene}-{ratio}-", dir=out.parent))
    try:
        simulate_capture(sc, rig, work / "capture", seed=seed, write_truth=False)
        scan(work / "capture", work / "scan")
        tmp = out.with_name(out.stem + ".tmp.npz")
        shutil.copyfile(work / "scan" / "range.npz", tmp)
        tmp.rename(out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out


def bench_range(scene: str, ratio: int, seed: int = 0) -> Path:
    """:func:`render_bench_range`'s ``range.npz``, made once and kept in :data:`CACHE` for the
    bench's later runs (the tests render theirs afresh)."""
    out = CACHE / f"{scene}-{ratio}to1-s{seed}" / "range.npz"
    return out if out.is_file() else render_bench_range(scene, ratio, out, seed)


def dragon_range(k: int = 0) -> tuple[str, np.ndarray]:
    """A real range image: Stanford's Cyberware scan ``dragonStandRight_<24 k>.ply`` (the
    ``stanford-dragon-turntable`` data) on its own 483 x 262 grid, depth z in mm, NaN where the
    scanner saw nothing. Returns (name, z (262, 483) float32)."""
    from shared.core.datapaths import shared_data_dir

    path = shared_data_dir() / "stanford-dragon-turntable" / f"dragonStandRight_{24 * k}.ply"
    with open(path, encoding="ascii") as f:
        cols = rows = nv = ng = 0
        for line in f:
            w = line.split()
            if w[:2] == ["obj_info", "num_cols"]:
                cols = int(w[2])
            elif w[:2] == ["obj_info", "num_rows"]:
                rows = int(w[2])
            elif w[:2] == ["element", "vertex"]:
                nv = int(w[2])
            elif w[:2] == ["element", "range_grid"]:
                ng = int(w[2])
            elif w[0] == "end_header":
                break
        xyz = np.loadtxt(f, max_rows=nv, dtype=np.float64)
        grid = [line.split() for _, line in zip(range(ng), f, strict=False)]
    z = np.full(rows * cols, np.nan, np.float32)
    for i, g in enumerate(grid):
        if g[0] != "0":
            z[i] = 1000.0 * xyz[int(g[1]), 2]
    return f"dragon scan {24 * k} (Cyberware, real)", z.reshape(rows, cols)[::-1].copy()
