"""Fixtures of the codec tests: range images of the virtual rig and of the five real captures."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from tests.support import real_ranges


@pytest.fixture(scope="session")
def sim_range(sim_capture_factory: Callable[..., Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``range.npz`` of the virtual rig's ``spheres`` scene scanned at 320x240 (holes, edges, curvature)."""
    from shared.scan.pipeline import scan  # numba kernels: imported when the fixture runs

    cap = sim_capture_factory("spheres", size=(320, 240), projector=(256, 192), seed=1)
    out = tmp_path_factory.mktemp("sim-scan")
    scan(cap, out)
    return out / "range.npz"


@pytest.fixture(scope="session")
def real_range_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    if not real_ranges.available():
        pytest.skip(f"real captures not found at {real_ranges.REAL}")
    return real_ranges.scan_real_ranges(tmp_path_factory.mktemp("real-scans"))
