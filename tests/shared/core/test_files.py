"""Atomic outputs and JSON inputs: nothing half-written, errors that name the file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shared.core.errors import InputError
from shared.core.files import atomic_file, read_json, write_json_atomic


def test_atomic_file_renames_on_success_and_leaves_nothing_on_failure(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "out.bin"
    with atomic_file(target, suffix=".bin") as tmp:
        assert tmp.parent == target.parent and tmp.name.endswith(".bin") and tmp != target
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new"
    with pytest.raises(RuntimeError), atomic_file(target) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("the writer failed")
    assert target.read_bytes() == b"new"  # the old file is untouched
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.bin"]


def test_json_round_trip(tmp_path: Path) -> None:
    doc = {"a": [1, 2.5, "x"], "b": None}
    assert read_json(write_json_atomic(tmp_path / "d.json", doc), "missing") == doc


@pytest.mark.parametrize(
    ("content", "message"),
    [(None, "the thing is missing"), (b"{\"a\": 1,,}", "malformed JSON at line 1 column 9"), (b"\xff\xfe{}", "not UTF-8")],
)
def test_bad_json_names_the_file(tmp_path: Path, content: bytes | None, message: str) -> None:
    p = tmp_path / "in.json"
    if content is not None:
        p.write_bytes(content)
    with pytest.raises(InputError) as err:
        read_json(p, "the thing is missing")
    assert str(err.value).startswith(f"{p}: ") and message in str(err.value)
    assert json.dumps(err.value.where) == json.dumps(str(p))
