"""Paradata written by the CLI: valid JSON-LD in PROV terms (expanded by pyld), the files by sha256, the
chain of earlier steps, and ``graylight rerun`` reproducing a scan and a merge bit for bit."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from pyld import jsonld

from services.cli.main import main
from shared.core.errors import InputError

# One group with test_publish.py: the session fixtures of conftest.py (the set, its scan and its merge)
# are made on one xdist worker, not once a worker.
pytestmark = pytest.mark.xdist_group("publish")

PROV = "http://www.w3.org/ns/prov#"


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_scan_paradata_is_prov_jsonld(scanned: Path, small_set: Path) -> None:
    doc = json.loads((scanned / "paradata.json").read_text())
    expanded = jsonld.expand(doc)
    nodes = [n for g in expanded for n in g.get("@graph", [g])]
    by_type: dict[str, list[dict]] = {}
    for n in nodes:
        for t in n.get("@type", []):
            by_type.setdefault(t, []).append(n)
    assert len(by_type[PROV + "Activity"]) == 1 and len(by_type[PROV + "SoftwareAgent"]) == 1
    act = by_type[PROV + "Activity"][0]
    assert act[PROV + "startedAtTime"][0]["@type"].endswith("dateTime")
    used = {u["@id"] for u in act[PROV + "used"]}
    entities = {n["@id"]: n for n in by_type[PROV + "Entity"]}
    # Every file of the capture is an input, by its sha256; every output names the activity.
    capture_files = sorted(p for p in (small_set / "view_00").rglob("*") if p.is_file())
    used_sha = {entities[u]["https://graylight.org/ns/paradata#sha256"][0]["@value"] for u in used}
    assert {_sha(p) for p in capture_files} == used_sha
    outs = [e for e in entities.values() if PROV + "wasGeneratedBy" in e]
    assert {e[PROV + "wasGeneratedBy"][0]["@id"] for e in outs} == {act["@id"]}
    sha_by_path = {e["https://graylight.org/ns/paradata#relativePath"][0]["@value"]:
                   e["https://graylight.org/ns/paradata#sha256"][0]["@value"] for e in outs}
    assert sha_by_path["cloud.ply"] == _sha(scanned / "cloud.ply")
    assert sha_by_path["range.npz"] == _sha(scanned / "range.npz")
    # Parameters as given and as defaulted, the rig's figures, the software; a summary for people.
    assert doc["@graph"][1]["command"][0] == "scan"
    params = next(n for n in doc["@graph"] if n["@id"] == doc["run"])["parameters"]
    assert params["rig"] is None and Path(params["capture"]).is_absolute()
    rig = next(n for n in doc["@graph"] if n.get("label") == "rig.json")["rig"]
    assert rig["units"] == "mm" and rig["baseline"] > 0
    agent = doc["@graph"][0]
    assert agent["version"] and "numpy" in agent["libraries"]
    assert "graylight scan" in doc["summary"][0] and "cloud.ply" in doc["summary"][0]


def test_rerun_reproduces_a_scan(scanned: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    again = tmp_path / "again"
    assert main(["rerun", str(scanned / "paradata.json"), "--out", str(again)]) == 0
    for name in ("cloud.ply", "range.npz"):
        assert _sha(again / name) == _sha(scanned / name)
    assert "reproduced: 2 of 3" in capsys.readouterr().out


def test_rerun_refuses_changed_inputs(small_set: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = tmp_path / "cap"
    shutil.copytree(small_set / "view_00", cap)
    assert main(["scan", str(cap), "--out", str(tmp_path / "scan")]) == 0
    img = sorted(cap.glob("*.png"))[3]
    img.write_bytes(img.read_bytes() + b"\0")
    capsys.readouterr()
    assert main(["rerun", str(tmp_path / "scan" / "paradata.json"), "--out", str(tmp_path / "again")]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"graylight rerun: error: {img}: input changed since the recorded run (sha256 differs)"
    assert not (tmp_path / "again").exists()


def test_rerun_refuses_what_is_not_paradata(scanned: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "p.json"
    bad.write_text(json.dumps({"format": "something-else"}))
    assert main(["rerun", str(bad), "--out", str(tmp_path / "x")]) == 1
    assert capsys.readouterr().err.strip() == f"graylight rerun: error: {bad}: format: not a graylight-paradata-v1 document"


def test_later_steps_carry_the_earlier_ones(scanned: Path, tmp_path: Path) -> None:
    tiles = tmp_path / "tiles"
    assert main(["tiles", str(scanned / "cloud.ply"), "--out", str(tiles)]) == 0
    doc = json.loads((tiles / "paradata.json").read_text())
    acts = [n for n in doc["@graph"] if n.get("@type") == "Activity"]
    assert sorted(a["stage"] for a in acts) == ["scan", "tiles"]
    scan_id = next(a["@id"] for a in acts if a["stage"] == "scan")
    this = next(a for a in acts if a["@id"] == doc["run"])
    assert this["wasInformedBy"] == [scan_id] and len(doc["summary"]) == 2
    jsonld.expand(doc)


@pytest.mark.slow
def test_rerun_reproduces_a_merge(merged: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    first, again = merged, tmp_path / "again"
    assert main(["rerun", str(first / "paradata.json"), "--out", str(again)]) == 0
    files = [p.relative_to(first) for p in sorted(first.rglob("*")) if p.is_file() and p.suffix in (".ply", ".glb", ".npz")]
    assert len(files) >= 10
    for rel in files:
        assert _sha(again / rel) == _sha(first / rel), rel
    assert "2 records equal but for timings" in capsys.readouterr().out


def test_rig_figures_of_a_json_file_that_is_not_quite_a_rig(tmp_path: Path) -> None:
    """Paradata tries every JSON file of an input folder as a rig: every field of a rig replaced by
    what a careless writer sends gives figures or None, never a bare exception (a number for its
    camera raised AttributeError), and a rig gives its figures."""
    from shared.formats.rig import save_rig
    from shared.publish.paradata import rig_figures
    from shared.sim.rigs import make_rig
    from tests.support.hostile import bare_failures

    path = save_rig(make_rig(camera_size=(640, 480), projector_size=(320, 240), seed=0), tmp_path / "rig.json")
    fig = rig_figures(path)
    assert fig["camera"]["size"] == [640, 480] and fig["baseline"] > 0 and len(fig["camera"]["dist"]) == 5
    doc = json.loads(path.read_text())
    other = tmp_path / "other.json"

    def read(d: object) -> None:
        other.write_text(json.dumps(d))
        rig_figures(other)

    assert not bare_failures(doc, read, InputError)
