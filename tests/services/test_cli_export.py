"""``graylight export``: every format from the command line, one-line errors, nothing half-written."""

from __future__ import annotations

from pathlib import Path

import laspy
import pytest

from services.cli.main import main
from tests.support.clouds import scan_surface


@pytest.fixture(scope="module")
def cloud(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return scan_surface(tmp_path_factory.mktemp("cli_export") / "cloud.ply", width=120, height=90)


@pytest.mark.parametrize("fmt", ["laz", "copc", "e57", "ply", "las"])
def test_export_each_format(
    fmt: str, cloud: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / f"cloud.{fmt}"
    assert main(["export", str(cloud), "--format", fmt, "--out", str(out), "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and "points" in printed
    assert out.is_file() and out.stat().st_size > 0
    # No temporary left beside it; the run's paradata is (services/cli/provenance.py).
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name, f"{out.name}.paradata.json"]
    if fmt in ("laz", "las"):
        assert laspy.read(out).header.point_count > 1000
    if fmt == "copc":
        with laspy.CopcReader.open(out) as r:
            assert len(r.query()) == r.header.point_count > 1000


def test_export_errors_are_one_line(cloud: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        main(["export", str(tmp_path / "nope.ply"), "--format", "laz", "--out", str(tmp_path / "x.laz")]) == 1
    )
    err = capsys.readouterr().err.strip()
    assert "nope.ply" in err and "\n" not in err
    bad = tmp_path / "bad.ply"
    bad.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n"
    )
    assert main(["export", str(bad), "--format", "copc", "--out", str(tmp_path / "y.laz")]) == 1
    err = capsys.readouterr().err.strip()
    assert "bad.ply" in err and "\n" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.ply"]
    with pytest.raises(SystemExit):
        main(["export", str(cloud), "--format", "xyz", "--out", str(tmp_path / "z.xyz")])
