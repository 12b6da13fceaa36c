"""Collections at scale, through the API with the real database and Redis (stages run in the
test process by the real runner): a batch's progress, its report (CSV and JSON, one row per
capture), retrying only what failed, ``graylight batch ...`` against a live server, and the
limits per API key (429 and 507, nothing accepted half-way)."""

from __future__ import annotations

import csv
import io
import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from shared.formats.ply import read_header
from shared.service.archive import ArchiveLimits, inspect_archive
from shared.service.jobstore import JobStore
from tests.support import inprocess, jobsvc

NO_RENDER = '{"render": false}'


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return jobsvc.simulate_small(tmp_path_factory.mktemp("cap") / "plane")


@pytest.fixture
def pg_url() -> Iterator[str]:
    with jobsvc.pg_database() as url:
        yield url


def _client(senv: jobsvc.ServiceEnv, name: str = "alice") -> tuple[TestClient, dict[str, str]]:
    key = JobStore(senv.settings.database_url).create_key(name)[1]
    return TestClient(create_app(senv.settings)), {"Authorization": f"Bearer {key}"}


def _files(archives: list[Path]) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [("captures", (a.name, a.read_bytes(), "application/zip")) for a in archives]


def _objects(root: Path) -> set[Path]:
    return set((root / "objects").rglob("MANIFEST.json")) if (root / "objects").exists() else set()


def _successes(store: JobStore, job_id: str) -> dict[str, int]:
    out: dict[str, int] = {}
    for stage, _old, new, _detail in store.events(job_id):
        if stage is not None and new == "succeeded":
            out[stage] = out.get(stage, 0) + 1
    return out


@pytest.mark.slow
def test_batch_progress_report_and_retry_of_what_failed(capture: Path, tmp_path: Path, pg_url: str) -> None:
    with jobsvc.service_env(tmp_path, GRAYLIGHT_DATABASE_URL=pg_url) as senv:
        client, auth = _client(senv)
        good = [jobsvc.capture_zip(capture, tmp_path / f"vase {i}.zip", note=str(i)) for i in range(2)]
        no_rig = jobsvc.capture_zip(capture, tmp_path / "no-rig.zip", drop=("rig.json",))
        bad_png = jobsvc.capture_zip(capture, tmp_path / "bad-png.zip", note="b", replace={"col_03.png": (capture / "col_03.png").read_bytes()[:200]})
        r = client.post("/v1/batches", headers=auth, data={"name": "museum 7", "params": NO_RENDER},
                        files=_files([*good, no_rig, bad_png]))  # fmt: skip
        assert r.status_code == 201, r.text
        b = r.json()
        assert len(b["jobs"]) == 4 and b["counts"] == {"queued": 4} and b["progress"] == 0.0
        for j in b["jobs"]:
            inprocess.drive(senv.settings, j)

        status = client.get(f"/v1/batches/{b['id']}", headers=auth).json()
        assert status["counts"] == {"succeeded": 2, "failed": 2} and status["progress"] == 1.0 and status["total"] == 4

        report = client.get(f"/v1/batches/{b['id']}/report.json", headers=auth).json()
        rows = {row["capture"]: row for row in report["rows"]}
        assert list(rows) == ["vase 0.zip", "vase 1.zip", "no-rig.zip", "bad-png.zip"]  # as submitted, in order
        for name in ("vase 0.zip", "vase 1.zip"):
            row = rows[name]
            assert row["state"] == "succeeded" and row["error"] is None
            cloud = client.get(f"/v1/jobs/{row['job']}/artifacts/cloud.ply", headers=auth)
            (tmp_path / "cloud.ply").write_bytes(cloud.content)
            assert row["points"] == read_header(tmp_path / "cloud.ply").count > 0
            names = [a["name"] for a in row["artifacts"]]
            assert {"capture.json", "decoded.npz", "cloud.ply"} <= set(names)
            url = next(a["url"] for a in row["artifacts"] if a["name"] == "cloud.ply")
            assert url.endswith(f"/v1/jobs/{row['job']}/artifacts/cloud.ply")
        for name, file in (("no-rig.zip", "rig.json"), ("bad-png.zip", "col_03.png")):
            row = rows[name]
            assert row["state"] == "failed" and row["points"] is None
            assert f"{name}:{file}" in row["error"] and "\n" not in row["error"], row["error"]

        text = client.get(f"/v1/batches/{b['id']}/report.csv", headers=auth)
        assert text.status_code == 200 and text.headers["content-type"].startswith("text/csv")
        table = list(csv.DictReader(io.StringIO(text.text)))
        assert [t["capture"] for t in table] == list(rows)
        for t in table:
            row = rows[t["capture"]]
            assert t["state"] == row["state"] and t["error"] == (row["error"] or "")
            assert t["points"] == ("" if row["points"] is None else str(row["points"]))
            assert t["artifacts"].split() == [a["url"] for a in row["artifacts"]]

        store = JobStore(senv.settings.database_url)
        before = {j: (_successes(store, j), store.get_job(j)) for j in b["jobs"]}
        r = client.post(f"/v1/batches/{b['id']}/retry", headers=auth)
        assert r.status_code == 200, r.text
        failed = [rows[n]["job"] for n in ("no-rig.zip", "bad-png.zip")]
        assert sorted(r.json()["retried"]) == sorted(failed)
        for j in b["jobs"]:
            inprocess.drive(senv.settings, j)
        for j, (succ, job) in before.items():
            assert _successes(store, j) == succ  # nothing that had succeeded ran again
            now = store.get_job(j)
            if j in failed:
                kept = [s.name for s in job.stages if s.state == "succeeded"]
                assert all(now.stage(n).attempts == job.stage(n).attempts for n in kept)
                rerun = [s.name for s in job.stages if s.state != "succeeded"]
                assert any(now.stage(n).attempts > job.stage(n).attempts for n in rerun)
            else:
                assert [s.attempts for s in now.stages] == [s.attempts for s in job.stages]
        assert client.get(f"/v1/batches/{b['id']}", headers=auth).json()["counts"] == {"succeeded": 2, "failed": 2}
        other = _client(senv, "bob")[1]
        for path in ("", "/report.csv", "/report.json"):
            assert client.get(f"/v1/batches/{b['id']}{path}", headers=other).status_code == 404
        assert client.post(f"/v1/batches/{b['id']}/retry", headers=other).status_code == 404


