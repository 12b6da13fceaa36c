"""The job service end to end with real Redis, real worker processes, a real beat and (for
two of them) the real PostgreSQL:

* a job submitted through the API completes and its cloud equals ``scan``'s;
* ``kill -9`` of a worker mid-stage: the job still completes, the stage succeeds once, the
  artifacts are intact;
* restarting the API and the workers loses no job (``graylight submit --wait`` follows);
* a Redis restart mid-run strands nothing (the reconciler re-publishes lost messages);
* 50 jobs at once, a few broken: good ones complete, broken ones fail once with a one-line
  reason naming the file.
"""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from shared.formats.ply import read_ply
from shared.service.artifacts import ArtifactStore
from shared.service.jobstore import JobStore
from tests.support.jobsvc import (
    GRAYLIGHT,
    ServiceEnv,
    capture_zip,
    start_api,
    start_beat,
    start_worker,
    wait_for,
)

# One group, so that --dist loadgroup hands the module to one xdist worker early (groups go before
# single tests): its tests mostly wait on service processes, which the other worker's computing
# then fills; as single tests they came last, side by side, the CPUs half idle (both workers
# waiting) for the suite's last 40-60 s.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("service")]

#: Render stages at a tiny size so they take a fraction of a second.
FAST = '{"preview": {"size": [96, 72], "seconds": 0.5, "fps": 4}}'
# These tests are about the job service, not the products: the scan stages only.
NO_RENDER = '{"render": false, "export": false}'


def client_for(senv: ServiceEnv) -> tuple[TestClient, dict[str, str]]:
    settings = senv.settings
    _rec, key = JobStore(settings.database_url).create_key("test")
    return TestClient(create_app(settings)), {"Authorization": f"Bearer {key}"}


def post_capture(client: TestClient, auth: dict[str, str], archive: Path, params: str = FAST) -> str:
    with open(archive, "rb") as f:
        r = client.post("/v1/jobs", headers=auth, files={"capture": (archive.name, f, "application/zip")},
                        data={"params": params})  # fmt: skip
    assert r.status_code == 201, r.text
    return r.json()["id"]


def wait_final(client: TestClient, auth: dict[str, str], ids: list[str], timeout: float, proc=None) -> dict[str, dict]:
    final: dict[str, dict] = {}

    def done() -> bool:
        for j in ids:
            if j not in final:
                doc = client.get(f"/v1/jobs/{j}", headers=auth).json()
                if doc["state"] in ("succeeded", "failed", "cancelled"):
                    final[j] = doc
        return len(final) == len(ids)

    try:
        wait_for(done, timeout, f"{len(ids)} jobs final", proc, interval=0.2)
    except AssertionError as exc:  # say how far it got (the message above is made before waiting)
        raise AssertionError(f"{len(final)} of {len(ids)} jobs final: {exc}") from None
    return final


def wait_batch_final(client: TestClient, auth: dict[str, str], batch: dict, timeout: float, proc=None) -> dict[str, dict]:
    """:func:`wait_final` for the jobs of a batch: waits on the batch's counts by state (one request
    a poll; polling the jobs one by one cost the test process about 10 s of CPU beside the workers
    with fifty jobs), then reads every job's final record."""
    final_states = ("succeeded", "failed", "cancelled")

    def done() -> bool:
        counts = client.get(f"/v1/batches/{batch['id']}", headers=auth).json()["counts"]
        return sum(counts.get(s, 0) for s in final_states) == len(batch["jobs"])

    wait_for(done, timeout, f"{len(batch['jobs'])} jobs of batch {batch['id']} final", proc, interval=0.2)
    final = {j: client.get(f"/v1/jobs/{j}", headers=auth).json() for j in batch["jobs"]}
    assert all(d["state"] in final_states for d in final.values()), final
    return final


def stage_successes(store: JobStore, job_id: str, stage: str) -> int:
    return sum(1 for e in store.events(job_id) if e[0] == stage and e[2] == "succeeded")


