"""The job service's publish stage and its paradata: a scan job and a multi-view job end with a
Voyager scene that validates, a quality report and the job's paradata.json holding every stage
(W3C PROV, expanded by pyld); each stage's output carries its own record."""

from __future__ import annotations

import hashlib
import json
import zipfile
from collections.abc import Callable
from pathlib import Path

import pytest
from pyld import jsonld

from shared.service.artifacts import ArtifactStore, sha256_file
from shared.service.jobs import PUBLISH_FILES, graph_for, stage_spec
from shared.service.jobstore import JobStore, NewJob
from tests.support.inprocess import drive, run_scan_job
from tests.support.jobsvc import capture_zip, make_env
from tests.support.voyager import svx_validator


def _activities(doc: dict) -> list[dict]:
    return [n for n in doc["@graph"] if n.get("@type") == "Activity"]


def test_scan_job_publishes_scene_report_and_paradata(tmp_path: Path, small_capture: Path) -> None:
    assert stage_spec("scan", "publish").publish == PUBLISH_FILES
    arts, job = run_scan_job(make_env(tmp_path / "svc").settings, small_capture, tmp_path,
                             {"render": False, "export": False})
    assert [s.name for s in job.stages][-1] == "publish"
    out = arts.fetch(job.stage("publish").output_key, tmp_path / "pub")
    scene = json.loads((out / "scene.svx.json").read_text())
    assert list(svx_validator().iter_errors(scene)) == []
    assert scene["metas"][0]["collection"]["identifier"] == job.id
    assert [s["stage"] for s in scene["metas"][0]["process"]["steps"]] == ["ingest", "decode", "triangulate", "publish"]
    qa = json.loads((out / "qa.json").read_text())
    assert qa["views"][0]["points"] > 1000 and qa["verdict"]["line"]
    doc = json.loads((out / "paradata.json").read_text())
    assert sorted(a["stage"] for a in _activities(doc)) == ["decode", "ingest", "publish", "triangulate"]
    jsonld.expand(doc)
    # The submitted capture's files are named once (by the stage that read them first), by sha256.
    with zipfile.ZipFile(tmp_path / "c.zip") as z:  # the archive run_scan_job submitted
        submitted = sorted(hashlib.sha256(z.read(m)).hexdigest() for m in z.namelist())
    entities = [n for n in doc["@graph"] if n.get("role") == "capture"]
    assert sorted(e["sha256"] for e in entities) == submitted
    # Every stage's output holds its own record; the cloud the publish stage used is triangulate's output.
    tri = arts.fetch(job.stage("triangulate").output_key, tmp_path / "tri")
    record = json.loads((tri / ".paradata.json").read_text())
    cloud = next(n for n in record["@graph"] if n.get("path") == "cloud.ply")
    assert cloud["sha256"] == sha256_file(tri / "cloud.ply")
    publish = next(a for a in _activities(doc) if a["stage"] == "publish")
    assert cloud["@id"] in publish["used"]


def _run_job(settings, folder: Path, archive: Path, kind: str, params: dict, owner: int | None = None,
             drop: tuple[str, ...] = ()) -> tuple[JobStore, ArtifactStore, object, str | None]:
    """Submit ``folder`` zipped as ``archive`` as a ``kind`` job (for ``owner``, else a new key's) and run
    it to its end in-process: the store, the artifact store, the finished job and the new key (or None)."""
    store = JobStore(settings.database_url)
    key = None
    if owner is None:
        rec, key = store.create_key("t")
        owner = rec.id
    arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
    capture_zip(folder, archive, drop=drop)
    ckey = sha256_file(archive)
    arts.put_files(ckey, {"capture.zip": archive})
    job, _ = store.create_job(owner, NewJob(kind=kind, capture_ref=f"object:{ckey}", capture_key=ckey,
                                            graph=graph_for(kind, params), name=archive.name, params=params))
    drive(settings, job.id, rounds=40)
    return store, arts, store.get_job(job.id), key


HOSTILE = {"title": "<script>alert(1)</script>", "collection": "Dept. \"A&B\" / casts", "identifier": "../1990.12/7"}
#: Two small textured levels (256 px maps): the derivatives stage runs in seconds.
MV_PARAMS = {"render": False, "export": False, **HOSTILE,
             "derivatives": {"levels": [{"name": "thumb", "texture_px": 256}, {"name": "low", "texture_px": 256}]}}


