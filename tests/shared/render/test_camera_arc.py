"""The default preview path: an arc on the scanner's side for one view, an orbit for a merged
model; the object framed (not its empty bounding box); grey objects shaded so they read."""

from __future__ import annotations

from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np
import pytest

from shared.render.camera_path import ARC_ELEVATION, ARC_SWEEP, SCANNER, is_single_view, make_path
from shared.render.octree import build_tiles
from shared.render.preview import BACKGROUND, render_preview
from tests.support.clouds import surface_points, synthetic_scan, write_cloud

pytestmark = pytest.mark.xdist_group("preview")


def _sphere_all_round(n: int = 20_000, seed: int = 0) -> np.ndarray:
    """A model merged from views all around: points on a whole sphere 500 mm ahead."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * 80.0 + [0.0, 0.0, 500.0]


def test_single_view_or_merged() -> None:
    scan = surface_points(200, 150)["xyz"]
    assert is_single_view(scan)
    assert not is_single_view(_sphere_all_round())
    # The same model seen from inside its bounds is not one view either.
    assert not is_single_view(_sphere_all_round() - [0.0, 0.0, 500.0])


def test_auto_path_is_an_arc_on_the_scanners_side() -> None:
    pts = surface_points(200, 150)["xyz"].astype(np.float64)
    lo, hi = pts.min(0), pts.max(0)
    poses = make_path("auto", lo, hi, 60, points=pts, aspect=16 / 9)
    centre = (lo + hi) / 2
    home = np.asarray(SCANNER) - centre
    home /= np.linalg.norm(home)
    angles = []
    for p in poses:
        d = p.eye - p.target  # the direction the object is seen from
        angles.append(np.degrees(np.arccos(np.clip(d @ home / np.linalg.norm(d), -1, 1))))
        assert p.eye[2] < lo[2]  # in front of the surface, where the scanner saw it
    assert max(angles) <= np.hypot(ARC_SWEEP / 2, ARC_ELEVATION) + 1
    assert max(angles) >= ARC_SWEEP / 2 - 5  # it does swing
    # A loop: the last pose leads back to the first.
    assert np.linalg.norm(poses[-1].eye - poses[0].eye) < np.linalg.norm(hi - lo) * 0.2


def test_auto_path_orbits_a_merged_model() -> None:
    pts = _sphere_all_round()
    lo, hi = pts.min(0), pts.max(0)
    poses = make_path("auto", lo, hi, 40, points=pts)
    centre = (lo + hi) / 2
    behind = [p.eye[2] > centre[2] for p in poses]
    assert any(behind) and not all(behind)  # goes round the back


@pytest.fixture(scope="module")
def grey_tiles(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Tiles of a grey object: one with normals, one without; and a synthetic scan."""
    folder = tmp_path_factory.mktemp("arc")
    a = surface_points(220, 165, seed=2)
    a["rgb"][:] = 200
    out = {}
    for name, fields in (("normals", ("xyz", "rgb", "normal", "size")), ("bare", ("xyz", "rgb", "size"))):
        cloud = write_cloud(folder / f"{name}.ply", a, fields)
        out[name] = folder / f"{name}_tiles"
        build_tiles(cloud, out[name], workers=1, max_leaf=2_000)
    scan = synthetic_scan(folder / "scan.ply", 40_000, seed=3)
    out["scan"] = folder / "scan_tiles"
    build_tiles(scan, out["scan"], workers=1, max_leaf=2_000)
    return out


def _frames(path: Path) -> list[np.ndarray]:
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    return [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in gen]


def _covered(frame: np.ndarray) -> np.ndarray:
    return np.abs(frame.astype(int) - np.array(BACKGROUND)).sum(axis=2) > 24


@pytest.mark.parametrize("which", ["normals", "scan"])
def test_default_preview_frames_the_object(which: str, grey_tiles: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "p.mp4"
    render_preview(grey_tiles[which], out, size=(192, 108), seconds=1.0, fps=12)
    for f in _frames(out):
        cov = _covered(f)
        ys, xs = np.nonzero(cov)
        assert ys.size
        span_y = (ys.max() - ys.min() + 1) / f.shape[0]
        span_x = (xs.max() - xs.min() + 1) / f.shape[1]
        # The object fills the frame in its limiting direction (FILL = 0.9 of it, less the
        # splats' and the compression's blur) and is not cut off by the frame's edges.
        assert max(span_x, span_y) > 0.75, (span_x, span_y)
        assert span_x < 0.99 and span_y < 0.99


def test_grey_object_is_shaded(grey_tiles: dict[str, Path], tmp_path: Path) -> None:
    """Flat grey points read as a shape: lit by their normals, or with eye-dome lighting."""
    stds = {}
    for name, kw in (("normals", {}), ("bare", {}), ("bare_flat", {"edl": 0.0})):
        tiles = grey_tiles[name.removesuffix("_flat")]
        out = tmp_path / f"{name}.mp4"
        render_preview(tiles, out, size=(192, 108), seconds=0.25, fps=4, **kw)
        f = _frames(out)[0]
        inner = cv2.erode(_covered(f).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # no edges
        stds[name] = f.astype(float).mean(axis=2)[inner].std()
    assert stds["bare_flat"] < 3, stds  # unshaded: one grey (codec noise only)
    assert stds["normals"] > 4 * stds["bare_flat"] and stds["normals"] > 12
    assert stds["bare"] > stds["bare_flat"] + 2  # EDL darkens depth steps
