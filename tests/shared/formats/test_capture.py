"""The ``graycode-v1`` capture contract: what it accepts, what it writes, and its errors."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from shared.core.errors import InputError
from shared.formats.capture import (
    CAPTURE_FILE,
    code_bits,
    load_capture,
    numbered_frames,
    opencv_order_capture,
    parse_capture,
    write_capture,
)
from shared.scan.graycode import capture_for_names


def _doc(w: int = 1024, h: int = 768) -> dict[str, Any]:
    doc = capture_for_names(Path("/unused"), w, h).to_json()
    return json.loads(json.dumps(doc))


def test_code_bits() -> None:
    assert [code_bits(n) for n in (2, 3, 4, 5, 768, 1024, 1025)] == [1, 2, 2, 3, 10, 10, 11]


def test_round_trip_keeps_every_field(tmp_path: Path) -> None:
    cap = capture_for_names(tmp_path, 1024, 768)
    cap = type(cap)(**{**cap.__dict__, "rig": tmp_path / "rig.json", "extra": {"simulated": {"scene": "ada"}}})
    path = write_capture(cap)
    assert path == tmp_path / CAPTURE_FILE
    back = load_capture(tmp_path, check=False)
    assert back == cap and back.extra == {"simulated": {"scene": "ada"}}
    doc = json.loads(path.read_text())
    assert doc["white"] == "white.png" and doc["rig"] == "rig.json"  # relative to its own folder
    assert [e["bit"] for e in doc["columns"]] == list(range(9, -1, -1))  # most significant first


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.update(format="graycode-v2"), 'field "format" is \'graycode-v2\''),
        (lambda d: d.pop("white"), 'missing field "white"'),
        (lambda d: d.update(projector={"width": 1024.5, "height": 768}), '"projector.width" must be an integer'),
        (lambda d: d.update(white="../white.png"), "must be a relative path to a file inside the capture folder"),
        (lambda d: d.update(white="/tmp/white.png"), "must be a relative path to a file inside the capture folder"),
        (lambda d: d.update(black="black.gif"), "is not a PNG, TIFF, JPEG or BMP file name"),
        (lambda d: d["columns"][0].update(bit=10), '"columns[0].bit" is 10, but a projector of this size has 10 bits'),
        (lambda d: d["columns"].reverse(), "most significant first"),
        (lambda d: d.update(columns=[]), 'field "columns" must list at least one pattern'),
        (lambda d: d.update(operator="ada"), "unknown field 'operator' at the top level"),
        (lambda d: d["projector"].update(units="mm"), "unknown field 'units' in \"projector\""),
        (lambda d: d["columns"][1].update(inverted="x.png"), "unknown field 'inverted' in \"columns[1]\""),
        (lambda d: d.update(simulated=[1]), 'field "simulated" must be an object'),
        (lambda d: d["projector"].update(width=10**30), '"projector.width" must be an integer in 2..16384'),
        (lambda d: d.update(rig="../rig.json"), 'field "rig" must be a relative path to a file inside the capture folder'),
    ],
)
def test_bad_documents_name_the_file_and_field(tmp_path: Path, change, message: str) -> None:
    doc = _doc()
    change(doc)
    where = tmp_path / CAPTURE_FILE
    with pytest.raises(InputError) as err:
        parse_capture(doc, tmp_path, where)
    assert str(err.value).startswith(f"{where}: ") and message in str(err.value), str(err.value)


def test_finest_bits_may_be_left_out(tmp_path: Path) -> None:
    doc = _doc()
    doc["columns"] = doc["columns"][:7]
    cap = parse_capture(doc, tmp_path)
    assert cap.column_lowest_bit == 3 and cap.column_bits == 10


def test_missing_image_is_named(tmp_path: Path) -> None:
    write_capture(capture_for_names(tmp_path, 64, 32))
    with pytest.raises(InputError, match=r"white\.png: image file is missing"):
        load_capture(tmp_path)


def test_paths_outside_the_folder_cannot_be_written(tmp_path: Path) -> None:
    cap = capture_for_names(tmp_path / "cap", 64, 32)
    cap = type(cap)(**{**cap.__dict__, "white": tmp_path / "elsewhere.png"})
    with pytest.raises(InputError, match="lies outside the capture folder"):
        write_capture(cap)


def test_opencv_order_from_a_relative_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "c0"
    folder.mkdir()
    n = 2 * (code_bits(64) + code_bits(32)) + 2
    for i in range(n):
        (folder / f"graycode_{i:02d}.png").write_bytes(b"x")
    monkeypatch.chdir(tmp_path)
    cap = opencv_order_capture(Path("c0"), numbered_frames(Path("c0")), 64, 32)
    doc = json.loads(write_capture(cap).read_text())
    assert doc["white"] == f"graycode_{n - 2:02d}.png" and doc["black"] == f"graycode_{n - 1:02d}.png"
    assert doc["columns"][0] == {"bit": 5, "pattern": "graycode_00.png", "inverse": "graycode_01.png"}
    assert doc["rows"][0]["pattern"] == f"graycode_{2 * code_bits(64):02d}.png"
    assert load_capture(folder, check=False).white == folder.absolute() / f"graycode_{n - 2:02d}.png"


def test_numbered_frames_sort_by_number_and_refuse_duplicates(tmp_path: Path) -> None:
    for name in ("f_10.png", "f_2.png", "f_1.png"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in numbered_frames(tmp_path)] == ["f_1.png", "f_2.png", "f_10.png"]
    (tmp_path / "g_2.png").write_bytes(b"x")
    with pytest.raises(InputError, match="distinct number"):
        numbered_frames(tmp_path)
