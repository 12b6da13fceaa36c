"""``graylight tiles``: the same tiles as the stage, the caller's garbage collector left as it
was, one-line errors."""

from __future__ import annotations

import gc
from pathlib import Path

import pytest

from services.cli.main import main
from shared.render.octree import build_tiles
from tests.support.clouds import synthetic_scan


@pytest.fixture(scope="module")
def cloud(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthetic_scan(tmp_path_factory.mktemp("cli_render") / "cloud.ply", 30_000, seed=7)


def test_tiles_writes_the_stage_s_tiles(cloud: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    build_tiles(cloud, tmp_path / "stage", workers=1)
    assert gc.isenabled()
    assert main(["tiles", str(cloud), "--out", str(tmp_path / "cli")]) == 0
    assert gc.isenabled()  # the command runs without collections, and gives them back
    printed = capsys.readouterr().out
    assert "30000 points" in printed or "points in" in printed
    assert f"tiles: {tmp_path / 'cli'}" in printed
    for name in ("octree.bin", "hierarchy.bin", "metadata.json"):
        assert (tmp_path / "cli" / name).read_bytes() == (tmp_path / "stage" / name).read_bytes(), name


def test_tiles_errors_are_one_line(cloud: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["tiles", str(cloud), "--out", str(tmp_path / "t"), "--workers", "0"]) == 1
    err = capsys.readouterr().err.strip()
    assert "--workers" in err and "\n" not in err
    assert main(["tiles", str(tmp_path / "nope.ply"), "--out", str(tmp_path / "t")]) == 1
    err = capsys.readouterr().err.strip()
    assert "nope.ply" in err and "\n" not in err
    assert gc.isenabled()
    assert not (tmp_path / "t").exists()
