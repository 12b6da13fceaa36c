"""``graylight merge`` and ``graylight simulate --views``: outputs, the one-line errors, exit status,
nothing half-written."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

from services.cli.main import main
from shared.service.jobs import MESH_LOD_FILES


@pytest.fixture(scope="module")
def small_set(scanset_factory: Callable[..., Path]) -> Path:
    return scanset_factory(views=8, size=(320, 240), projector=(256, 192))


def test_merge_writes_every_output(small_set: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["merge", str(small_set), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "8 of 8 views registered" in text and "loop closure" in text and "rotation axis" in text
    names = {p.name for p in out.iterdir()}
    assert {"merged.ply", "registration.json", "mesh.ply", "mesh.glb", "mesh_lod1.glb", "mesh_lod2.glb",
            "mesh_lod3.glb", "report.json", "ranges"} <= names
    assert not [n for n in names if n.startswith(".")]
    # The levels the job service publishes by name are exactly the ones a merge writes.
    assert {n for n in names if n.startswith("mesh_lod")} == set(MESH_LOD_FILES)
    reg = json.loads((out / "registration.json").read_text())
    for v in reg["views"]:
        R = np.array(v["R"])
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
        assert {"T", "rms_mm", "overlap", "inlier_share"} <= set(v)
    assert reg["method"] and reg["turntable_axis"] and reg["loop_closure"]
    glb = trimesh.load(out / "mesh.glb", force="mesh", process=False)
    assert len(glb.faces) > 1000 and glb.visual.kind == "vertex"


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (lambda d: d.update(views=d["views"][:1]), "views: a scan set needs 2..1000 views"),
        (lambda d: d["views"][1]["pose"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]),
         "views[1] (view_01).pose.R: is not a rotation"),
        (lambda d: d["turntable"].update(angles_deg=[0, 90]), "turntable.angles_deg: must give one angle per view (8)"),
        (lambda d: d["views"][2].update(capture="view_09"), "views[2].capture: 'view_09' not found in the scan set folder"),
    ],
)
def test_bad_scan_sets_fail_in_one_line(small_set: Path, tmp_path: Path, change, expected: str,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    work = tmp_path / "set"
    shutil.copytree(small_set, work)
    doc = json.loads((work / "scanset.json").read_text())
    doc["views"][1]["pose"] = {"R": np.eye(3).tolist(), "T": [0, 0, 0]}
    change(doc)
    (work / "scanset.json").write_text(json.dumps(doc))
    out = tmp_path / "out"
    out.mkdir()
    assert main(["merge", str(work), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("graylight merge: error: ") and expected in err and "\n" not in err
    assert list(out.iterdir()) == []


def test_simulate_views_writes_a_scan_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "orbit"
    assert main(["simulate", "--scene", "bunny", "--views", "2", "--orbit", "--size", "64x48", "--projector", "64x48",
                 "--out", str(out)]) == 0
    doc = json.loads((out / "scanset.json").read_text())
    assert doc["format"] == "graylight-scanset-v1" and len(doc["views"]) == 2 and "turntable" not in doc
    with np.load(out / "truth.npz") as z:
        assert z["poses"].shape == (2, 4, 4)
    assert main(["simulate", "--scene", "plane", "--views", "2", "--out", str(tmp_path / "x")]) == 1
    assert "is not a mesh on a floor" in capsys.readouterr().err