@pytest.fixture(scope="module")
def mv_job(tmp_path_factory: pytest.TempPathFactory, scanset_factory: Callable[..., Path]):
    """A multiview job run to its end once for the module, with two derivative levels and a hostile
    title: (settings, artifact store, job, key, its publish folder)."""
    root = tmp_path_factory.mktemp("mv-job")
    scanset = scanset_factory(views=8, size=(320, 240), projector=(256, 192))
    settings = make_env(root / "svc").settings
    _store, arts, job, key = _run_job(settings, scanset, root / "set.zip", "multiview", MV_PARAMS)
    assert job.state == "succeeded", [(s.name, s.error) for s in job.stages if s.error]
    return settings, arts, job, key, arts.fetch(job.stage("publish").output_key, root / "pub")


def test_publish_reads_the_derivatives_stage_when_the_job_runs_it() -> None:
    """The multiview publish stage waits for the derivatives when the job makes them; without them
    ({"derivatives": false}) it still runs, on the merge alone (its levels are the fallback)."""
    with_d = {s.name: s for s in graph_for("multiview", {})}
    without = {s.name: s for s in graph_for("multiview", {"derivatives": False})}
    assert set(with_d["publish"].depends_on) == {"mv_merge", "derivatives"}
    assert "derivatives" not in without and without["publish"].depends_on == ("mv_merge",)


def test_object_names_are_job_parameters() -> None:
    """title, collection and identifier: any text (markup kept, escaped where shown), checked at submission."""
    from shared.core.errors import InputError
    from shared.service.params import check_job_params

    for kind in ("scan", "multiview"):
        assert check_job_params(kind, HOSTILE) == HOSTILE
    with pytest.raises(InputError, match=r"^params.title: control character U\+0007 is not allowed$"):
        check_job_params("scan", {"title": "bell\a"})
    with pytest.raises(InputError, match=r"^params.identifier: must be a string"):
        check_job_params("multiview", {"identifier": 7})
    with pytest.raises(InputError, match=r"^params.collection: 501 characters, at most 500$"):
        check_job_params("scan", {"collection": "x" * 501})


@pytest.mark.slow
def test_multiview_job_publishes_the_merged_object(mv_job, tmp_path: Path) -> None:
    _settings, arts, job, _key, out = mv_job
    scene = json.loads((out / "scene.svx.json").read_text())
    assert list(svx_validator().iter_errors(scene)) == []
    # The derivatives stage's textured levels, measured as published (not the merge's LODs).
    derivs = scene["models"][0]["derivatives"]
    assert [d["quality"] for d in derivs] == ["Thumb", "Low"]
    made = json.loads((arts.fetch(job.stage("derivatives").output_key, tmp_path / "d") / "derivatives.json").read_text())
    for d, lv in zip(derivs, made["levels"], strict=True):
        asset = d["assets"][0]
        assert asset["uri"] == lv["file"] and asset["byteSize"] == (out / lv["file"]).stat().st_size == lv["bytes"]
        assert asset["numFaces"] == lv["faces"] and asset["imageSize"] == lv["texture_px"] == 256
    qa = json.loads((out / "qa.json").read_text())
    assert [(r["file"], r["faces"], r["image_size"]) for r in qa["derivatives"]] == [
        (lv["file"], lv["faces"], lv["texture_px"]) for lv in made["levels"]]
    assert qa["derivative_set"]["made_by"] == "graylight derivatives"
    assert qa["derivative_set"]["master_faces"] == made["master"]["faces"]
    # The submission's names: verbatim in qa.json, escaped in the scene (Voyager shows HTML) and in qa.html.
    assert {k: qa["object"][k] for k in HOSTILE} == HOSTILE
    assert scene["metas"][0]["collection"]["title"] == "&lt;script&gt;alert(1)&lt;/script&gt;"
    page = (out / "qa.html").read_text()
    assert "<script>" not in page and "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    doc = json.loads((out / "paradata.json").read_text())
    stages = sorted(a["stage"] for a in _activities(doc))
    assert stages.count("mv_triangulate#7") == 1 and {"mv_merge", "derivatives", "publish"} <= set(stages)
    jsonld.expand(doc)
    assert len(qa["views"]) == 8 and qa["calibration"]["rig"].endswith("rig.json")


