"""Loading scan-set views: captures through the scanner's stages, clouds from PLY in their units."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.ply import write_ply
from shared.formats.scanset import load_scanset, scanset_doc, write_scanset
from shared.merge.views import crop_to_roi, estimate_normals, load_view, view_from_scan_outputs
from shared.scan.pipeline import decode_stage, triangulate_stage
from shared.sim.simulate import load_truth


@pytest.fixture(scope="module")
def small(scanset_factory: Callable[..., Path]) -> Path:
    # roi: the crop is tested here (a simulated set has none by default, as a real capture).
    return scanset_factory(size=(160, 120), projector=(128, 96), views=2, roi=True)


def test_captured_view_matches_truth_and_stage_outputs(small: Path, tmp_path: Path) -> None:
    ss = load_scanset(small)
    view = load_view(ss.views[1])
    truth = load_truth(ss.views[1].path)
    assert len(view) > 1000 and view.range_image is not None and view.K is not None
    # Points sit on the true surface at their pixels (mm), confidences are the decoder's contrast.
    true = truth.points[view.pixel[:, 1], view.pixel[:, 0]]
    ok = np.all(np.isfinite(true), axis=1)
    err = np.linalg.norm(view.xyz[ok] - true[ok], axis=1)
    assert np.median(err) < 1.0
    assert 0.0 < float(view.confidence.mean()) <= 1.0
    # The job service's per-view stage outputs rebuild the same view.
    decode_stage(ss.views[1].path, tmp_path)
    triangulate_stage(tmp_path / "decoded.npz", ss.views[1].rig, tmp_path)
    again = view_from_scan_outputs(ss.views[1], tmp_path)
    np.testing.assert_array_equal(again.pixel, view.pixel)
    np.testing.assert_allclose(again.xyz, view.xyz, atol=1e-3)
    np.testing.assert_array_equal(again.confidence, view.confidence)


def test_roi_crop_keeps_the_object(small: Path) -> None:
    ss = load_scanset(small)
    view = load_view(ss.views[0])
    truth = load_truth(ss.views[0].path)
    cropped = crop_to_roi(view, ss.roi)
    surf = truth.surface[cropped.pixel[:, 1], cropped.pixel[:, 0]]
    assert len(cropped) < len(view)
    assert np.mean(surf <= 1) > 0.97  # object (0) and turntable plate (1) only, the background cropped away
    # Every object point the decoder measured right (within 10 mm of the truth) is kept; a gross
    # decoding error (one of 3577 here, 386 mm off) may fall outside the sphere.
    true = truth.points[view.pixel[:, 1], view.pixel[:, 0]]
    right = (truth.surface[view.pixel[:, 1], view.pixel[:, 0]] == 0) & (np.linalg.norm(view.xyz - true, axis=1) < 10)
    w = truth.depth.shape[1]
    kept = np.isin(view.pixel[:, 1] * w + view.pixel[:, 0], cropped.pixel[:, 1] * w + cropped.pixel[:, 0])
    assert right.sum() > 1000 and kept[right].all()


def test_cloud_view_in_metres_with_estimated_normals(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.linspace(-0.05, 0.05, 60), np.linspace(-0.05, 0.05, 60))
    xyz = np.stack([u.ravel(), v.ravel(), 0.5 + 0.2 * u.ravel()], axis=1)  # a tilted plane 0.5 m ahead
    write_ply(tmp_path / "a.ply", (xyz + rng.normal(0, 1e-6, xyz.shape)).astype(np.float32))
    write_scanset(tmp_path, scanset_doc([{"cloud": "a.ply", "units": "m"}, {"cloud": "a.ply", "name": "b"}]))
    ss = load_scanset(tmp_path)
    view = load_view(ss.views[0])
    np.testing.assert_allclose(view.xyz[:, 2].mean(), 500.0, atol=1.0)
    expected = np.array([-0.2, 0.0, 1.0]) / np.hypot(0.2, 1.0)
    cos = np.abs(view.normals @ expected)
    assert np.median(cos) > 0.999
    np.testing.assert_allclose(np.median(view.size), 100.0 / 59, rtol=0.1)
    assert load_view(ss.views[1]).xyz[:, 2].mean() == pytest.approx(0.5, abs=1e-3)


def test_cloud_view_sizes_that_are_not_sizes_keep_the_estimate(tmp_path: Path) -> None:
    """Another scanner's size field with NaN, zero and negative values: the fusion's grid is
    scaled by sizes, so there the estimated spacing stands; the file's other sizes are kept."""
    u, v = np.meshgrid(np.linspace(-50, 50, 60), np.linspace(-50, 50, 60))
    xyz = np.stack([u.ravel(), v.ravel(), 500.0 + 0.2 * u.ravel()], axis=1).astype(np.float32)
    size = np.full(len(xyz), 3.0, np.float32)
    bad = [1830, 1831, 1832]  # inside the grid, where the estimate is the spacing
    size[bad] = np.nan, 0.0, -1.0
    write_ply(tmp_path / "a.ply", xyz, size=size)
    write_scanset(tmp_path, scanset_doc([{"cloud": "a.ply"}, {"cloud": "a.ply", "name": "b"}]))
    view = load_view(load_scanset(tmp_path).views[0])
    assert np.isfinite(view.size).all() and (view.size > 0).all()
    np.testing.assert_allclose(view.size[bad], 100.0 / 59, rtol=0.1)  # the estimated spacing
    assert (np.delete(view.size, bad) == 3.0).all()


def test_normals_face_the_sensor() -> None:
    rng = np.random.default_rng(2)
    xyz = np.column_stack([rng.uniform(-10, 10, 500), rng.uniform(-10, 10, 500), np.full(500, 100.0)])
    n, _ = estimate_normals(xyz, sensor=np.zeros(3))
    assert np.all(n[:, 2] < -0.99)


def test_capture_view_that_gives_no_points(small: Path, tmp_path: Path) -> None:
    work = tmp_path / "set"
    shutil.copytree(small, work)
    cap = work / "view_01"
    for name in json.loads((cap / "capture.json").read_text())["columns"]:
        shutil.copy(cap / "black.png", cap / name["pattern"])
    shutil.copy(cap / "black.png", cap / "white.png")
    ss = load_scanset(work)
    with pytest.raises(InputError, match=r"^views\[1\] \(view_01\): "):
        load_view(ss.views[1])
