"""Fusion on small synthetic views: the free-space test, the grid merge's keys, one point per cell."""

from __future__ import annotations

import numpy as np

from shared.merge._fusion_kernels import cell_keys, free_space_violations
from shared.merge.fusion import fuse_views, sample_confidence
from shared.merge.views import ViewCloud

K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]])


def _plane_view(index: int, z: float, n: int = 48, rgb: int = 100, conf: float = 0.9, at: int = 8) -> ViewCloud:
    """A fronto-parallel n x n patch at depth ``z`` (mm) seen by a 64x48 camera from pixel
    (``at``, ``at - 8``), with its range image."""
    ys, xs = np.mgrid[0:n, 0:n]
    px = np.stack([xs.ravel() + at, ys.ravel() + at - 8], axis=1).astype(np.int32)
    x = (px[:, 0] - K[0, 2]) * z / K[0, 0]
    y = (px[:, 1] - K[1, 2]) * z / K[1, 1]
    xyz = np.stack([x, y, np.full(len(x), z)], axis=1)
    rng = np.full((48, 64), np.nan, np.float32)
    rng[px[:, 1], px[:, 0]] = z
    m = len(xyz)
    return ViewCloud(index=index, name=f"v{index}", xyz=xyz, normals=np.tile(np.float32([0, 0, -1]), (m, 1)),
                     size=np.full(m, z / K[0, 0], np.float32), confidence=np.full(m, conf, np.float32),
                     rgb=np.full((m, 3), rgb, np.uint8), pixel=px, range_image=rng, K=K, dist=np.zeros(5))


def test_free_space_kernel_marks_points_in_front_of_the_surface() -> None:
    zmin = np.full((48, 64), 100.0, np.float32)
    zmin[:, :10] = 0.0  # nothing measured in the first columns
    pts = np.array([[0.0, 0.0, 90.0],  # 10 mm in front of the surface: seen through
                    [0.0, 0.0, 99.9],  # within the tolerance
                    [0.0, 0.0, 120.0],  # behind it
                    [-0.3 * 90.0, 0.0, 90.0],  # projects onto a pixel with nothing measured
                    [50.0, 0.0, 90.0],  # outside the image
                    [0.0, 0.0, -5.0]])  # behind the camera
    bad = np.zeros(len(pts), np.bool_)
    n = free_space_violations(pts, np.full(len(pts), 0.1, np.float32), np.eye(4), K, np.zeros(5), zmin, 0.1, 6.0,
                              0.5, bad)
    assert bad.tolist() == [True, False, False, False, False, False] and n == 1
    # The motion is applied: the same point moved 15 mm back lands behind the surface.
    rel = np.eye(4)
    rel[2, 3] = 15.0
    bad[:] = False
    free_space_violations(pts[:1], np.full(1, 0.1, np.float32), rel, K, np.zeros(5), zmin, 0.1, 6.0, 0.5, bad[:1])
    assert not bad[0]


def test_cell_keys_match_the_numpy_grid() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-20, 30, size=(5000, 3))
    size = rng.choice(np.float32([0.2, 0.41, 0.8]), size=5000)
    normals = rng.normal(size=(5000, 3)).astype(np.float32)
    keys = np.empty(5000, np.int64)
    level = np.empty(5000, np.int64)
    s0 = float(size.min())
    cell_keys(xyz, size, normals, s0, 1.5, keys, level)
    lv = np.floor(np.log2(np.maximum(size.astype(np.float64), s0) / s0) + 0.5).astype(np.int64)
    cell = 1.5 * s0 * np.exp2(lv)
    ijk = np.floor(xyz / cell[:, None]).astype(np.int64)
    ijk -= ijk.min(axis=0)
    dims = ijk.max(axis=0) + 1
    ax = np.argmax(np.abs(normals), axis=1)
    side = ax * 2 + (normals[np.arange(5000), ax] > 0)
    ref = ((((lv - lv.min()) * dims[0] + ijk[:, 0]) * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]) * 6 + side
    np.testing.assert_array_equal(level, lv)
    np.testing.assert_array_equal(keys, ref)


def test_fusion_merges_overlap_and_removes_seen_through_points() -> None:
    a = _plane_view(0, 100.0, rgb=100, conf=0.9)
    b = _plane_view(1, 100.0, rgb=200, conf=0.3)
    # A third view's stray points 20 mm in front of the surface both other views measured.
    c = _plane_view(2, 80.0, n=4, at=30)
    fused = fuse_views([a, b, c], np.stack([np.eye(4)] * 3))
    assert fused.stats["free_space_violations"] == len(c)
    assert fused.stats["samples"] == len(a) + len(b) + len(c)
    assert 2 not in set(fused.view.tolist())
    # The two coincident views merge into about one point per sample-sized cell, confidence-weighted.
    assert len(fused) <= 1.1 * len(a) and fused.stats["points_from_several_views"] > 0.9 * len(fused)
    both = fused.views_per_point == 2
    expect = (0.9 * 100 + 0.3 * 200) / 1.2
    assert np.all(np.abs(fused.rgb[both].astype(float) - expect) <= 1.0)
    # Confidences add up: nothing of the two kept views is lost or counted twice.
    total = float(sample_confidence(a).sum() + sample_confidence(b).sum())
    np.testing.assert_allclose(float(fused.confidence.sum()), total, rtol=1e-5)
    assert np.all(fused.view[both] == 0)  # the most confident view
    np.testing.assert_allclose(fused.xyz[:, 2], 100.0, atol=1e-4)
    np.testing.assert_allclose(fused.normals, np.tile([0, 0, -1], (len(fused), 1)), atol=1e-6)