@pytest.mark.slow
def test_scene_route_serves_voyager_on_another_origin(mv_job) -> None:
    """GET /v1/jobs/{id}/scene gives a link whose token in the path lets a viewer without the key read
    every file the scene names, with CORS headers; a wrong, foreign, expired or revoked token is refused."""
    import time

    from fastapi.testclient import TestClient

    from services.api.app import create_app
    from shared.service.scene_tokens import sign_scene_token

    settings, _arts, job, key, out = mv_job
    client = TestClient(create_app(settings))
    assert client.get(f"/v1/jobs/{job.id}/scene").status_code == 401
    r = client.get(f"/v1/jobs/{job.id}/scene", headers={"Authorization": f"Bearer {key}"}, params={"seconds": 600})
    assert r.status_code == 200, r.text
    link = r.json()
    assert link["url"] == link["root"] + "scene.svx.json" and 0 < link["expires"] - time.time() <= 600
    origin = {"Origin": "https://museum.example"}
    scene = client.get(link["url"], headers=origin)
    assert scene.status_code == 200 and scene.headers["access-control-allow-origin"] == "*"
    assert scene.content == (out / "scene.svx.json").read_bytes()
    named = [a["uri"] for d in scene.json()["models"][0]["derivatives"] for a in d["assets"]]
    assert {"mesh_thumb.glb", "mesh_low.glb"} <= set(named)
    for uri in named:  # every file the scene names, byte for byte
        got = client.get(link["root"] + uri, headers=origin)
        assert got.status_code == 200 and got.content == (out / uri).read_bytes(), uri
        assert got.headers["access-control-allow-origin"] == "*"
    part = client.get(link["root"] + named[0], headers={**origin, "Range": "bytes=0-3"})
    assert part.status_code == 206 and part.content == b"glTF"
    pre = client.options(link["root"] + named[0], headers={**origin, "Access-Control-Request-Method": "GET",
                                                            "Access-Control-Request-Headers": "range"})
    assert pre.status_code == 204 and "Range" in pre.headers["access-control-allow-headers"]
    assert client.get(link["root"] + "nothing.glb").status_code == 404
    base = f"/v1/jobs/{job.id}/scene"
    secret = settings.signing_secret()
    expires, sig = link["root"].rstrip("/").rsplit("/", 1)[1].split(".")
    bad = {
        "forged": f"{expires}.{sig[:-1]}{'A' if sig[-1] != 'A' else 'B'}",
        "extended": f"{int(expires) + 1}.{sig}",
        "another job": sign_scene_token(secret, "00000000-0000-0000-0000-000000000000", job.owner_id, int(expires)),
        "another key": sign_scene_token(secret, job.id, job.owner_id + 1, int(expires)),
        "expired": sign_scene_token(secret, job.id, job.owner_id, int(time.time()) - 1),
        "malformed": "not-a-token",
    }
    for why, token in bad.items():
        got = client.get(f"{base}/{token}/scene.svx.json", headers=origin)
        assert got.status_code == 403, why
        assert got.headers["access-control-allow-origin"] == "*" and "token" in got.json()["detail"], why
    # Authorised as the artifacts are: revoking the owner's key ends its links.
    store = JobStore(settings.database_url)
    assert store.revoke_key(key[:10])
    assert client.get(link["url"]).status_code == 403


def test_publish_a_job_by_its_id(tmp_path: Path, small_capture: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``graylight publish JOB_ID``: the publish stage's folder as the service made it, checked by sha256;
    with a title, the job's scan outputs published here; a job still running is refused in one line."""
    from fastapi.testclient import TestClient

    from services.api.app import create_app
    from services.cli.jobs import Client, ServiceError
    from services.cli.publish import fetch_published
    from shared.core.errors import InputError
    from shared.publish.folder import ObjectMeta

    settings = make_env(tmp_path / "svc").settings
    store, _arts, job, key = _run_job(settings, small_capture, tmp_path / "c.zip", "scan",
                                      {"render": False, "export": False})
    assert job.state == "succeeded", job
    jid = job.id
    client = Client(url="http://testserver", key=key, http=TestClient(create_app(settings)))
    qa = fetch_published(client, jid, tmp_path / "web", ObjectMeta(title="unused"))
    names = sorted(p.name for p in (tmp_path / "web").iterdir())
    assert {"scene.svx.json", "qa.json", "qa.html", "paradata.json", "cloud_high.glb", "cloud_thumb.glb"} <= set(names)
    assert qa == json.loads((tmp_path / "web" / "qa.json").read_text())
    scene = json.loads((tmp_path / "web" / "scene.svx.json").read_text())
    assert scene["metas"][0]["collection"]["identifier"] == jid
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".web")]
    qa2 = fetch_published(client, jid, tmp_path / "named", ObjectMeta(title="<i>Plane</i>", identifier="P-1"),
                          republish=True)
    assert qa2["object"]["title"] == "<i>Plane</i>"
    scene2 = json.loads((tmp_path / "named" / "scene.svx.json").read_text())
    assert scene2["metas"][0]["collection"] == {"title": "&lt;i&gt;Plane&lt;/i&gt;", "identifier": "P-1"}
    assert list(svx_validator().iter_errors(scene2)) == []
    with pytest.raises(ServiceError, match="HTTP 404: job 00000000-0000-0000-0000-000000000000 not found"):
        fetch_published(client, "00000000-0000-0000-0000-000000000000", tmp_path / "none", ObjectMeta(title="x"))
    # A job that has not run yet: refused by name, nothing written.
    queued, _ = store.create_job(store.get_job(jid).owner_id, NewJob(
        kind="scan", capture_ref=f"object:{'0' * 64}", capture_key="0" * 64, graph=graph_for("scan", {}),
        name="q.zip", params={}))
    with pytest.raises(InputError, match=f"^job {queued.id}: is queued: only a finished job can be published$"):
        fetch_published(client, queued.id, tmp_path / "q", ObjectMeta(title="x"))
    assert not (tmp_path / "q").exists()


