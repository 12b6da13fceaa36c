"""Load: a collection of 40 small captures, 3 of them broken, on two real workers (with beat
and its reconciler) while one worker is killed with SIGKILL and the broker (a private
redis-server) is restarted mid-batch. Every good capture succeeds, each of its stages exactly
once; each broken one fails with a reason naming its file; the batch report says exactly that."""

from __future__ import annotations

import csv
import io
import re
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from shared.service.jobstore import JobStore
from tests.support.jobsvc import capture_zip, service_env, start_beat, start_worker, wait_for

pytestmark = pytest.mark.slow

NO_RENDER = '{"render": false}'
GOOD = 37


def test_batch_of_forty_survives_a_killed_worker_and_a_broker_restart(tmp_path: Path, redis_server) -> None:
    from shared.sim.simulate import simulate_named

    capture = simulate_named("plane", tmp_path / "tiny", size=(96, 72), projector=(32, 16), seed=5).root
    capture_json = (capture / "capture.json").read_text()
    broken = {  # name -> (how it is broken, the file its failure must name)
        "no-rig.zip": ({"drop": ("rig.json",)}, "rig.json"),
        "truncated.zip": ({"replace": {"col_02.png": (capture / "col_02.png").read_bytes()[:60]}}, "col_02.png"),
        "badjson.zip": ({"replace": {"capture.json": capture_json.replace('"format"', '"formt"', 1).encode()}}, "capture.json"),
    }
    files = [capture_zip(capture, tmp_path / f"object {i:02d}.zip", note=f"capture {i}") for i in range(GOOD)]
    files += [capture_zip(capture, tmp_path / name, **how) for name, (how, _) in broken.items()]
    files.insert(GOOD // 2, files.pop())  # a broken one in the middle of the batch

    with service_env(tmp_path, GRAYLIGHT_BROKER_URL=redis_server.url) as senv:
        victim = start_worker(senv, "cpu,render", concurrency=1)
        survivor = start_worker(senv, "cpu,render", concurrency=1)
        start_beat(senv)
        store = JobStore(senv.settings.database_url)
        key = store.create_key("museum")[1]
        client = TestClient(create_app(senv.settings))
        auth = {"Authorization": f"Bearer {key}"}
        r = client.post("/v1/batches", headers=auth, data={"name": "collection", "params": NO_RENDER},
                        files=[("captures", (p.name, p.read_bytes(), "application/zip")) for p in files])  # fmt: skip
        assert r.status_code == 201, r.text
        batch = r.json()
        assert len(batch["jobs"]) == 40 and not batch["rejected"]

        def counts() -> dict[str, int]:
            return client.get(f"/v1/batches/{batch['id']}", headers=auth).json()["counts"]

        # Mid-batch: SIGKILL one worker while it runs a stage, then restart the broker.
        wait_for(lambda: counts().get("succeeded", 0) >= 5, 300, "5 jobs done", survivor, interval=0.3)
        held: list[tuple[str, str]] = []  # (job, stage) the victim runs

        def victim_holds_a_stage() -> bool:
            pids = _group(victim.popen.pid)
            jobs = store.list_jobs(batch_id=batch["id"], state="running", limit=100)[0]
            held[:] = [(j.id, s.name) for j in jobs for s in j.stages
                       if s.state == "running" and s.lease_owner and int(s.lease_owner.rsplit(":", 1)[1]) in pids]  # fmt: skip
            return bool(held)

        wait_for(victim_holds_a_stage, 120, "the victim running a stage", victim, interval=0.05)
        victim.kill9()  # the whole process group: the worker and its pool child, no goodbye
        killed = [(j, n) for j, n in held if store.get_job(j).stage(n).state == "running"]  # not done in between
        redis_server.stop()  # every queued message is gone with it
        time.sleep(1.0)
        redis_server.start()

        wait_for(lambda: sum(counts().get(s, 0) for s in ("succeeded", "failed", "cancelled")) == 40, 900,
                 f"40 jobs final ({counts()})", survivor, interval=0.5)  # fmt: skip

        status = client.get(f"/v1/batches/{batch['id']}", headers=auth).json()
        assert status["counts"] == {"succeeded": GOOD, "failed": 3} and status["progress"] == 1.0
        report = client.get(f"/v1/batches/{batch['id']}/report.json", headers=auth).json()["rows"]
        assert [row["capture"] for row in report] == [p.name for p in files]  # every capture, as submitted
        for job_id, name in killed:  # the SIGKILLed worker's stage ran again elsewhere
            assert store.get_job(job_id).stage(name).attempts >= 2
            assert f"({name}) of job {job_id} lost its worker" in survivor.text()
        # The reconciler put the messages the broker restart lost back on the queue.
        assert re.search(r"'republished': [1-9]", survivor.text()), survivor.text()[-2000:]
        for row in report:
            job = store.get_job(row["job"])
            if row["capture"] in broken:
                assert row["state"] == "failed" and row["points"] is None
                file = broken[row["capture"]][1]
                assert f"{row['capture']}:{file}" in row["error"] and "\n" not in row["error"], row["error"]
                continue
            assert row["state"] == "succeeded" and row["error"] is None and row["points"] > 0, row
            assert "cloud.ply" in [a["name"] for a in row["artifacts"]]
            for st in job.stages:  # exactly once, though a worker died under some of them
                successes = [e for e in store.events(job.id) if e[0] == st.name and e[2] == "succeeded"]
                assert len(successes) == 1, (row["capture"], st.name, successes)
        table = list(csv.DictReader(io.StringIO(client.get(f"/v1/batches/{batch['id']}/report.csv", headers=auth).text)))
        assert [(t["capture"], t["state"], t["error"]) for t in table] == [
            (row["capture"], row["state"], row["error"] or "") for row in report
        ]


def _group(pgid: int) -> set[int]:
    """Pids of the processes in process group ``pgid`` (a worker and its pool children)."""
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid:  # fields after the name: state, ppid, pgrp, ...
            out.add(int(stat.parent.name))
    return out