def test_api_job_matches_scan(pg_env: ServiceEnv, small_capture: Path, tmp_path: Path) -> None:
    from shared.scan.pipeline import scan

    svc_env = pg_env  # this one runs on PostgreSQL

    worker = start_worker(svc_env, "cpu,render", concurrency=1)
    client, auth = client_for(svc_env)
    jid = post_capture(client, auth, capture_zip(small_capture, tmp_path / "c.zip"))
    job = wait_final(client, auth, [jid], 120, worker)[jid]
    assert job["state"] == "succeeded", job
    assert [s["state"] for s in job["stages"]] == ["succeeded"] * len(job["stages"])
    assert all(s["seconds"] is not None and s["attempts"] == 1 for s in job["stages"])
    r = client.get(f"/v1/jobs/{jid}/artifacts/cloud.ply", headers=auth)
    assert r.status_code == 200
    (tmp_path / "api.ply").write_bytes(r.content)
    report = scan(small_capture, tmp_path / "embedded")
    ours, theirs = read_ply(tmp_path / "api.ply"), read_ply(tmp_path / "embedded" / "cloud.ply")
    assert len(ours) == report["points"] > 1000
    np.testing.assert_array_equal(ours.xyz, theirs.xyz)
    np.testing.assert_array_equal(ours.rgb, theirs.rgb)
    names = {a["name"] for a in client.get(f"/v1/jobs/{jid}/artifacts", headers=auth).json()["artifacts"]}
    if "tiles" in [s["name"] for s in job["stages"]]:
        # The viewer's way in: a stage's file by path, with the Bearer key.
        assert client.get(f"/v1/jobs/{jid}/artifacts/tiles/metadata.json", headers=auth).json()
        assert "preview.mp4" in names
        assert client.get(f"/v1/jobs/{jid}/artifacts/preview.mp4", headers=auth).content[4:8] == b"ftyp"


def test_kill9_worker_mid_stage(pg_env: ServiceEnv, small_capture: Path, tmp_path: Path) -> None:
    svc_env = pg_env  # on PostgreSQL: several worker processes and the API share it
    worker = start_worker(svc_env, "cpu", concurrency=1)
    beat = start_beat(svc_env)
    client, auth = client_for(svc_env)
    r = client.post("/v1/jobs", headers=auth, json={"kind": "probe", "params": {"seconds": 3}})
    assert r.status_code == 201, r.text
    probe = r.json()["id"]
    scan_job = post_capture(client, auth, capture_zip(small_capture, tmp_path / "c.zip"), NO_RENDER)
    store = JobStore(svc_env.settings.database_url)
    wait_for(lambda: store.get_job(probe).stage("probe").state == "running", 60, "probe running", worker)
    time.sleep(0.8)
    worker.kill9()  # the worker and its pool child, mid-stage
    assert store.get_job(probe).stage("probe").state == "running"  # the database still thinks so
    worker2 = start_worker(svc_env, "cpu", concurrency=1)
    final = wait_final(client, auth, [probe, scan_job], 90, worker2)
    assert final[probe]["state"] == "succeeded" and final[scan_job]["state"] == "succeeded", final
    job = store.get_job(probe)
    st = job.stage("probe")
    assert st.attempts == 2 and stage_successes(store, probe, "probe") == 1
    assert any(e[0] == "probe" and e[3] and "expired" in e[3] for e in store.events(probe))
    arts = ArtifactStore(svc_env.settings.storage_url)
    assert arts.verify(st.output_key).files["probe.json"].size > 0
    for s in store.get_job(scan_job).stages:
        assert stage_successes(store, scan_job, s.name) == 1
        arts.verify(s.output_key)
    assert beat.popen.poll() is None
    # Exactly one beat: a second one for the same queues refuses to start.
    second = subprocess.run([GRAYLIGHT, "beat"], env=svc_env.env, capture_output=True, text=True, timeout=60)
    assert second.returncode == 1 and "another beat already runs" in second.stderr


