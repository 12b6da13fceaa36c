"""A small simulated turntable set (8 views of the bunny, 320x240), its merge and view 0's scan, made
once per session through the CLI (so each carries its paradata)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from services.cli.main import main


@pytest.fixture(scope="session")
def small_set(scanset_factory: Callable[..., Path]) -> Path:
    return scanset_factory(views=8, size=(320, 240), projector=(256, 192))


@pytest.fixture(scope="session")
def scanned(small_set: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("scan") / "scan"
    assert main(["scan", str(small_set / "view_00"), "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="session")
def merged(small_set: Path, merge_factory: Callable[[Path], Path]) -> Path:
    return merge_factory(small_set)  # the same merge as the multi-view job's comparison
