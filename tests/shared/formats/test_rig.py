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
        (lambda d: d["projector"].update(width=0), 'field "projector.width" must be a positive integer'),
        (lambda d: d.update(T=[float("nan"), 0, 0]), 'field "T" holds NaN'),
        (lambda d: d.update(units=""), 'field "units" must be a string'),
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