@pytest.mark.slow
def test_batch_commands_against_a_live_server(capture: Path, tmp_path: Path) -> None:
    with jobsvc.service_env(tmp_path) as senv:
        key = JobStore(senv.settings.database_url).create_key("cli")[1]
        _proc, url = jobsvc.start_api(senv)
        client = TestClient(create_app(senv.settings))
        auth = {"Authorization": f"Bearer {key}"}
        archives = [jobsvc.capture_zip(capture, tmp_path / "ok.zip"),
                    jobsvc.capture_zip(capture, tmp_path / "broken.zip", drop=("rig.json",))]  # fmt: skip
        b = client.post("/v1/batches", headers=auth, data={"name": "cli", "params": NO_RENDER}, files=_files(archives)).json()
        env = {**senv.env, "GRAYLIGHT_API_URL": url, "GRAYLIGHT_API_KEY": key}

        def cli(*args: str) -> subprocess.CompletedProcess:
            return subprocess.run([jobsvc.GRAYLIGHT, "batch", *args], env=env, capture_output=True, text=True, timeout=60)

        r = cli("status", b["id"])
        assert r.returncode == 0 and "2 captures, 2 queued, 0.0 % done" in r.stdout, r.stdout + r.stderr
        for j in b["jobs"]:
            inprocess.drive(senv.settings, j)
        r = cli("status", b["id"])
        assert r.returncode == 1 and "1 failed, 1 succeeded, 100.0 % done" in r.stdout, r.stdout + r.stderr
        r = cli("report", b["id"], "--out", str(tmp_path / "out" / "report.csv"))
        assert r.returncode == 0, r.stderr
        table = list(csv.DictReader((tmp_path / "out" / "report.csv").open()))
        assert [(t["capture"], t["state"]) for t in table] == [("ok.zip", "succeeded"), ("broken.zip", "failed")]
        assert "broken.zip:rig.json" in table[1]["error"]
        r = cli("report", b["id"], "--format", "json")
        assert [row["capture"] for row in json.loads(r.stdout)["rows"]] == ["ok.zip", "broken.zip"]
        r = cli("retry-failed", b["id"])
        assert r.returncode == 0 and r.stdout.split() == [table[1]["job"]]
        r = cli("status", "00000000-0000-0000-0000-000000000000")
        assert r.returncode != 0 and "not found" in r.stderr


