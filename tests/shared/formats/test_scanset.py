"""The scan-set contract graylight-scanset-v1: what loads, and a one-line error naming the view or field
for every bad input the issue lists."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.ply import write_ply
from shared.formats.scanset import load_scanset, scanset_doc, write_scanset
from tests.support.scansets import cached_scanset

# roi: the contract's crop sphere is read here (a simulated set has none by default, as a real capture).
TINY = {"size": (64, 48), "projector": (64, 48), "views": 3, "roi": True}


@pytest.fixture(scope="module")
def tiny(scanset_factory: Callable[..., Path]) -> Path:
    return scanset_factory(**TINY)


@pytest.fixture
def work(tiny: Path, tmp_path: Path) -> Path:
    """A private copy of the tiny scan set that a test may break."""
    dst = tmp_path / "set"
    shutil.copytree(tiny, dst)
    return dst


def _doc(folder: Path) -> dict:
    return json.loads((folder / "scanset.json").read_text())


def _write(folder: Path, doc: dict) -> None:
    (folder / "scanset.json").write_text(json.dumps(doc))


def _error(folder: Path) -> str:
    with pytest.raises(InputError) as exc:
        load_scanset(folder)
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_simulated_scanset_loads(tiny: Path) -> None:
    ss = load_scanset(tiny)
    assert len(ss) == 3 and [v.name for v in ss.views] == ["view_00", "view_01", "view_02"]
    assert all(v.kind == "capture" and v.rig is not None and v.units == "mm" for v in ss.views)
    np.testing.assert_allclose(ss.turntable_deg, [0.0, 120.0, 240.0])
    assert ss.roi is not None and ss.roi.radius > 0


def test_cloud_views_and_poses(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    for k in range(2):
        write_ply(tmp_path / f"scan_{k}.ply", rng.normal(size=(50, 3)).astype(np.float32))
    R = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    doc = scanset_doc([{"cloud": "scan_0.ply", "units": "m"},
                       {"cloud": "scan_1.ply", "pose": {"R": R, "T": [1, 2, 3]}}])
    write_scanset(tmp_path, doc)
    ss = load_scanset(tmp_path / "scanset.json")
    assert ss.views[0].units == "m" and ss.views[0].scale_mm == 1000.0 and ss.views[0].pose is None
    np.testing.assert_allclose(ss.views[1].pose[0], R)
    np.testing.assert_allclose(ss.views[1].pose[1], [1, 2, 3])


def test_fewer_than_two_views(work: Path) -> None:
    doc = _doc(work)
    doc["views"] = doc["views"][:1]
    doc.pop("turntable")
    _write(work, doc)
    assert "views: a scan set needs 2..1000 views, got 1" in _error(work)


def test_missing_view(work: Path) -> None:
    shutil.rmtree(work / "view_01")
    msg = _error(work)
    assert msg == "views[1].capture: 'view_01' not found in the scan set folder"


def test_corrupt_capture_view(work: Path) -> None:
    (work / "view_02" / "capture.json").write_text("{ not json")
    assert _error(work).startswith("views[2] (view_02): bad capture:")


def test_corrupt_image_in_a_view(work: Path) -> None:
    (work / "view_01" / "white.png").write_bytes(b"\x89PNG broken")
    assert _error(work).startswith("views[1] (view_01)")


def test_corrupt_cloud_view(work: Path, tmp_path: Path) -> None:
    (work / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n")
    doc = _doc(work)
    doc["views"].append({"cloud": "bad.ply"})
    doc.pop("turntable")
    _write(work, doc)
    msg = _error(work)
    assert msg.startswith("views[3] (bad): bad point cloud: bad.ply: ") and "'y'" in msg


def test_different_image_sizes_without_own_rig(work: Path, tmp_path: Path) -> None:
    other = cached_scanset(tmp_path / "other", size=(80, 60), projector=(64, 48), views=2)
    shutil.copytree(other / "view_01", work / "view_03")
    cap = json.loads((work / "view_03" / "capture.json").read_text())
    cap.pop("rig")  # the shared rig applies: its camera is 64x48
    (work / "view_03" / "capture.json").write_text(json.dumps(cap))
    doc = _doc(work)
    doc["views"].append({"capture": "view_03"})
    doc.pop("turntable")
    _write(work, doc)
    msg = _error(work)
    assert msg.startswith("views[3] (view_03): images are 80x60 but views[0] (view_00) are 64x48")


def test_different_image_sizes_with_own_rig_load(work: Path, tmp_path: Path) -> None:
    other = cached_scanset(tmp_path / "other", size=(80, 60), projector=(64, 48), views=2)
    shutil.copytree(other / "view_01", work / "view_03")  # keeps its own rig.json
    doc = _doc(work)
    doc["views"].append({"capture": "view_03"})
    doc.pop("turntable")
    _write(work, doc)
    ss = load_scanset(work)
    assert ss.views[3].rig == work / "view_03" / "rig.json"


def test_pose_that_is_not_a_rotation(work: Path) -> None:
    doc = _doc(work)
    doc["views"][2]["pose"] = {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "T": [0, 0, 0]}
    _write(work, doc)
    msg = _error(work)
    assert msg.startswith("views[2] (view_02).pose.R: is not a rotation")


def test_pose_that_is_a_reflection(work: Path) -> None:
    doc = _doc(work)
    doc["views"][1]["pose"] = {"R": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [0, 0, 0]}
    _write(work, doc)
    assert "det = -1" in _error(work)


def test_pose_with_a_bad_shape(work: Path) -> None:
    doc = _doc(work)
    doc["views"][1]["pose"] = {"R": [[1, 0], [0, 1], [0, 0]], "T": [0, 0, 0]}
    _write(work, doc)
    assert _error(work).startswith("views[1] (view_01).pose.R: must be a list of 3 numbers")


def test_turntable_angles_do_not_match_views(work: Path) -> None:
    doc = _doc(work)
    doc["turntable"]["angles_deg"] = [0, 120]
    _write(work, doc)
    assert _error(work) == "turntable.angles_deg: must give one angle per view (3), got 2"


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (lambda d: d.update(format="graycode-v1"), "format: must be 'graylight-scanset-v1'"),
        (lambda d: d["views"][0].update(cloud="x.ply"), 'views[0]: must name exactly one of "capture"'),
        (lambda d: d["views"][1].update(units="m"), "views[1].units: applies to cloud views only"),
        (lambda d: d.update(roi={"center": [0, 0], "radius": 5}), "roi.center: must be a list of 3 numbers"),
        (lambda d: d.update(roi={"center": [0, 0, 0], "radius": -5}), "roi.radius: must be a positive number"),
        (lambda d: d["views"][2].update(name="view_00"), "views[2] (view_00): view name 'view_00' is used twice"),
        (lambda d: d.update(rig="nowhere.json"), "rig: 'nowhere.json' not found in the scan set folder"),
        (lambda d: d["turntable"].update(angles_deg=[0, "a", 2]), "turntable.angles_deg: must hold numbers only"),
        # Strict: every unknown key is named, with where it belongs when that is known.
        (lambda d: d.update(units="m"), "units: unknown field: goes in each cloud view"),
        (lambda d: d.update(angles_deg=[0, 1, 2]), 'angles_deg: unknown field: goes in "turntable"'),
        (lambda d: d.update(comment="x"), "comment: unknown field: allowed here: format, rig, views"),
        (lambda d: d["views"][0].update(rig="rig.json"), "views[0].rig: unknown field: allowed here: capture, name, pose"),
        (lambda d: d["views"][0].update(pose={"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [0, 0, 0], "t": 1}),
         "pose.t: unknown field"),
        (lambda d: d["turntable"].update(axis=[0, 1, 0]), "turntable.axis: unknown field: allowed here: angles_deg"),
        (lambda d: d.update(roi={"center": [0, 0, 0], "radius": 5, "units": "m"}), "roi.units: unknown field"),
        (lambda d: d.update(simulated="yes"), "simulated: must be an object"),
        # Numbers bounded at intake.
        (lambda d: d.update(roi={"center": [0, 0, 1e30], "radius": 5}), "roi.center: must hold numbers of magnitude"),
        (lambda d: d.update(roi={"center": [0, 0, 0], "radius": 1e300}), "roi.radius: must be a positive number"),
        (lambda d: d["turntable"].update(angles_deg=[0, 1e9, 2]), "turntable.angles_deg: must hold numbers of magnitude"),
        (lambda d: d["views"][0].update(name=7), "views[0].name: must be a string"),
    ],
)
def test_bad_fields(work: Path, change, expected: str) -> None:
    doc = _doc(work)
    change(doc)
    _write(work, doc)
    assert expected in _error(work)


def test_bad_cloud_units(tmp_path: Path) -> None:
    write_ply(tmp_path / "a.ply", np.zeros((5, 3), np.float32))
    _write(tmp_path, scanset_doc([{"cloud": "a.ply", "units": "inch"}, {"cloud": "a.ply", "name": "b"}]))
    assert _error(tmp_path).startswith("views[0] (a).units: must be one of mm, m")


def test_cloud_units_that_are_not_a_string_are_refused(tmp_path: Path) -> None:
    # a list or an object (valid JSON) was looked up in the units table: a bare TypeError
    write_ply(tmp_path / "a.ply", np.zeros((5, 3), np.float32))
    for units in (["mm"], {"mm": 1}):
        _write(tmp_path, scanset_doc([{"cloud": "a.ply", "units": units}, {"cloud": "a.ply", "name": "b"}]))
        assert _error(tmp_path).startswith("views[0] (a).units: must be one of mm, m")


def test_top_level_units_is_refused_not_read_as_mm(tmp_path: Path) -> None:
    """Issue 22: cloud views with ``units`` at the top level were silently read as millimetres."""
    write_ply(tmp_path / "a.ply", np.zeros((5, 3), np.float32))
    doc = scanset_doc([{"cloud": "a.ply"}, {"cloud": "a.ply", "name": "b"}])
    doc["units"] = "m"
    _write(tmp_path, doc)
    msg = _error(tmp_path)
    assert msg.startswith("units: unknown field: goes in each cloud view") and '"units": "m"' in msg, msg


def test_missing_scanset_json(tmp_path: Path) -> None:
    assert "scan set description not found" in _error(tmp_path)
