"""The rig contract: camera, projector, and the pose between them, with one-line errors."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.rig import check_rig_matches, load_rig, parse_rig, save_rig


def _doc() -> dict[str, Any]:
    a = np.deg2rad(12.0)
    R = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    return {
        "units": "mm",
        "camera": {"width": 2048, "height": 1536, "K": [[2400, 0, 1024], [0, 2400, 768], [0, 0, 1]],
                   "dist": [0.01, -0.02, 0.0, 0.0, 0.0]},
        "projector": {"width": 1024, "height": 768, "K": [[1500, 0, 512], [0, 1500, 700], [0, 0, 1]]},
        "R": R,
        "T": [-220.0, 0.0, 30.0],
    }  # fmt: skip


def test_round_trip(tmp_path: Path) -> None:
    rig = parse_rig(_doc())
    back = load_rig(save_rig(rig, tmp_path / "rig.json"))
    assert np.array_equal(back.R, rig.R) and np.array_equal(back.T, rig.T) and back.units == "mm"
    assert np.array_equal(back.camera.K, rig.camera.K) and back.projector.dist.tolist() == [0.0] * 5
    assert json.loads((tmp_path / "rig.json").read_text())["camera"]["width"] == 2048


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.pop("T"), 'missing field "T"'),
        (lambda d: d.update(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), 'field "R" is not a rotation matrix'),
        (lambda d: d.update(R=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]), 'field "R" is not a rotation matrix'),
        (lambda d: d.update(T=[0, 0, 0]), 'field "T" is zero'),
        (lambda d: d["camera"].update(K=[[1, 0], [0, 1]]), 'field "camera.K" has shape (2, 2)'),
        (lambda d: d["camera"].update(K=[[-5, 0, 1], [0, 5, 1], [0, 0, 1]]), 'field "camera.K" is not a camera matrix'),
        (lambda d: d["projector"].update(dist=[0.1, 0.2, 0.3]), 'field "projector.dist" must be OpenCV distortion'),
        (lambda d: d["projector"].update(width=0), 'field "projector.width" must be an integer in 2..65536'),
        (lambda d: d.update(T=[float("nan"), 0, 0]), 'field "T" holds NaN'),
        (lambda d: d.update(units=""), 'field "units" must be a string'),
        # units go into every output's PLY header and paradata: printable ASCII only
        (lambda d: d.update(units="mm\nend_header"), 'field "units" must be a string'),
        (lambda d: d.update(units="µm"), 'field "units" must be a string'),
        (lambda d: d.update(scale=2), "unknown field 'scale' at the top level"),
        (lambda d: d["camera"].update(k=[1]), "unknown field 'k' in \"camera\""),
        (lambda d: d["camera"]["K"][0].__setitem__(0, 1e308), 'field "camera.K": focal length and skew must be at most'),
        (lambda d: d["camera"]["K"][0].__setitem__(2, 1e12), 'field "camera.K": principal point'),
        (lambda d: d["projector"].update(height=10**30), 'field "projector.height" must be an integer in 2..65536'),
        (lambda d: d["camera"].update(width=1), 'field "camera.width" must be an integer in 2..65536'),
        (lambda d: d["camera"].update(dist=[1e300, 0, 0, 0, 0]), 'field "camera.dist": coefficients must be at most'),
        (lambda d: d["camera"].update(dist=[True, 0, 0, 0, 0]), 'field "camera.dist" must be OpenCV distortion'),
        (lambda d: d.update(T=[1e300, 0, 0]), 'field "T": a baseline of'),
        # integers past float's range (a library caller's document: files are parsed with bounded
        # numbers) were a bare OverflowError
        (lambda d: d["camera"]["K"][0].__setitem__(0, 10**400), 'field "camera.K" must be numbers of shape (3, 3)'),
        (lambda d: d["camera"].update(dist=[10**400, 0, 0, 0, 0]), 'field "camera.dist" must be OpenCV distortion'),
        (lambda d: d.update(T=[10**400, 0, 0]), 'field "T" must be numbers of shape (3,)'),
    ],
)
def test_bad_rigs_name_the_field(change, message: str) -> None:
    doc = _doc()
    change(doc)
    with pytest.raises(InputError) as err:
        parse_rig(doc, "my/rig.json")
    assert str(err.value).startswith("my/rig.json: ") and message in str(err.value), str(err.value)


def test_sizes_must_match_the_capture() -> None:
    rig = parse_rig(_doc())
    check_rig_matches(rig, (2048, 1536), (1024, 768), "cap")
    with pytest.raises(InputError, match="rig camera is 2048x1536 but the images are 1024x768"):
        check_rig_matches(rig, (1024, 768), (1024, 768), "cap")
    with pytest.raises(InputError, match="rig projector is 1024x768"):
        check_rig_matches(rig, (2048, 1536), (800, 600), "cap")


def test_uploaded_rig_over_the_limit_is_too_large_not_malformed() -> None:
    """An uploaded rig of more than 1 MiB is refused as too large (it used to be cut at 1 MiB and
    reported as malformed JSON)."""
    from shared.formats.rig import MAX_RIG_BYTES, parse_rig_bytes

    doc = _doc()
    ok = parse_rig_bytes(json.dumps(doc).encode(), "rig")
    assert ok.camera.width == doc["camera"]["width"]
    big = json.dumps(doc).encode() + b" " * MAX_RIG_BYTES
    with pytest.raises(InputError, match=r"^rig: JSON document of \d+ bytes is too large"):
        parse_rig_bytes(big, "rig")
    deep = b"[" * 10000 + b"]" * 10000
    with pytest.raises(InputError, match=r"^rig: JSON nested 10000 levels deep"):
        parse_rig_bytes(deep, "rig")
