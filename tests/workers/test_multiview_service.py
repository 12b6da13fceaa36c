"""A multi-view job end to end: a scan-set archive submitted through the API, its per-view stages
spread over two real worker processes, the merge, the artifacts; a broken view fails the job with a
message naming the view; a worker killed mid-merge loses nothing.

The set is a realistic turntable capture: no ``roi`` (backdrop, floor and plate in every view), so
the job must find the object itself, and its registration must match the CLI's on the same set."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from shared.merge.fusion import read_fused
from shared.service.artifacts import ArtifactStore
from shared.service.jobs import MESH_LOD_FILES
from shared.service.jobstore import JobStore
from tests.support.jobsvc import ServiceEnv, capture_zip, start_beat, start_worker, wait_for

# One group: the module's scan set is made on one xdist worker, not once a worker.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("multiview_service")]

# Small derivatives (one Thumb with 256 px maps): the stage runs, in seconds.
PARAMS = '{"render": false, "derivatives": {"levels": [{"name": "thumb", "texture_px": 256}]}}'
VIEWS = 8
#: The scan set (scanset_factory's arguments).
SET = {"views": VIEWS, "size": (320, 240), "projector": (256, 192)}


@pytest.fixture(scope="module")
def scanset(tmp_path_factory: pytest.TempPathFactory, scanset_factory: Callable[..., Path]) -> Path:
    # 8 views: at 90 deg steps (4 views) the object alone, without the plate, overlaps too little.
    root = tmp_path_factory.mktemp("mv-jobs")
    simulated = scanset_factory(**SET)
    work = root / "no-roi"
    shutil.copytree(simulated, work)
    doc = json.loads((work / "scanset.json").read_text())
    doc.pop("roi", None)  # what a real turntable capture looks like (the simulator writes none unless asked)
    (work / "scanset.json").write_text(json.dumps(doc))
    return work


def _client(senv: ServiceEnv) -> tuple[TestClient, dict[str, str]]:
    _rec, key = JobStore(senv.settings.database_url).create_key("test")
    return TestClient(create_app(senv.settings)), {"Authorization": f"Bearer {key}"}


def _submit(client: TestClient, auth: dict[str, str], archive: Path) -> str:
    with open(archive, "rb") as f:
        r = client.post("/v1/jobs", headers=auth, files={"capture": (archive.name, f, "application/zip")},
                        data={"params": PARAMS, "kind": "multiview"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _final(client: TestClient, auth: dict[str, str], jid: str, timeout: float, proc) -> dict:
    out: dict = {}

    def done() -> bool:
        out.update(client.get(f"/v1/jobs/{jid}", headers=auth).json())
        return out["state"] in ("succeeded", "failed", "cancelled")

    wait_for(done, timeout, f"job {jid} final", proc, interval=0.3)
    return out


def _runners(store: JobStore, jid: str, prefix: str) -> set[str]:
    return {e[3] for e in store.events(jid) if e[0] and e[0].startswith(prefix) and e[2] == "running" and e[3]}


def test_multiview_job_over_two_workers(pg_env: ServiceEnv, scanset: Path, tmp_path: Path,
                                        scanset_factory: Callable[..., Path], merge_factory: Callable[[Path], Path]) -> None:
    w1 = start_worker(pg_env, "cpu", concurrency=1)
    start_worker(pg_env, "cpu", concurrency=1)
    client, auth = _client(pg_env)
    jid = _submit(client, auth, capture_zip(scanset, tmp_path / "set.zip"))
    job = _final(client, auth, jid, 600, w1)
    assert job["state"] == "succeeded", job
    names = [s["name"] for s in job["stages"]]
    per_view = {f"{m}#{i}" for m in ("mv_ingest", "mv_decode", "mv_triangulate") for i in range(VIEWS)}
    assert names[:1] == ["mv_plan"] and per_view <= set(names) and "mv_merge" in names
    store = JobStore(pg_env.settings.database_url)
    # Each view's decode waits for that view's ingest only, its triangulation for its decode.
    events = [(e[0], e[2]) for e in store.events(jid)]
    for i in range(VIEWS):
        assert events.index((f"mv_ingest#{i}", "succeeded")) < events.index((f"mv_decode#{i}", "running"))
        assert events.index((f"mv_decode#{i}", "succeeded")) < events.index((f"mv_triangulate#{i}", "running"))
    runners = _runners(store, jid, "mv_decode#") | _runners(store, jid, "mv_triangulate#")
    print("per-view stages ran on", runners)
    assert len(runners) == 2
    r = client.get(f"/v1/jobs/{jid}/artifacts/registration.json", headers=auth)
    reg = r.json()
    assert [v["registered"] for v in reg["views"]] == [True] * VIEWS and reg["loop_closure"]
    assert reg["quality"]["passed"] and reg["quality"]["removed"]["object"]["source"] == "found"
    # The CLI on the same set registers the same poses: graylight merge of the set as simulated (made
    # once a run, merge_factory), which is the job's set: the job's copy only had any roi removed.
    simulated = scanset_factory(**SET)
    assert "roi" not in json.loads((simulated / "scanset.json").read_text())
    cli = json.loads((merge_factory(simulated) / "registration.json").read_text())
    for a, b in zip(reg["views"], cli["views"], strict=True):
        np.testing.assert_allclose(a["R"], b["R"], atol=1e-4)
        np.testing.assert_allclose(a["T"], b["T"], atol=0.05)
    (tmp_path / "merged.ply").write_bytes(client.get(f"/v1/jobs/{jid}/artifacts/merged.ply", headers=auth).content)
    rec = read_fused(tmp_path / "merged.ply")
    assert len(rec) > 10000 and set(np.unique(rec["view"])) == set(range(VIEWS))
    for name in ("mesh.glb", *MESH_LOD_FILES, "mesh_thumb.glb"):  # the meshes and the derivative, by short names
        glb = client.get(f"/v1/jobs/{jid}/artifacts/{name}", headers=auth).content
        assert glb[:4] == b"glTF", name
    derivatives = client.get(f"/v1/jobs/{jid}/artifacts/derivatives.json", headers=auth).json()
    assert [lv["level"] for lv in derivatives["levels"]] == ["thumb"] and derivatives["levels"][0]["texture_px"] == 256


def test_broken_view_fails_the_job_naming_it(svc_env: ServiceEnv, scanset: Path, tmp_path: Path) -> None:
    client, auth = _client(svc_env)
    # A broken image is refused at submission, naming the file in the archive.
    work = tmp_path / "set"
    shutil.copytree(scanset, work)
    (work / "view_02" / "col_03.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    archive = capture_zip(work, tmp_path / "bad.zip")
    with open(archive, "rb") as f:
        r = client.post("/v1/jobs", headers=auth, files={"capture": (archive.name, f, "application/zip")},
                        data={"params": PARAMS, "kind": "multiview"})
    assert r.status_code == 422 and "view_02/col_03.png" in r.text
    # A pose that is not a rotation passes the archive checks; the plan stage fails, naming the view.
    shutil.copyfile(scanset / "view_02" / "col_03.png", work / "view_02" / "col_03.png")
    doc = json.loads((work / "scanset.json").read_text())
    doc["views"][2]["pose"] = {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 3]], "T": [0, 0, 0]}
    (work / "scanset.json").write_text(json.dumps(doc))
    w = start_worker(svc_env, "cpu", concurrency=1)
    jid = _submit(client, auth, capture_zip(work, tmp_path / "pose.zip"))
    job = _final(client, auth, jid, 300, w)
    assert job["state"] == "failed"
    failed = [s for s in job["stages"] if s["state"] == "failed"]
    assert failed and failed[0]["name"] == "mv_plan"
    assert "views[2] (view_02).pose.R: is not a rotation" in failed[0]["error"] and "\n" not in failed[0]["error"]


def test_worker_killed_mid_merge_loses_nothing(pg_env: ServiceEnv, scanset: Path, tmp_path: Path) -> None:
    worker = start_worker(pg_env, "cpu", concurrency=1)
    start_beat(pg_env)
    client, auth = _client(pg_env)
    jid = _submit(client, auth, capture_zip(scanset, tmp_path / "set.zip", note="kill"))
    store = JobStore(pg_env.settings.database_url)
    wait_for(lambda: store.get_job(jid).stage("mv_merge").state == "running", 600, "merge running", worker)
    time.sleep(1.0)
    worker.kill9()
    worker2 = start_worker(pg_env, "cpu", concurrency=1)
    job = _final(client, auth, jid, 600, worker2)
    assert job["state"] == "succeeded", job
    st = store.get_job(jid).stage("mv_merge")
    assert st.attempts == 2
    assert sum(1 for e in store.events(jid) if e[0] == "mv_merge" and e[2] == "succeeded") == 1
    for s in store.get_job(jid).stages:
        assert sum(1 for e in store.events(jid) if e[0] == s.name and e[2] == "succeeded") == 1
    files = ArtifactStore(pg_env.settings.storage_url).verify(st.output_key).files
    assert {"merged.ply", "registration.json", "mesh.glb", "report.json"} <= set(files)
    assert json.loads(client.get(f"/v1/jobs/{jid}/artifacts/report.json", headers=auth).content)["registered_views"] == VIEWS