def test_batch_report_repeats_the_verdict_with_links(tmp_path: Path, small_capture: Path) -> None:
    """A batch of a good scan and one that fails: the report's rows carry the verdict of the one that was
    published and the links to its scene and quality report; the failed one has neither."""
    import csv
    import io

    from shared.service.report import report_csv, report_rows

    settings = make_env(tmp_path / "svc").settings
    params = {"render": False, "export": False}
    _store, arts, good_job, _key = _run_job(settings, small_capture, tmp_path / "good.zip", "scan", params)
    bad_job = _run_job(settings, small_capture, tmp_path / "no-rig.zip", "scan", params, owner=good_job.owner_id,
                       drop=("rig.json",))[2]
    jobs = [good_job, bad_job]
    rows = report_rows(jobs)
    good, bad = rows
    published = arts.fetch(jobs[0].stage("publish").output_key, tmp_path / "pub")
    assert good.verdict == json.loads((published / "qa.json").read_text())["verdict"]["line"]
    assert {"scene.svx.json", "qa.html", "qa.json", "paradata.json"} <= set(good.artifacts)
    assert bad.state == "failed" and bad.verdict is None and "scene.svx.json" not in bad.artifacts
    table = list(csv.DictReader(io.StringIO(report_csv(rows, lambda r, a: f"/v1/jobs/{r.job}/artifacts/{a}", "https://h"))))
    assert table[0]["verdict"] == good.verdict and table[1]["verdict"] == ""
    assert f"/v1/jobs/{good.job}/artifacts/scene.svx.json" in table[0]["artifacts"].split()
    # Links to each published object's scene (the route giving its Voyager link) and its QA report.
    assert table[0]["scene"] == f"https://h/v1/jobs/{good.job}/scene"
    assert table[0]["qa_report"] == f"/v1/jobs/{good.job}/artifacts/qa.html"
    assert table[1]["scene"] == table[1]["qa_report"] == ""


@pytest.mark.slow
def test_calibrate_job_serves_its_paradata(tmp_path: Path) -> None:
    """A calibration job's paradata.json names every file of the session by sha256 and the rig it made."""
    from shared.sim.calibration import simulate_session

    session = simulate_session(tmp_path / "session", n_poses=5, camera_size=(320, 240), projector_size=(128, 96),
                               seed=1, inverses=False).root
    settings = make_env(tmp_path / "svc").settings
    _store, arts, job, _key = _run_job(settings, session, tmp_path / "session.zip", "calibrate", {})
    assert job.state == "succeeded", job
    assert "paradata.json" in stage_spec("calibrate", "calibrate").publish
    out = arts.fetch(job.stage("calibrate").output_key, tmp_path / "cal")
    doc = json.loads((out / "paradata.json").read_text())
    jsonld.expand(doc)
    with zipfile.ZipFile(tmp_path / "session.zip") as z:
        submitted = sorted(hashlib.sha256(z.read(m)).hexdigest() for m in z.namelist())
    assert sorted(n["sha256"] for n in doc["@graph"] if n.get("role") == "capture") == submitted
    rig = next(n for n in doc["@graph"] if n.get("path") == "rig.json")
    assert rig["sha256"] == sha256_file(out / "rig.json") and rig["wasGeneratedBy"] == doc["run"]
