"""The stage runner in-process (no broker): a job's cloud equals ``scan``'s, duplicates do
nothing, identical work is reused, bad input fails once with a one-line reason, and the
same holds with the artifacts on S3 (moto)."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest

from shared.formats.ply import read_ply
from shared.service.artifacts import ArtifactStore, detached_key, sha256_file
from shared.service.jobs import graph_for
from shared.service.jobstore import Job, JobStore, NewJob
from tests.support.jobsvc import capture_zip, make_env
from workers.runner import run_stage

#: Tiny previews keep the render stages quick in tests.
FAST = {"preview": {"size": [96, 72], "seconds": 0.5, "fps": 4}}


def submit(settings, archive: Path, kind: str = "scan") -> tuple[JobStore, Job]:
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("t")
    arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
    key = sha256_file(archive)
    arts.put_files(key, {"capture.zip": archive})
    job, _ = store.create_job(owner.id, NewJob(kind=kind, capture_ref=f"object:{key}", capture_key=key,
                                               graph=graph_for(kind), name=archive.name, params=FAST))  # fmt: skip
    return store, job


def drive(store: JobStore, settings, job_id: str) -> tuple[Job, list[str]]:
    """Run queued stages in-process until the job is final; the outcomes in order."""
    outcomes = []
    for _ in range(20):
        job = store.get_job(job_id)
        if job.state in ("succeeded", "failed", "cancelled"):
            return job, outcomes
        for st in job.stages:
            if st.state == "queued":
                outcomes.append(run_stage(st.id, settings, publish=False).status)
    raise AssertionError(f"job {job_id} did not finish: {store.get_job(job_id)}")


def cloud_points(path: Path) -> np.ndarray:
    return read_ply(path).xyz


@pytest.mark.slow
def test_job_cloud_equals_scan_and_duplicates_do_nothing(tmp_path: Path, small_capture: Path) -> None:
    from shared.scan.pipeline import scan

    settings = make_env(tmp_path / "svc").settings
    store, job = submit(settings, capture_zip(small_capture, tmp_path / "c.zip"))
    done, outcomes = drive(store, settings, job.id)
    assert done.state == "succeeded", done
    assert outcomes == ["succeeded"] * len(done.stages)
    if any(s.is_map for s in graph_for("scan")):  # tiles fanned out into chunk stages, merged after
        assert any(s.name.startswith("tiles_chunk#") for s in done.stages)
    arts = ArtifactStore(settings.storage_url)
    cloud = arts.fetch(done.stage("triangulate").output_key, tmp_path / "cache") / "cloud.ply"
    report = scan(small_capture, tmp_path / "embedded")
    ours, theirs = cloud_points(cloud), cloud_points(tmp_path / "embedded" / "cloud.ply")
    assert len(ours) == report["points"] > 1000
    np.testing.assert_array_equal(ours, theirs)
    # A re-delivered message for a finished stage finds it done and does nothing.
    assert run_stage(done.stage("decode").id, settings, publish=False).status == "skipped"
    assert [e[2] for e in store.events(job.id) if e[0] == "decode"].count("succeeded") == 1
    # The same capture again: every stage finds its output by key and runs nothing.
    store2, job2 = submit(settings, capture_zip(small_capture, tmp_path / "c2.zip"))
    done2, outcomes2 = drive(store2, settings, job2.id)
    assert outcomes2 == ["reused"] * len(done2.stages) and all(s.reused for s in done2.stages)
    assert done2.stage("triangulate").output_key == done.stage("triangulate").output_key


def test_bad_input_fails_once_with_one_line_reason(tmp_path: Path, small_capture: Path) -> None:
    settings = make_env(tmp_path / "svc").settings
    archive = capture_zip(small_capture, tmp_path / "broken.zip", replace={"col_01.png": b"\x89PNG\r\n\x1a\ntruncated"})
    store, job = submit(settings, archive)
    done, outcomes = drive(store, settings, job.id)
    assert done.state == "failed" and outcomes == ["failed"]
    ingest = done.stage("ingest")
    assert ingest.attempts == 1 and "\n" not in ingest.error
    assert "col_01.png" in ingest.error and done.error.startswith("ingest: ")
    assert {s.name: s.state for s in done.stages} == {"ingest": "failed"} | {s.name: "cancelled" for s in done.stages[1:]}


@pytest.mark.slow
def test_runner_on_s3_store(tmp_path: Path, small_capture: Path, moto_endpoint: str,
                           monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    import boto3

    for k, v in {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}.items():
        monkeypatch.setenv(k, v)
    bucket = f"b{uuid.uuid4().hex[:12]}"
    boto3.client("s3", endpoint_url=moto_endpoint).create_bucket(Bucket=bucket)
    settings = make_env(tmp_path / "svc", GRAYLIGHT_STORAGE_URL=f"s3://{bucket}/gl",
                        GRAYLIGHT_S3_ENDPOINT=moto_endpoint).settings  # fmt: skip
    store, job = submit(settings, capture_zip(small_capture, tmp_path / "c.zip"))
    done, _ = drive(store, settings, job.id)
    assert done.state == "succeeded", done
    arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
    m = arts.verify(done.stage("triangulate").output_key)
    assert "cloud.ply" in m.files and "range.npz" not in m.files  # detached: an object of its own
    assert set(arts.verify(detached_key(done.stage("triangulate").output_key, "range.npz")).files) == {"range.npz"}
    assert not (Path(settings.storage_url)).exists()  # nothing went to a local folder by mistake


@pytest.mark.slow
def test_tiles_fan_out_into_chunk_stages_and_merge(tmp_path: Path, small_capture: Path) -> None:
    import json

    settings = make_env(tmp_path / "svc").settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("t")
    arts = ArtifactStore(settings.storage_url)
    archive = capture_zip(small_capture, tmp_path / "c.zip")
    key = sha256_file(archive)
    arts.put_files(key, {"capture.zip": archive})
    params = {"tiles": {"max_chunk": 2000, "max_leaf": 500}, "preview": FAST["preview"]}
    job, _ = store.create_job(owner.id, NewJob(kind="scan", capture_ref=f"object:{key}", capture_key=key,
                                               graph=graph_for("scan", params), params=params))  # fmt: skip
    done, _ = drive(store, settings, job.id)
    assert done.state == "succeeded", done
    chunks = [s for s in done.stages if s.name.startswith("tiles_chunk#")]
    assert len(chunks) > 1 and sorted(done.stage("tiles").depends_on) == sorted(["tiles_plan", *(c.name for c in chunks)])
    tiles = arts.fetch(done.stage("tiles").output_key, tmp_path / "cache")
    meta = json.loads((tiles / "metadata.json").read_text())
    cloud = arts.fetch(done.stage("triangulate").output_key, tmp_path / "cache") / "cloud.ply"
    assert meta["points"] == len(read_ply(cloud)) > 1000  # every point once, over all chunks


def test_cancel_stops_a_running_stage_at_its_next_progress_report(tmp_path: Path) -> None:
    import threading
    import time

    settings = make_env(tmp_path / "svc").settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("c")
    seconds = 60.0  # the longest probe: far longer than cancelling takes
    job, ready = store.create_job(owner.id, NewJob(kind="probe", capture_ref="none:", capture_key="c" * 64,
                                                   graph=graph_for("probe"), params={"seconds": seconds}))  # fmt: skip
    result = {}

    def run() -> None:
        t0 = time.monotonic()
        result["outcome"] = run_stage(ready[0].id, settings, publish=False)
        result["ran"] = time.monotonic() - t0

    worker = threading.Thread(target=run)
    worker.start()
    # Cancel once the stage has reported progress through a heartbeat (it is running).
    while store.get_job(job.id).stage("probe").progress == 0.0 and worker.is_alive():
        time.sleep(0.05)
    assert store.cancel_job(job.id) is not None
    worker.join(seconds + 30)
    assert result["outcome"].status == "lost"
    # It stopped instead of sleeping its minute out, and stored nothing.
    assert result["ran"] < seconds
    final = store.get_job(job.id)
    assert final.state == "cancelled" and final.stage("probe").output_key is None
