"""Operations: ``/metrics`` scraped after jobs ran (real database and Redis, stages run by the
real runner in this process) counts them, times their stages, sees the store and the
reconciler's repairs; JSON log lines carry the job and stage ids."""

from __future__ import annotations

import io
import json
import logging
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from services.api.app import create_app
from shared.service.jobstore import JobStore
from shared.service.logs import JsonFormatter, configure_logging, log_context
from tests.support import inprocess, jobsvc
from workers.reconciler import reconcile_once


def scrape(client: TestClient) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for fam in text_string_to_metric_families(r.text) for s in fam.samples}  # fmt: skip


def test_metrics_count_jobs_stages_store_and_repairs(tmp_path: Path) -> None:
    with jobsvc.service_env(tmp_path) as senv:
        store = JobStore(senv.settings.database_url)
        key = store.create_key("ops")[1]
        client = TestClient(create_app(senv.settings))
        auth = {"Authorization": f"Bearer {key}"}
        before = scrape(client)
        assert before[("graylight_artifact_store_bytes", ())] == 0
        assert before[("graylight_queue_depth", (("queue", "cpu"),))] == 0

        done = client.post("/v1/jobs", headers=auth, json={"kind": "probe", "params": {"seconds": 0.01}}).json()
        waiting = client.post("/v1/jobs", headers=auth, json={"kind": "probe"}).json()
        m = scrape(client)
        assert m[("graylight_jobs", (("kind", "probe"), ("state", "queued")))] == 2
        # Both messages wait on the broker (Redis): no worker consumes this test's queues.
        assert m[("graylight_queue_depth", (("queue", "cpu"),))] == 2

        inprocess.drive(senv.settings, done["id"])
        m = scrape(client)
        assert m[("graylight_jobs", (("kind", "probe"), ("state", "succeeded")))] == 1
        assert m[("graylight_jobs", (("kind", "probe"), ("state", "queued")))] == 1
        assert m[("graylight_stage_duration_seconds_count", (("stage", "probe"),))] == 1
        job = store.get_job(done["id"])
        took = job.stages[0].finished_at - job.stages[0].started_at
        assert m[("graylight_stage_duration_seconds_sum", (("stage", "probe"),))] == pytest.approx(took)
        assert m[("graylight_stage_duration_seconds_bucket", (("le", "+Inf"), ("stage", "probe")))] == 1
        artifacts = client.get(f"/v1/jobs/{done['id']}/artifacts", headers=auth).json()["artifacts"]
        stored = sum(a["size"] for a in artifacts if "/" in a["name"])
        assert m[("graylight_artifact_store_bytes", ())] >= stored > 0
        assert m[("graylight_stages", (("queue", "cpu"), ("state", "succeeded")))] == 1

        # A worker that vanished mid-stage: the reconciler re-queues it, the metrics count the repair.
        st = store.get_job(waiting["id"]).stages[0]
        assert store.claim_stage(st.id, "gone:1") is not None
        assert m[("graylight_reconciler_repairs_total", (("repair", "lease_expired"),))] == 0
        reconcile_once(senv.settings, store, now=st.queued_at + 3600)
        m = scrape(client)
        assert m[("graylight_reconciler_repairs_total", (("repair", "lease_expired"),))] == 1


def test_json_log_lines_carry_job_and_stage(tmp_path: Path) -> None:
    capture = jobsvc.simulate_small(tmp_path / "plane")
    archive = jobsvc.capture_zip(capture, tmp_path / "plane.zip")
    with jobsvc.service_env(tmp_path, GRAYLIGHT_LOG_FORMAT="json") as senv:
        key = JobStore(senv.settings.database_url).create_key("logs")[1]
        client = TestClient(create_app(senv.settings))
        auth = {"Authorization": f"Bearer {key}"}
        ids = []
        for _ in range(2):
            r = client.post("/v1/jobs", headers=auth, files={"capture": ("plane.zip", archive.read_bytes(), "application/zip")},
                            data={"params": '{"render": false}'})  # fmt: skip
            ids.append(r.json()["id"])
        inprocess.drive(senv.settings, ids[0], stop_after="ingest")

        out = io.StringIO()
        handler = logging.StreamHandler(out)
        root = logging.getLogger()
        old_level = root.level
        # configure_logging switches every root handler, pytest's own too: put theirs back after.
        old_formatters = [(h, h.formatter) for h in root.handlers]
        root.addHandler(handler)
        try:
            configure_logging(senv.settings, logging.INFO)  # switches every root handler, ours too
            assert isinstance(handler.formatter, JsonFormatter)
            # The second job's ingest finds the first's output (same capture): the runner logs that.
            inprocess.drive(senv.settings, ids[1], stop_after="ingest")
            with log_context(job="j-1"):
                logging.getLogger("graylight.test").warning("outside any stage", extra={"stage": "s-1"})
        finally:
            root.removeHandler(handler)
            root.setLevel(old_level)
            for h, f in old_formatters:
                h.setFormatter(f)
        lines = [json.loads(line) for line in out.getvalue().splitlines()]
        reuse = [d for d in lines if d["logger"] == "workers.runner" and "reusing" in d["message"]]
        ingest = JobStore(senv.settings.database_url).get_job(ids[1]).stage("ingest").id
        assert reuse and all(d["job"] == ids[1] and d["stage"] == "ingest" and d["stage_id"] == ingest for d in reuse)
        mine = [d for d in lines if d["logger"] == "graylight.test"]
        assert mine == [{**mine[0], "level": "WARNING", "message": "outside any stage", "job": "j-1", "stage": "s-1"}]
        assert mine[0]["time"].endswith("Z") and "T" in mine[0]["time"]


def test_compose_watches_the_service() -> None:
    """The compose file runs Flower on the workers' own Celery app and a Prometheus that
    scrapes the API's /metrics; a worker serves the control queue beside those that skip it."""
    import yaml

    deploy = Path(__file__).resolve().parents[2] / "deploy"
    services = yaml.safe_load((deploy / "compose.yaml").read_text())["services"]
    assert "workers.celery_app:app" in services["flower"]["command"] and "flower" in services["flower"]["command"]
    mount = next(v for v in services["prometheus"]["volumes"] if v.endswith("/etc/prometheus/prometheus.yml:ro"))
    config = yaml.safe_load((deploy / mount.split(":")[0]).read_text())
    [job] = config["scrape_configs"]
    api_port = services["api"]["command"][services["api"]["command"].index("--port") + 1]
    assert job["metrics_path"] == "/metrics" and job["static_configs"][0]["targets"] == [f"api:{api_port}"]
    assert services["worker-control"]["command"][3] == "control"
    assert all("--no-control" in services[w]["command"] for w in ("worker-cpu", "worker-render"))
