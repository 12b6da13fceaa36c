"""``graylight publish``: the Voyager scene validates against Voyager's own schemas and stands the object
upright on the origin; the quality report; hostile titles escaped; bad and older inputs refused in one
line or published by the documented fallback; the scene opens in Voyager Explorer and the report in
Chromium without an error."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from jsonschema import Draft7Validator
from scipy.spatial.transform import Rotation

from services.cli.main import main
from tests.support.voyager import svx_validator

# One group with test_paradata.py: the session fixtures of conftest.py (the set, its scan and its merge)
# are made on one xdist worker, not once a worker.
pytestmark = pytest.mark.xdist_group("publish")

HOSTILE = '<script>alert(1)</script> "Bunny" / ../x'


def _validator() -> Draft7Validator:
    return svx_validator()


def _publish(source: Path, out: Path, *extra: str) -> int:
    return main(["publish", str(source), "--out", str(out), *extra])


@pytest.fixture(scope="module")
def published(merged: Path, scanned: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("published")
    assert _publish(merged, root / "merge", "--title", HOSTILE, "--collection", "Sim & Co",
                    "--identifier", "sim/bunny-01") == 0
    assert _publish(scanned, root / "scan", "--title", "view 0") == 0
    return {"merge": root / "merge", "scan": root / "scan"}


@pytest.mark.parametrize("kind", ["merge", "scan"])
def test_scene_validates_against_voyager_schemas(published: dict[str, Path], kind: str) -> None:
    validator = _validator()
    doc = json.loads((published[kind] / "scene.svx.json").read_text())
    assert list(validator.iter_errors(doc)) == []
    # The validator does check the referenced schemas: a wrong unit or quality in the model fails.
    bad = json.loads(json.dumps(doc))
    bad["models"][0]["units"] = "furlong"
    bad["models"][0]["derivatives"][0]["quality"] = "Best"
    assert len(list(validator.iter_errors(bad))) >= 2
    model = doc["models"][0]
    assert model["units"] == "mm" and doc["scenes"][0]["units"] == "mm"
    for d in model["derivatives"]:
        glb = d["assets"][0]
        path = published[kind] / glb["uri"]
        assert d["usage"] == "Web3D" and glb["byteSize"] == path.stat().st_size
        loaded = trimesh.load(path, process=False)
        geom = next(iter(loaded.geometry.values()))
        if kind == "merge":
            assert glb["numFaces"] == len(geom.faces)
        else:
            assert "numFaces" not in glb and len(geom.vertices) > 1000
    qualities = [d["quality"] for d in model["derivatives"]]
    assert qualities == (["Thumb", "Low", "Medium", "High"] if kind == "merge" else ["Thumb", "High"])
    assert doc["metas"][0]["process"]["steps"][0]["stage"] == ("merge" if kind == "merge" else "scan")


def test_scene_stands_the_object_upright_on_the_origin(published: dict[str, Path], small_set: Path) -> None:
    doc = json.loads((published["merge"] / "scene.svx.json").read_text())
    model = doc["models"][0]
    R = Rotation.from_quat(model["rotation"]).as_matrix()
    t = np.array(model["translation"])
    mesh = trimesh.load(published["merge"] / "mesh.glb", force="mesh", process=False)
    placed = np.asarray(mesh.vertices) @ R.T + t
    assert abs(placed[:, 1].min()) < 1e-3  # standing on y = 0
    truth = np.load(small_set / "truth.npz")
    up = R @ truth["axis_direction"]  # the true table axis, pointing up in view 0's image
    assert np.degrees(np.arccos(np.clip(up[1], -1, 1))) < 1.0
    axis_point = R @ truth["axis_point"] + t  # the true axis runs through the origin
    assert np.hypot(axis_point[0], axis_point[2]) < 2.0


def test_quality_report(published: dict[str, Path], merged: Path) -> None:
    qa = json.loads((published["merge"] / "qa.json").read_text())
    reg = json.loads((merged / "registration.json").read_text())
    assert [v["rms_mm"] for v in qa["views"]] == [v["rms_mm"] for v in reg["views"]]
    assert len(qa["pairs"]) == len(reg["edges"]) and qa["loop_closure"] == reg["loop_closure"]
    assert 0 < qa["noise"]["median_mm"] < 1.0
    seen = qa["coverage"]["seen_by"]
    assert sum(seen.values()) == len(trimesh.load(merged / "mesh.glb", force="mesh", process=False).vertices)
    assert qa["coverage"]["bridged_share"] < 0.25 and int(seen["2"]) > 0
    assert {d["quality"] for d in qa["derivatives"]} == {"Thumb", "Low", "Medium", "High"}
    assert qa["verdict"]["publishable"] and qa["verdict"]["line"] == "publishable"
    assert "no quality block" in " ".join(qa["notes"]) or qa["quality_flags"]
    scan_qa = json.loads((published["scan"] / "qa.json").read_text())
    assert scan_qa["views"][0]["points"] > 10_000 and scan_qa["coverage"]["bridged_share"] is None


def test_titles_are_text_everywhere(published: dict[str, Path]) -> None:
    html = (published["merge"] / "qa.html").read_text()
    assert "<script" not in html.lower()
    assert "&lt;script&gt;alert(1)&lt;/script&gt; &quot;Bunny&quot; / ../x" in html
    assert json.loads((published["merge"] / "qa.json").read_text())["object"]["title"] == HOSTILE
    scene = json.loads((published["merge"] / "scene.svx.json").read_text())
    # Voyager shows the title as HTML: the scene holds it escaped, so it shows as text.
    assert scene["metas"][0]["collection"]["title"] == "&lt;script&gt;alert(1)&lt;/script&gt; &quot;Bunny&quot; / ../x"
    assert scene["metas"][0]["collection"]["identifier"] == "sim/bunny-01"
    # The path separators named nothing: the folder holds only what publish writes.
    assert sorted(p.name for p in published["merge"].iterdir()) == sorted(
        ["mesh.glb", "mesh_lod1.glb", "mesh_lod2.glb", "mesh_lod3.glb", "paradata.json", "qa.html", "qa.json",
         "scene.svx.json"])


def test_publish_paradata_carries_the_making_of_the_model(published: dict[str, Path], tmp_path: Path) -> None:
    from pyld import jsonld

    doc = json.loads((published["merge"] / "paradata.json").read_text())
    stages = sorted(n["stage"] for n in doc["@graph"] if n.get("@type") == "Activity")
    assert stages == ["merge", "publish"]
    jsonld.expand(doc)
    # Publishing again from the paradata gives the same folder, bit for bit.
    assert main(["rerun", str(published["merge"] / "paradata.json"), "--out", str(tmp_path / "again")]) == 0
    for name in ("scene.svx.json", "qa.json", "qa.html", "mesh.glb"):
        assert (tmp_path / "again" / name).read_bytes() == (published["merge"] / name).read_bytes()


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    return err


def test_bad_input_is_refused_in_one_line(merged: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert _publish(merged, out, "--title", "a\x07b") == 1
    assert _one_line_error(capsys) == "graylight publish: error: --title: control character U+0007 is not allowed"
    assert _publish(tmp_path, out) == 1
    assert "no report.json: not a graylight merge or scan output folder" in _one_line_error(capsys)
    (out / "keep.txt").parent.mkdir()
    (out / "keep.txt").write_text("mine")
    assert _publish(merged, out) == 1
    assert "exists and is not an empty folder" in _one_line_error(capsys)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    # An older Graylight's registration without per-view records: refused, nothing written.
    old = tmp_path / "old"
    shutil.copytree(merged, old)
    reg = json.loads((old / "registration.json").read_text())
    del reg["views"]
    (old / "registration.json").write_text(json.dumps(reg))
    assert _publish(old, tmp_path / "o2") == 1
    assert _one_line_error(capsys).endswith("registration.json: views: missing (an older Graylight's registration?)")
    assert not (tmp_path / "o2").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_fallbacks_no_mesh_and_no_paradata(merged: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "nomesh"
    shutil.copytree(merged, src)
    for p in src.glob("mesh*"):
        p.unlink()
    (src / "paradata.json").unlink()  # as an output folder from before paradata
    assert _publish(src, tmp_path / "pub") == 0
    scene = json.loads((tmp_path / "pub" / "scene.svx.json").read_text())
    assets = [a for d in scene["models"][0]["derivatives"] for a in d["assets"]]
    assert [a["uri"] for a in assets] == ["cloud_thumb.glb", "cloud_high.glb", "merged.ply"]
    assert assets[-1]["type"] == "Points"
    assert scene["metas"][0]["process"]["paradata"] is None and "before Graylight recorded" in \
        scene["metas"][0]["process"]["note"]
    assert list(_validator().iter_errors(scene)) == []


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["merge", "scan"])
def test_voyager_explorer_opens_the_scene(published: dict[str, Path], kind: str, tmp_path: Path) -> None:
    from tests.support.voyager import open_in_voyager

    shot = tmp_path / f"voyager-{kind}.png"
    res = open_in_voyager(published[kind], shot)
    assert res.console_errors == [] and res.failed_requests == [] and res.notices == []
    assert res.loaded >= 1
    assert any(u.endswith(("/mesh.glb", "/cloud_high.glb")) for u in res.model_requests)
    # The model is on screen: the middle of the picture is not the background.
    import cv2

    img = cv2.imread(str(shot))
    h, w = img.shape[:2]
    centre = img[h // 3: 2 * h // 3, w // 3: 2 * w // 3].astype(float)
    corner = img[h // 2 - 40: h // 2 + 40, 5:60].astype(float)
    assert np.abs(centre.mean(axis=(0, 1)) - corner.mean(axis=(0, 1))).max() > 8 or centre.std() > 15


@pytest.mark.slow
def test_qa_html_renders_offline_in_chromium(published: dict[str, Path], tmp_path: Path) -> None:
    from tests.support.viewer_browser import chromium

    problems: list[str] = []
    with chromium() as browser:
        page = browser.new_page(viewport={"width": 1100, "height": 900})
        page.on("console", lambda m: problems.append(m.text) if m.type in ("error", "warning") else None)
        page.on("pageerror", lambda e: problems.append(str(e)))
        page.on("request", lambda r: problems.append(r.url) if not r.url.startswith(("file:", "data:")) else None)
        page.on("dialog", lambda d: problems.append(f"dialog {d.message}"))
        page.goto((published["merge"] / "qa.html").as_uri())
        assert page.inner_text("h1") == HOSTILE
        imgs = page.evaluate("[...document.images].map(i => i.naturalWidth)")
        page.screenshot(path=str(tmp_path / "qa.png"), full_page=True)
    assert problems == []
    assert len(imgs) >= 2 and min(imgs) > 100  # the plots decoded


def test_calibration_evidence_and_the_verdict(small_set: Path, tmp_path: Path) -> None:
    """A rig with its calibration session's report beside it (as graylight calibrate writes them) shows
    its figures; a camera reprojection RMS over the threshold makes the object not publishable."""
    cap = tmp_path / "cap"
    shutil.copytree(small_set / "view_00", cap)
    rig = json.loads((cap / "rig.json").read_text())
    poses = [{"name": f"pose_{i:02d}", "used": i != 3, "reason": "board not found" if i == 3 else None,
              "camera_rms_px": 0.1 + 0.02 * i, "projector_rms_px": 0.08 + 0.01 * i} for i in range(6)]
    report = {"format": "graylight-calibration-v1", "rig": rig, "units": "mm", "baseline": 250.0,
              "rms_px": {"camera": 0.18, "projector": 0.12, "stereo": 0.2}, "poses": poses,
              "board_check": {"square_size": 40.0, "square_rms_error_pct": 0.3, "poses": []}}
    (cap / "rig-report.json").write_text(json.dumps(report))
    assert main(["scan", str(cap), "--out", str(tmp_path / "scan")]) == 0
    assert _publish(tmp_path / "scan", tmp_path / "good") == 0
    qa = json.loads((tmp_path / "good" / "qa.json").read_text())
    assert qa["calibration"]["rms_px"]["camera"] == 0.18 and qa["calibration"]["poses_used"] == 5
    assert qa["calibration"]["skipped"] == {"pose_03": "board not found"}
    assert qa["verdict"]["publishable"]
    html = (tmp_path / "good" / "qa.html").read_text()
    assert "reprojection RMS per pose" in html and "board not found" in html
    # The scan's own paradata carries the session's figures with the rig.
    para = json.loads((tmp_path / "scan" / "paradata.json").read_text())
    act = next(n for n in para["@graph"] if n["@id"] == para["run"])
    assert next(iter(act["rig"].values()))["calibration"]["rms_px"]["camera"] == 0.18
    report["rms_px"]["camera"] = 1.6
    (cap / "rig-report.json").write_text(json.dumps(report))
    assert _publish(tmp_path / "scan", tmp_path / "bad") == 0
    verdict = json.loads((tmp_path / "bad" / "qa.json").read_text())["verdict"]
    assert verdict == {"publishable": False, "reasons": ["calibration reprojection RMS of the camera 1.60 px > 1 px"],
                       "line": "not publishable: calibration reprojection RMS of the camera 1.60 px > 1 px"}
    # A report of another rig (the rig was re-calibrated since) is not taken as this rig's evidence.
    report["rig"]["T"][0] += 1.0
    (cap / "rig-report.json").write_text(json.dumps(report))
    assert _publish(tmp_path / "scan", tmp_path / "other") == 0
    assert "rms_px" not in json.loads((tmp_path / "other" / "qa.json").read_text())["calibration"]


def test_publish_a_merge_that_graylight_derivatives_wrote_into(merged: Path, tmp_path: Path) -> None:
    """``graylight derivatives`` then ``graylight publish`` on the same merge folder: the scene lists the
    textured Draco levels as derivatives.json measured them (not the merge's LODs), and the report's
    budget table and its note say so."""
    work = tmp_path / "merge"
    shutil.copytree(merged, work)
    assert main(["derivatives", str(work), "--levels", "thumb:3000:128,low:8000:256"]) == 0
    assert main(["publish", str(work), "--out", str(tmp_path / "web"), "--title", "t"]) == 0
    made = json.loads((work / "derivatives.json").read_text())
    scene = json.loads((tmp_path / "web" / "scene.svx.json").read_text())
    assert list(svx_validator().iter_errors(scene)) == []
    assets = [d["assets"][0] for d in scene["models"][0]["derivatives"]]
    assert [(a["uri"], a["byteSize"], a["numFaces"], a["imageSize"]) for a in assets] == [
        (lv["file"], lv["bytes"], lv["faces"], lv["texture_px"]) for lv in made["levels"]]
    qa = json.loads((tmp_path / "web" / "qa.json").read_text())
    assert [r["file"] for r in qa["derivatives"]] == ["mesh_thumb.glb", "mesh_low.glb"]
    assert qa["derivative_set"]["made_by"] == "graylight derivatives"
    assert "Levels: graylight derivatives" in (tmp_path / "web" / "qa.html").read_text()