def test_limit_of_running_jobs_per_key(tmp_path: Path) -> None:
    with jobsvc.service_env(tmp_path, GRAYLIGHT_KEY_MAX_RUNNING_JOBS="2") as senv:
        client, alice = _client(senv)
        _c, bob = _client(senv, "bob")
        first = [client.post("/v1/jobs", headers=alice, json={"kind": "probe"}).json()["id"] for _ in range(2)]
        r = client.post("/v1/jobs", headers=alice, json={"kind": "probe"})
        assert r.status_code == 429 and "GRAYLIGHT_KEY_MAX_RUNNING_JOBS" in r.json()["detail"] and "2 jobs" in r.json()["detail"]
        assert r.headers["retry-after"]
        assert client.post("/v1/jobs", headers=bob, json={"kind": "probe"}).status_code == 201  # a limit per key
        inprocess.drive(senv.settings, first[0])
        # One slot is free: a batch of two is refused whole, nothing of it recorded.
        r = client.post("/v1/batches", headers=alice, data={"name": "two", "kind": "probe"},
                        files=[("captures", ("a.zip", b"a", "application/zip")), ("captures", ("b.zip", b"b", "application/zip"))])  # fmt: skip
        assert r.status_code == 429, r.text
        assert client.get("/v1/jobs", headers=alice).json()["total"] == 2
        assert client.post("/v1/jobs", headers=alice, json={"kind": "probe"}).status_code == 201
        # A retry is new work too.
        inprocess.drive(senv.settings, first[1])
        assert client.post("/v1/jobs", headers=alice, json={"kind": "probe"}).status_code == 201
        r = client.post(f"/v1/jobs/{first[1]}/retry", headers=alice, json={"params": {"seconds": 0.01}})
        assert r.status_code == 429


def test_limit_of_stored_bytes_per_key(capture: Path, tmp_path: Path) -> None:
    one = jobsvc.capture_zip(capture, tmp_path / "one.zip", note="1")
    two = jobsvc.capture_zip(capture, tmp_path / "two.zip", note="2")
    # The stored archive, and its unpacked copy in a worker's cache while the job is unfinished.
    unpacked = inspect_archive(one, ArchiveLimits()).total_bytes
    limit = one.stat().st_size + unpacked + one.stat().st_size // 2
    with jobsvc.service_env(tmp_path, GRAYLIGHT_KEY_MAX_STORED_BYTES=str(limit)) as senv:
        root = Path(senv.settings.storage_url)
        client, alice = _client(senv)
        r = client.post("/v1/jobs", headers=alice, files={"capture": (one.name, one.read_bytes(), "application/zip")},
                        data={"params": NO_RENDER})  # fmt: skip
        assert r.status_code == 201, r.text
        stored = _objects(root)
        r = client.post("/v1/jobs", headers=alice, files={"capture": (two.name, two.read_bytes(), "application/zip")})
        assert r.status_code == 507 and "GRAYLIGHT_KEY_MAX_STORED_BYTES" in r.json()["detail"] and str(limit) in r.json()["detail"]
        r = client.post("/v1/batches", headers=alice, data={"name": "b"}, files=_files([two]))
        assert r.status_code == 507
        up = client.post("/v1/uploads", headers=alice, json={"filename": "two.zip"}).json()
        r = client.patch(f"/v1/uploads/{up['id']}", headers={**alice, "Upload-Offset": "0"}, content=two.read_bytes())
        assert r.status_code == 507 and client.get(f"/v1/uploads/{up['id']}", headers=alice).json()["offset"] == 0
        assert _objects(root) == stored  # nothing of the refused requests was stored
        assert client.get("/v1/jobs", headers=alice).json()["total"] == 1
        _c, bob = _client(senv, "bob")
        r = client.post("/v1/jobs", headers=bob, files={"capture": (two.name, two.read_bytes(), "application/zip")})
        assert r.status_code == 201  # another key has its own budget
