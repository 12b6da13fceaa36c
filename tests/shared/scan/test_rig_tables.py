"""The rig's undistortion tables: computed in blocks on threads, kept per process and in the
user's cache folder, they are the same values bit for bit as one OpenCV call gives, and a
triangulation from cached tables equals one from computed tables."""

from __future__ import annotations

import importlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.scan.decode import decode_stack
from shared.sim.simulate import make_rig

tri = importlib.import_module("shared.scan.triangulate")  # the package exports the function of that name


def test_blocks_on_threads_equal_one_call(monkeypatch: pytest.MonkeyPatch) -> None:
    rig = make_rig((160, 120), (96, 72), seed=3)
    dev = rig.projector
    monkeypatch.setattr(tri, "_UNDISTORT_BLOCK", 1000)  # about ten blocks
    a, b, _ = tri._undistort_table(dev, 1)
    xs = np.arange(-tri._MARGIN, dev.width + tri._MARGIN + 1, 1, dtype=np.float64)
    ys = np.arange(-tri._MARGIN, dev.height + tri._MARGIN + 1, 1, dtype=np.float64)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1).reshape(-1, 1, 2)
    one = cv2.undistortPoints(pts, dev.K, dev.dist, criteria=tri._UNDISTORT_CRITERIA).reshape(-1, 2)
    assert np.array_equal(a.ravel(), one[:, 0]) and np.array_equal(b.ravel(), one[:, 1])


def _fields(t) -> dict[str, np.ndarray]:
    return {f: np.asarray(getattr(t, f)) for f in ("cam_a", "cam_b", "cam_stride", "cam_org", "pa", "pb", "pta", "ptb",
                                                   "p_org")}  # fmt: skip


def test_cached_tables_equal_computed_ones(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GRAYLIGHT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(tri, "_TABLES", {})
    rig = make_rig((160, 120), (96, 72), seed=5)
    computed = tri.rig_tables(rig)
    files = list((tmp_path / "rig-tables").glob("*.npz"))
    assert len(files) == 1
    tri._TABLES.clear()
    cached = tri.rig_tables(rig)
    assert cached is not computed  # read from the file, not this process's copy
    a, b = _fields(computed), _fields(cached)
    for name in a:
        assert a[name].dtype == b[name].dtype and a[name].flags.c_contiguous == b[name].flags.c_contiguous, name
        assert np.array_equal(a[name], b[name]), name
    # Another rig gets its own file; a corrupt file is computed again, not trusted.
    tri.rig_tables(make_rig((160, 120), (96, 72), seed=6))
    assert len(list((tmp_path / "rig-tables").glob("*.npz"))) == 2
    files[0].write_bytes(b"not an npz")
    tri._TABLES.clear()
    again = tri.rig_tables(rig)
    assert all(np.array_equal(v, _fields(again)[k]) for k, v in a.items())


def test_triangulation_from_cached_tables_is_identical(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GRAYLIGHT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(tri, "_TABLES", {})
    rig = make_rig((64, 48), (32, 24), seed=2, distortion=True)
    rng = np.random.default_rng(0)
    # A decodable stack is not needed for this: any columns/rows inside the projector will do.
    dec = decode_stack(np.full((48, 64), 200, np.uint8), np.zeros((48, 64), np.uint8),
                       [(4 - k, rng.integers(0, 255, (48, 64), dtype=np.uint8), None) for k in range(5)],
                       projector_size=(32, 24))  # fmt: skip
    dec.column[:] = np.linspace(2, 29, 64, dtype=np.float32)[None, :]
    dec.row[:] = np.linspace(2, 21, 48, dtype=np.float32)[:, None]
    first = tri.triangulate(dec, rig, min_support=0)
    tri._TABLES.clear()
    second = tri.triangulate(dec, rig, min_support=0)
    assert len(first) > 0
    for name in ("xyz", "normals", "size", "pixel", "range_image"):
        assert np.array_equal(getattr(first, name), getattr(second, name), equal_nan=True), name