def test_restarting_api_and_workers_loses_no_job(svc_env: ServiceEnv, small_capture: Path, tmp_path: Path) -> None:
    api, url = start_api(svc_env)
    start_beat(svc_env)
    _rec, key = JobStore(svc_env.settings.database_url).create_key("cli")
    env = {**svc_env.env, "GRAYLIGHT_API_URL": url, "GRAYLIGHT_API_KEY": key}
    caps = [capture_zip(small_capture, tmp_path / f"c{i}.zip", note=str(i)) for i in range(2)]
    out = subprocess.run([GRAYLIGHT, "submit", *map(str, caps), "--batch", "restart", "--params", FAST], env=env,
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert out.returncode == 0, out.stderr
    ids = out.stdout.split()
    assert len(ids) == 2
    api.stop()  # no worker has run anything yet; the API goes away
    port = url.rsplit(":", 1)[1]
    api2, _ = start_api(svc_env, int(port))
    worker = start_worker(svc_env, "cpu,render", concurrency=1)
    time.sleep(0.5)
    worker.stop()  # a graceful restart in the middle of the run
    start_worker(svc_env, "cpu,render", concurrency=1)
    follow = subprocess.run([GRAYLIGHT, "submit", str(caps[0]), "--wait", "--timeout", "60", "--params", NO_RENDER], env=env,
                            capture_output=True, text=True, timeout=180)  # fmt: skip
    assert follow.returncode == 0, follow.stderr
    import httpx

    for j in ids:
        doc = httpx.get(f"{url}/v1/jobs/{j}", headers={"Authorization": f"Bearer {key}"}).json()
        deadline = time.monotonic() + 30
        while doc["state"] not in ("succeeded", "failed") and time.monotonic() < deadline:
            time.sleep(0.3)
            doc = httpx.get(f"{url}/v1/jobs/{j}", headers={"Authorization": f"Bearer {key}"}).json()
        assert doc["state"] == "succeeded", doc
    listing = subprocess.run([GRAYLIGHT, "jobs", "--batch", "restart"], env=env, capture_output=True, text=True, timeout=60)
    assert listing.returncode == 0 and all(j in listing.stdout for j in ids)
    assert api2.popen.poll() is None


def test_redis_restart_strands_nothing(tmp_path: Path, redis_server, small_capture: Path) -> None:
    from tests.support.jobsvc import service_env

    with service_env(tmp_path, GRAYLIGHT_BROKER_URL=redis_server.url) as senv:
        worker = start_worker(senv, "cpu", concurrency=1)
        start_beat(senv)
        client, auth = client_for(senv)
        first = client.post("/v1/jobs", headers=auth, json={"kind": "probe", "params": {"seconds": 2}}).json()["id"]
        second = client.post("/v1/jobs", headers=auth, json={"kind": "probe", "params": {"seconds": 0.2}}).json()["id"]
        store = JobStore(senv.settings.database_url)
        wait_for(lambda: store.get_job(first).stage("probe").state == "running", 60, "first probe running", worker)
        redis_server.stop()  # every queued message (the second job's) is gone with it
        time.sleep(1.0)
        redis_server.start()
        final = wait_final(client, auth, [first, second], 90, worker)
        assert {j: d["state"] for j, d in final.items()} == {first: "succeeded", second: "succeeded"}
        assert stage_successes(store, second, "probe") == 1
        # It was the reconciler that put the lost message back on the queue.
        assert re.search(r"'republished': [1-9]", worker.text()), worker.text()[-2000:]


def test_fifty_jobs_with_broken_captures(svc_env: ServiceEnv, tmp_path: Path) -> None:
    from shared.sim.simulate import simulate_named

    worker = start_worker(svc_env, "cpu", concurrency=2)
    # A tinier capture than elsewhere: fifty of them run here.
    small_capture = simulate_named("plane", tmp_path / "tiny", size=(96, 72), projector=(32, 16), seed=5).root
    client, auth = client_for(svc_env)
    capture_json = (small_capture / "capture.json").read_text()
    broken = {
        "missing.zip": ({"drop": ("col_01_inv.png",)}, "col_01_inv.png"),
        "truncated.zip": ({"replace": {"col_02.png": (small_capture / "col_02.png").read_bytes()[:60]}}, "col_02.png"),
        "badjson.zip": ({"replace": {"capture.json": capture_json.replace('"format"', '"formt"', 1).encode()}}, "capture.json"),
    }
    files = []
    for i in range(47):
        files.append(capture_zip(small_capture, tmp_path / f"good{i:02d}.zip", note=f"capture {i}"))
    for name, (how, _) in broken.items():
        files.append(capture_zip(small_capture, tmp_path / name, **how))
    handles = [open(p, "rb") for p in files]
    try:
        r = client.post("/v1/batches", headers=auth, data={"name": "fifty", "params": NO_RENDER},
                        files=[("captures", (p.name, h, "application/zip")) for p, h in zip(files, handles, strict=True)])  # fmt: skip
    finally:
        for h in handles:
            h.close()
    assert r.status_code == 201, r.text
    batch = r.json()
    assert batch["rejected"] == [] and len(batch["jobs"]) == 50
    final = wait_batch_final(client, auth, batch, 240, worker)
    by_name = {d["name"]: d for d in final.values()}
    for i in range(47):
        assert by_name[f"good{i:02d}.zip"]["state"] == "succeeded", by_name[f"good{i:02d}.zip"]
    for name, (_how, culprit) in broken.items():
        d = by_name[name]
        assert d["state"] == "failed", d
        assert culprit in d["error"] and "\n" not in d["error"], d["error"]
        assert d["error"].split(": ", 1)[1].startswith(f"{name}:"), d["error"]  # names the capture, not a cache path
        # Bad input is never retried: the stage that found it ran once, nothing after it ran.
        ran = [s for s in d["stages"] if s["attempts"]]
        assert all(s["attempts"] == 1 for s in ran) and ran[-1]["state"] == "failed"
        assert all(s["state"] == "cancelled" for s in d["stages"][len(ran):])
    progress = client.get(f"/v1/batches/{batch['id']}", headers=auth).json()
    assert progress["progress"] == 1.0 and progress["counts"] == {"succeeded": 47, "failed": 3}

