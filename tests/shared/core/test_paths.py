"""shared.core.paths: the confinement rule's plain cases and the bounded, non-blocking reads."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from shared.core.errors import InputError
from shared.core.paths import confine, open_regular, read_bounded


def test_inside_paths_pass_and_links_inside_are_followed(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.png").write_bytes(b"x")
    (tmp_path / "alias.png").symlink_to(tmp_path / "sub" / "a.png")
    assert confine(tmp_path, "sub/a.png", where="w") == tmp_path / "sub" / "a.png"
    assert confine(tmp_path, "alias.png", where="w") == tmp_path / "alias.png"
    assert confine(tmp_path, "sub", where="w", kind="dir") == tmp_path / "sub"
    assert confine(tmp_path, "later.png", where="w", check=False) == tmp_path / "later.png"


@pytest.mark.parametrize("value", ["", None, 3, "/etc/passwd", "../x", "a/../../x", "~/x", "a\\b", "a\x00b"])
def test_malformed_or_outside_values_share_one_text(tmp_path: Path, value: object) -> None:
    with pytest.raises(InputError) as err:
        confine(tmp_path, value, where="views[0].cloud", folder="scan set folder")
    assert str(err.value).startswith("views[0].cloud: must be a relative path to a file inside the scan set folder, got ")


def test_inside_problems_are_said_plainly(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "pipe")
    (tmp_path / "dir").mkdir()
    for value, kind, problem in (("gone.png", "file", "not found in the submission folder"),
                                 ("pipe", "file", "is not a regular file"), ("dir", "file", "is not a regular file"),
                                 ("pipe", "dir", "is not a folder"), ("pipe", "any", "neither a regular file nor a folder")):
        with pytest.raises(InputError, match=problem):
            confine(tmp_path, value, where="f", kind=kind)


def test_reads_are_bounded_and_never_block(tmp_path: Path) -> None:
    (tmp_path / "small").write_bytes(b"12345")
    assert read_bounded(tmp_path / "small", "small", 5) == b"12345"
    with pytest.raises(InputError, match=r"^small: file of 5 bytes is too large \(at most 4\)$"):
        read_bounded(tmp_path / "small", "small", 4)
    os.mkfifo(tmp_path / "pipe")  # no writer: a blocking open would wait for ever
    for target in (tmp_path / "pipe", Path("/dev/zero"), tmp_path):
        with pytest.raises(InputError, match="is not a regular file"):
            open_regular(target, "x")
    with pytest.raises(InputError, match="^x: file not found$"):
        read_bounded(tmp_path / "none", "x", 10)
