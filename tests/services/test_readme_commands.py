"""The README's command lines, run as a new user types them: relative paths, from a fresh
working folder, with the installed ``graylight`` command.

The embedded-pipeline block of the README is read from the README itself, so a command that
changes there is tested as it is written. Sizes are made small (``--size``, ``--seconds``,
both documented options) to keep the suite fast.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from shared.formats.capture import load_capture
from shared.scan.graycode import pattern_sequence

REPO = Path(__file__).resolve().parents[2]
GRAYLIGHT = Path(sys.executable).with_name("graylight")
SMALL = {"simulate": ["--size", "320x240"], "preview": ["--size", "160x120", "--seconds", "0.5"]}


def _readme_pipeline() -> list[list[str]]:
    """The runnable lines of the README's "The pipeline, embedded" code block."""
    text = (REPO / "README.md").read_text()
    section = text.split("## The pipeline, embedded", 1)[1]
    block = section.split("```", 2)[1]
    lines = []
    for raw in block.splitlines():
        cmd = raw.split("#", 1)[0].strip()
        if not cmd.startswith(".venv/bin/graylight"):
            continue
        words = [w for w in shlex.split(cmd)[1:] if not re.fullmatch(r"\[.*\]", w)]
        # Optional parts written as [--flag VALUE] span two words: drop them whole.
        words = " ".join(words)
        words = re.sub(r"\[[^\]]*\]", "", words).split()
        if any(w.isupper() or w.endswith("_DIR") for w in words):
            continue  # a placeholder (SESSION_DIR, FILE): not runnable as written
        lines.append(words)
    return lines


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    res = subprocess.run([str(GRAYLIGHT), *args], cwd=cwd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, f"graylight {' '.join(args)}: {res.stderr[-2000:]}"
    return res


@pytest.mark.slow
def test_readme_pipeline_runs_with_relative_paths(tmp_path: Path) -> None:
    commands = _readme_pipeline()
    assert [c[0] for c in commands[:4]] == ["simulate", "scan", "tiles", "preview"], commands
    for words in commands:
        _run(words + SMALL.get(words[0], []), tmp_path)
    assert (tmp_path / "scan" / "cloud.ply").stat().st_size > 0
    assert (tmp_path / "tiles" / "metadata.json").exists()
    assert (tmp_path / "preview.mp4").stat().st_size > 0


def test_import_sequence_with_a_relative_folder(tmp_path: Path) -> None:
    """``graylight import-sequence c0`` then ``graylight scan c0``: capture.json paths are
    relative to its own folder, whatever the working folder was."""
    _run(["simulate", "--scene", "plane", "--size", "160x120", "--out", "cap"], tmp_path)
    cap = load_capture(tmp_path / "cap")
    # Re-number the frames in OpenCV's GrayCodePattern order: patterns with inverses, white, black.
    frames = [e for axis in (cap.columns, cap.rows) for c in axis for e in (c.pattern, c.inverse)]
    frames += [cap.white, cap.black]
    (tmp_path / "c0").mkdir()
    for i, src in enumerate(frames):
        shutil.copy(src, tmp_path / "c0" / f"graycode_{i:02d}{src.suffix}")
    w, h = cap.projector_width, cap.projector_height
    assert len(frames) == len(pattern_sequence(w, h))  # the patterns, white and black
    _run(["import-sequence", "c0", "--projector", f"{w}x{h}"], tmp_path)
    doc = json.loads((tmp_path / "c0" / "capture.json").read_text())
    assert doc["white"] == f"graycode_{len(frames) - 2:02d}.png", doc["white"]
    _run(["scan", "c0", "--out", "s0", "--rig", "cap/rig.json"], tmp_path)
    ours = json.loads((tmp_path / "s0" / "report.json").read_text())["points"]
    _run(["scan", "cap", "--out", "s1"], tmp_path)
    assert ours == json.loads((tmp_path / "s1" / "report.json").read_text())["points"] > 1000
