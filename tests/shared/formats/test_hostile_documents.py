"""Every field of valid contract documents replaced by what a careless or hostile writer sends
(:func:`tests.support.hostile.field_variants`: wrong types, numbers past float's range, NaN,
paths, ragged lists, fields left out): each variant is read or refused with an
:class:`InputError` naming the document, never a bare exception (an unhashable list looked up in
a table, ``int(inf)``, numpy refusing a shape). Found this way: a cloud view's units as a list,
integers past float's range in a rig, infinite sizes and malformed cameras in container headers."""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from shared.calib.board import parse_board
from shared.compress.cloud import decode_cloud, encode_cloud
from shared.compress.range import RangeImage, encode_range, read_range
from shared.core.errors import InputError
from shared.formats.capture import parse_capture
from shared.formats.container import CONTAINER_VERSION, KINDS, MAGIC, TRAILER, open_container
from shared.formats.ply import CLOUD_DTYPE, write_ply
from shared.formats.rig import parse_rig
from shared.formats.scanset import parse_scanset
from shared.sim.simulate import simulate_named
from tests.support.hostile import bare_failures


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("hostile") / "cap"
    simulate_named("spheres", root, size=(64, 48), projector=(32, 24), seed=1)
    return root


def test_capture_json(capture: Path) -> None:
    doc = json.loads((capture / "capture.json").read_text())
    assert not bare_failures(doc, lambda d: parse_capture(d, capture, capture / "capture.json"), InputError)


def test_rig_json(capture: Path) -> None:
    doc = json.loads((capture / "rig.json").read_text())
    assert not bare_failures(doc, lambda d: parse_rig(d, "rig.json"), InputError)


def test_scanset_json(capture: Path, tmp_path: Path) -> None:
    root = tmp_path / "set"
    for name in ("view_00", "view_01"):
        shutil.copytree(capture, root / name)
    write_ply(root / "other.ply", np.zeros((5, 3), np.float32))
    doc = {"format": "graylight-scanset-v1", "rig": "view_00/rig.json",
           "views": [{"capture": "view_00", "pose": {"R": np.eye(3).tolist(), "T": [0, 0, 0]}}, {"capture": "view_01"},
                     {"cloud": "other.ply", "units": "m", "name": "other"}],  # a cloud from another scanner
           "turntable": {"angles_deg": [0, 30, 60]}, "roi": {"center": [0, 0, 500], "radius": 100}}
    parse_scanset(doc, root, check=False)  # the document as written is read
    assert not bare_failures(doc, lambda d: parse_scanset(d, root, check=False), InputError)


@pytest.mark.parametrize("doc", [
    {"kind": "chessboard", "inner_corners": [9, 6], "square_size": 25.0, "units": "mm"},
    {"kind": "charuco", "squares": [7, 5], "square_size": 30.0, "marker_size": 22.0, "dictionary": "DICT_5X5_100",
     "units": "mm"},
])
def test_board_json(doc: dict) -> None:
    # a square size of 2^63 (19 digits, within the parser's number length) was a bare TypeError
    parse_board(doc, "board.json")
    assert not bare_failures(doc, lambda d: parse_board(d, "board.json"), InputError)


@pytest.mark.parametrize("kind", ["range lossless", "range bounded", "cloud"])
def test_container_headers(kind: str) -> None:
    if kind == "cloud":
        rec = np.zeros(2000, CLOUD_DTYPE)
        rec["x"] = np.arange(2000) * 0.1
        blob, reader = encode_cloud(rec, 0.5), decode_cloud
    else:
        z = (500 + np.random.default_rng(0).normal(0, 0.1, (70, 40))).astype(np.float32)
        z[:5, :3] = np.nan
        img = RangeImage(z, np.eye(3) * 300.0, np.zeros(5), "mm")
        kw = {"quantum": 0.02} if kind == "range lossless" else {"max_error": 0.1}
        blob, reader = encode_range(img, **kw), read_range
    header, chunks = open_container(blob)
    payloads = list(chunks)

    def read(meta: object) -> None:
        # the container written by hand around the hostile header: the writer needs a chunk count
        doc = json.dumps(meta).encode()
        out = MAGIC + struct.pack("<HBBII", CONTAINER_VERSION, KINDS[header.kind], 0, len(doc), zlib.crc32(doc)) + doc
        for payload in payloads:
            out += struct.pack("<II", len(payload), zlib.crc32(payload)) + payload
        reader(out + TRAILER)

    assert not bare_failures(header.meta, read, InputError)
