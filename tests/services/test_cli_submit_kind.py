"""``graylight submit`` picks each job's kind from what it is given (issue 24, defect 1: a scan
set's folder went in as a capture and was refused): ``scanset.json`` at the top (or in the one
folder an archive holds) is a scan set, ``board.json`` a calibration session, else a capture."""

from __future__ import annotations

import tarfile
import zipfile
from pathlib import Path

import pytest

from services.cli.jobs import detect_kind
from shared.service.jobs import GRAPHS


def _tree(root: Path, files: list[str]) -> Path:
    for f in files:
        (root / f).parent.mkdir(parents=True, exist_ok=True)
        (root / f).write_text("{}")
    return root


@pytest.mark.parametrize(("files", "kind"), [
    (["scanset.json", "rig.json", "view_00/capture.json", "view_01/capture.json"], "multiview"),
    (["board.json", "pose_00/capture.json", "pose_01/capture.json"], "calibrate"),
    (["capture.json", "col_00.png", "rig.json"], "scan"),
    (["notes.txt", "old/sets/scanset.json"], "scan"),  # not at the top
])  # fmt: skip
def test_kind_of_a_folder_and_of_its_archives(tmp_path: Path, files: list[str], kind: str) -> None:
    folder = _tree(tmp_path / "set", files)
    assert detect_kind(folder) == kind
    flat = tmp_path / "flat.zip"
    with zipfile.ZipFile(flat, "w") as z:
        for f in files:
            z.write(folder / f, f)
    assert detect_kind(flat) == kind
    wrapped = tmp_path / "wrapped.tar"
    with tarfile.open(wrapped, "w") as t:
        t.add(folder, arcname="mv6")  # one folder archived whole
    assert detect_kind(wrapped) == kind
    assert kind in GRAPHS


def test_what_is_not_an_archive_goes_as_a_capture(tmp_path: Path) -> None:
    junk = tmp_path / "notazip.zip"
    junk.write_bytes(b"not an archive")
    assert detect_kind(junk) == "scan"  # the service names the problem
