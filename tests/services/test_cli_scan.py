"""``graylight scan / patterns / import-sequence``: results, and one-line errors on bad input."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.cli.main import main
from shared.core.datapaths import shared_data_dir
from shared.formats.capture import load_capture
from shared.formats.ply import read_ply
from tests.support.links import place_file
from tests.support.synthetic_plane import render_plane_capture

REPO = Path(__file__).resolve().parents[2]
REAL = shared_data_dir() / "procam-kamino410"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "capture"
    render_plane_capture(out, (160, 120), (40, 30), seed=4)
    return out


def test_scan_command(tmp_path: Path, tiny: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["scan", str(tiny), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert str(out / "cloud.ply") in printed and str(out / "report.json") in printed
    report = json.loads((out / "report.json").read_text())
    assert len(read_ply(out / "cloud.ply")) == report["points"] > 1000
    # --rig takes a rig file from anywhere.
    rig = tmp_path / "elsewhere" / "my-rig.json"
    rig.parent.mkdir()
    shutil.copy(tiny / "rig.json", rig)
    assert main(["scan", str(tiny), "--out", str(tmp_path / "out2"), "--rig", str(rig)]) == 0
    assert json.loads((tmp_path / "out2" / "report.json").read_text())["rig"] == str(rig)


def _break_missing(c: Path) -> str:
    (c / "col_03.png").unlink()
    return "col_03.png: image file is missing"


def _break_truncated(c: Path) -> str:
    p = c / "col_02_inv.png"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    return "col_02_inv.png: truncated PNG"


def _break_corrupt(c: Path) -> str:
    (c / "row_01.png").write_bytes(b"\x00garbage, not an image" * 50)
    return "row_01.png: not a PNG, JPEG, TIFF or BMP image"


def _break_sizes(c: Path) -> str:
    cv2.imwrite(str(c / "col_04.png"), np.zeros((60, 80), np.uint8))
    return "col_04.png: image is 80x60, but the white frame white.png is 160x120"


def _break_count(c: Path) -> str:
    doc = json.loads((c / "capture.json").read_text())
    doc["projector"]["width"] = 20  # 5 bits, but 6 column patterns are listed
    (c / "capture.json").write_text(json.dumps(doc))
    return 'capture.json: field "columns[0].bit" is 5, but a projector of this size has 5 bits'


def _break_dark(c: Path) -> str:
    shutil.copy(c / "black.png", c / "white.png")
    return "white.png: nothing is lit by the projector"


def _break_rig_json(c: Path) -> str:
    (c / "rig.json").write_text('{"units": "mm", "camera": {')
    return "rig.json: malformed JSON"


def _break_rig_size(c: Path) -> str:
    doc = json.loads((c / "rig.json").read_text())
    doc["camera"]["width"] = 1280
    (c / "rig.json").write_text(json.dumps(doc))
    return "rig.json: rig camera is 1280x120 but the images are 160x120"


def _break_no_rig(c: Path) -> str:
    doc = json.loads((c / "capture.json").read_text())
    del doc["rig"]
    (c / "capture.json").write_text(json.dumps(doc))
    return 'capture.json: no rig: name one in the "rig" field or pass --rig FILE'


BREAKERS: list[Callable[[Path], str]] = [
    _break_missing, _break_truncated, _break_corrupt, _break_sizes,
    _break_count, _break_dark, _break_rig_json, _break_rig_size, _break_no_rig,
]  # fmt: skip


@pytest.mark.parametrize("breaker", BREAKERS, ids=lambda f: f.__name__.removeprefix("_break_"))
def test_bad_input_one_line_error_nothing_written(
    tmp_path: Path, tiny: Path, capsys: pytest.CaptureFixture[str], breaker: Callable[[Path], str]
) -> None:
    cap = tmp_path / "cap"
    shutil.copytree(tiny, cap)
    expected = breaker(cap)
    out = tmp_path / "out"
    code = main(["scan", str(cap), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert len(err.splitlines()) == 1, err
    assert err.startswith("graylight scan: error: ")
    assert expected in err
    assert not out.exists() or not any(out.iterdir())


def test_subprocess_exit_status_and_message(tmp_path: Path, tiny: Path) -> None:
    cap = tmp_path / "cap"
    shutil.copytree(tiny, cap)
    expected = _break_missing(cap)
    exe = REPO / ".venv" / "bin" / "graylight"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "services.cli.main"]
    proc = subprocess.run([*cmd, "scan", str(cap), "--out", str(tmp_path / "out")], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 1
    assert expected in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_patterns_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "patterns"
    assert main(["patterns", "--projector", "64x48", "--out", str(out)]) == 0
    cap = load_capture(out)
    assert (cap.projector_width, cap.projector_height) == (64, 48)
    assert len(cap.columns) == 6 and len(cap.rows) == 6
    col = cv2.imread(str(cap.columns[-1].pattern), cv2.IMREAD_UNCHANGED)
    inv = cv2.imread(str(cap.columns[-1].inverse), cv2.IMREAD_UNCHANGED)
    assert col.shape == (48, 64) and np.all(col.astype(int) + inv == 255)
    # Finest column bit: Gray code bit 0 of columns 0..3 is 0, 1, 1, 0.
    assert col[0, :4].tolist() == [0, 255, 255, 0]
    assert main(["patterns", "--projector", "64by48", "--out", str(out)]) == 1
    assert "--projector: expected WIDTHxHEIGHT" in capsys.readouterr().err


@pytest.mark.skipif(not (REAL / "capture_0").is_dir(), reason="real captures not available")
def test_import_sequence_on_real_frames(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "seq"
    folder.mkdir()
    for p in sorted((REAL / "capture_0").glob("graycode_*.png")):
        place_file(p, folder / p.name)  # not a symlink: a capture's files lie inside its folder
    assert main(["import-sequence", str(folder), "--projector", "1024x768"]) == 0
    cap = load_capture(folder)
    assert cap.white.name == "graycode_40.png" and cap.black.name == "graycode_41.png"
    assert [e.bit for e in cap.columns] == list(range(9, -1, -1))
    assert cap.columns[0].pattern.name == "graycode_00.png" and cap.columns[0].inverse.name == "graycode_01.png"
    assert cap.rows[0].pattern.name == "graycode_20.png"
    # The wrong projector size means the wrong number of frames: a clear error.
    capsys.readouterr()
    assert main(["import-sequence", str(folder), "--projector", "1920x1080"]) == 1
    assert "42 frames, but a 1920x1080 projector in OpenCV order needs exactly 46" in capsys.readouterr().err
