"""``graylight compress / decompress``: a scan's range image and cloud round-trip through the CLI
(range.npz as a scan writes it, PLY in the cloud contract); bad input is a one-line error and
leaves nothing behind."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from services.cli.main import main
from shared.compress.range import expected_lossless
from shared.formats.ply import read_header, read_ply


@pytest.fixture(scope="module")
def scanned(sim_capture_factory: Callable[..., Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    from shared.scan.pipeline import scan  # numba kernels: only when the fixture runs

    cap = sim_capture_factory("bunny", size=(256, 192), projector=(128, 96), seed=2)
    out = tmp_path_factory.mktemp("cli-compress") / "scan"
    scan(cap, out)
    return out


def test_range_round_trip_lossless(tmp_path: Path, scanned: Path, capsys: pytest.CaptureFixture[str]) -> None:
    glr = tmp_path / "range.glr"
    assert main(["compress", str(scanned), "--out", str(glr)]) == 0  # the folder: its range.npz
    printed = capsys.readouterr().out
    assert "lossless at quantum 0.02" in printed and str(glr) in printed
    assert main(["decompress", str(glr), "--out", str(tmp_path / "back")]) == 0
    with np.load(scanned / "range.npz") as a, np.load(tmp_path / "back" / "range.npz") as b:
        assert set(b.files) == set(a.files) == {"z", "K", "dist", "units"}
        assert b["z"].dtype == np.float32 and b["z"].shape == a["z"].shape
        np.testing.assert_array_equal(np.isnan(b["z"]), np.isnan(a["z"]))
        m = ~np.isnan(a["z"])
        np.testing.assert_array_equal(b["z"][m], expected_lossless(a["z"], 0.02)[m])
        np.testing.assert_array_equal(b["K"], a["K"])
        np.testing.assert_array_equal(b["dist"], a["dist"])
        assert str(b["units"]) == str(a["units"])


def test_range_round_trip_bounded(tmp_path: Path, scanned: Path) -> None:
    glr = tmp_path / "r.glr"
    assert main(["compress", str(scanned / "range.npz"), "--out", str(glr), "--max-error", "0.25"]) == 0
    assert main(["decompress", str(glr), "--out", str(tmp_path / "z.npz")]) == 0
    with np.load(scanned / "range.npz") as a, np.load(tmp_path / "z.npz") as b:
        m = ~np.isnan(a["z"])
        np.testing.assert_array_equal(np.isnan(b["z"]), ~m)
        assert np.abs(b["z"][m].astype(np.float64) - a["z"][m]).max() <= 0.25
    assert glr.stat().st_size < (scanned / "range.npz").stat().st_size / 4


def test_cloud_round_trip(tmp_path: Path, scanned: Path, capsys: pytest.CaptureFixture[str]) -> None:
    glo = tmp_path / "cloud.glo"
    assert main(["compress", str(scanned / "cloud.ply"), "--out", str(glo), "--max-error", "0.05"]) == 0
    assert "bits per point" in capsys.readouterr().out
    assert main(["decompress", str(glo), "--out", str(tmp_path / "out.ply")]) == 0
    a, b = read_ply(scanned / "cloud.ply"), read_ply(tmp_path / "out.ply")
    assert read_header(tmp_path / "out.ply").dtype == read_header(scanned / "cloud.ply").dtype
    assert len(a) == len(b)
    # Every point has a decoded point within 0.05 on each axis and vice versa (the decoder
    # returns them in octree order).
    for p, q in ((a.xyz, b.xyz), (b.xyz, a.xyz)):
        d, _ = cKDTree(q.astype(np.float64)).query(p.astype(np.float64), p=np.inf)
        assert d.max() <= 0.05
    np.testing.assert_array_equal(np.sort(a.rgb, axis=0), np.sort(b.rgb, axis=0))


def _truncate(tmp: Path, scanned: Path) -> tuple[list[str], str]:
    glr = tmp / "t.glr"
    assert main(["compress", str(scanned), "--out", str(glr), "--max-error", "1"]) == 0
    glr.write_bytes(glr.read_bytes()[:-30])
    return ["decompress", str(glr), "--out", str(tmp / "o" / "range.npz")], f"{glr}: truncated"


def _wrong_magic(tmp: Path, scanned: Path) -> tuple[list[str], str]:
    p = tmp / "x.glr"
    p.write_bytes(b"not a compressed file at all")
    return ["decompress", str(p), "--out", str(tmp / "o")], f"{p}: not a Graylight compressed file"


def _zero_bound(tmp: Path, scanned: Path) -> tuple[list[str], str]:
    return ["compress", str(scanned), "--out", str(tmp / "o" / "x.glr"), "--max-error", "0"], "--max-error: must be a positive number"


def _fine_quantum(tmp: Path, scanned: Path) -> tuple[list[str], str]:
    return ["compress", str(scanned), "--out", str(tmp / "o" / "x.glr"), "--quantum", "1e-7"], "--quantum: 1e-07 is finer than float32 can hold"


def _inf_depth(tmp: Path, scanned: Path) -> tuple[list[str], str]:
    with np.load(scanned / "range.npz") as d:
        parts = {k: d[k] for k in d.files}
    z = parts["z"].copy()
    y, x = np.argwhere(~np.isnan(z))[3]
    z[y, x] = np.inf
    parts["z"] = z
    np.savez(tmp / "bad.npz", **parts)
    return ["compress", str(tmp / "bad.npz"), "--out", str(tmp / "o" / "x.glr")], "infinite depth among the valid samples"


def _not_an_input(tmp: Path, scanned: Path) -> tuple[list[str], str]:
    (tmp / "notes.txt").write_text("hi")
    return ["compress", str(tmp / "notes.txt"), "--out", str(tmp / "o" / "x.glr")], "not a range.npz, a scan folder or a .ply cloud"


@pytest.mark.parametrize("breaker", [_truncate, _wrong_magic, _zero_bound, _fine_quantum, _inf_depth, _not_an_input])
def test_bad_input_one_line_error_nothing_written(breaker, tmp_path: Path, scanned: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    argv, expected = breaker(tmp_path, scanned)
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err, err
    out = tmp_path / "o"
    assert not out.exists() or not any(out.iterdir())


def test_subprocess_exit_status(tmp_path: Path) -> None:
    p = tmp_path / "x.glo"
    p.write_bytes(b"\x89GLC\r\n\x1a\n\x01")
    r = subprocess.run([sys.executable, "-m", "services.cli.main", "decompress", str(p), "--out", str(tmp_path / "o.ply")],
                       capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2])
    assert r.returncode == 1 and "truncated" in r.stderr and not (tmp_path / "o.ply").exists()
