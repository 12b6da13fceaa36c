"""``params.compress.keep_range`` false stores the raw range image only until ``range.glr`` is
stored: triangulate detaches ``range.npz`` into an object of its own, and the compress stage
deletes that object once its own output is stored. Through the real runner on the real
PostgreSQL: the drop shows in the stored-bytes accounting, a compress that fails keeps the
range image, and a compress run again after the drop (new parameters, or another job reusing
the triangulation) gets it back from a new run of the triangulation, bit-identical."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from shared.compress.range import read_range
from shared.service.artifacts import ArtifactStore, detached_key, sha256_file
from shared.service.config import Settings
from shared.service.jobs import StageView, graph_for, row_key, rows_to_rerun
from shared.service.jobstore import Job, JobStore, NewJob
from shared.service.queue import publish_stages
from shared.service.usage import ObjectSizes, key_usage
from tests.support.inprocess import drive, submit_scan_job
from tests.support.jobsvc import ServiceEnv, start_worker, wait_for

DROP = {"render": False, "export": False, "compress": {"max_error": 0.5, "keep_range": False}}
KEEP = {"render": False, "export": False}


def _submit(settings: Settings, capture: Path, tmp: Path, params: dict[str, Any],
            publish: bool = False) -> tuple[JobStore, ArtifactStore, int, Job]:  # fmt: skip
    store, arts, owner, job, queued = submit_scan_job(settings, capture, tmp, params)
    if publish:
        publish_stages(queued, settings)
    return store, arts, owner, job


def _retry(store: JobStore, job: Job, params: dict[str, Any]) -> None:
    """What ``POST /v1/jobs/{id}/retry`` does (services.api.routers.jobs.rerun), without HTTP."""
    rows = [StageView(st.name, st.state, st.depends_on, st.output_key) for st in job.stages]
    todo = rows_to_rerun(job.kind, rows, job.capture_key, params)
    assert todo
    store.reset_stages(job.id, todo, params=params)


def _range_key(job: Job) -> str:
    return detached_key(job.stage("triangulate").output_key, "range.npz")


def _object_bytes(arts: ArtifactStore, key: str) -> int:
    m = arts.manifest(key)
    return sum(e.size for e in m.files.values()) if m is not None else 0


def test_keep_range_false_deletes_the_raw_range_once_compressed(pg_env: ServiceEnv, small_capture: Path,
                                                                tmp_path: Path) -> None:  # fmt: skip
    settings = pg_env.settings
    store, arts, owner, job = _submit(settings, small_capture, tmp_path, DROP)
    sizes = ObjectSizes(arts, recheck_seconds=0.0)
    drive(settings, job.id, stop_after="triangulate")
    job = store.get_job(job.id)
    tri = job.stage("triangulate")
    assert tri.state == "succeeded" and job.stage("compress").state == "queued"
    # The range image is its own object, not a file of triangulate's.
    assert "range.npz" not in arts.manifest(tri.output_key).files
    raw = arts.fetch(_range_key(job), tmp_path / "cache") / "range.npz"
    with np.load(raw) as d:
        z = d["z"].copy()
    range_bytes = _object_bytes(arts, _range_key(job))
    assert range_bytes == raw.stat().st_size > 10_000
    before = key_usage(store, sizes, owner).stored_bytes

    drive(settings, job.id)
    job = store.get_job(job.id)
    assert job.state == "succeeded", job
    assert not arts.exists(_range_key(job))  # no longer stored anywhere
    out = arts.fetch(job.stage("compress").output_key, tmp_path / "cache")
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == ["compress.json", "range.glr"]
    back = read_range(out / "range.glr").z
    m = ~np.isnan(z)
    np.testing.assert_array_equal(np.isnan(back), ~m)
    assert np.abs(back[m].astype(np.float64) - z[m]).max() <= 0.5
    # The accounting sees the drop: less the range image, plus compress's own object.
    after = key_usage(store, sizes, owner).stored_bytes
    # The stages after triangulate (compress, and publish since issue 25) added their objects.
    added = {n: _object_bytes(arts, job.stage(n).output_key) for n in ("compress", "publish")}
    assert after == before - range_bytes + sum(added.values())
    assert after - added["publish"] < before


def test_a_failed_compress_keeps_the_raw_range_and_its_retry_drops_it(pg_env: ServiceEnv, small_capture: Path,
                                                                      tmp_path: Path) -> None:  # fmt: skip
    settings = pg_env.settings
    store, arts, _owner, job = _submit(settings, small_capture, tmp_path, DROP)
    drive(settings, job.id, stop_after="triangulate")
    job = store.get_job(job.id)
    key = row_key("scan", "compress", job.capture_key, job.params, {"triangulate": job.stage("triangulate").output_key})
    # The compress stage cannot store its output: its object's folder is taken by a file.
    blocker = Path(settings.storage_url) / "objects" / key[:2] / key
    blocker.parent.mkdir(parents=True, exist_ok=True)
    blocker.write_text("in the way")
    drive(settings, job.id)
    job = store.get_job(job.id)
    assert job.state == "failed" and job.stage("compress").state == "failed", job
    err = job.stage("compress").error
    assert "could not store its output as object " + key in err and "nothing of it was kept" in err, err
    assert str(settings.storage_url) not in err and "NotADirectoryError" not in err, err  # no worker path
    assert arts.exists(_range_key(job))  # the range image is still there
    arts.verify(_range_key(job))

    blocker.unlink()
    _retry(store, job, job.params)
    drive(settings, job.id)
    job = store.get_job(job.id)
    assert job.state == "succeeded" and job.stage("compress").attempts == 2, job
    assert arts.exists(job.stage("compress").output_key) and not arts.exists(_range_key(job))


def test_compress_after_the_drop_gets_the_range_back_bit_identical(pg_env: ServiceEnv, small_capture: Path,
                                                                   tmp_path: Path) -> None:  # fmt: skip
    settings = pg_env.settings
    store, arts, owner, job = _submit(settings, small_capture, tmp_path, DROP)
    drive(settings, job.id)
    job = store.get_job(job.id)
    assert job.state == "succeeded" and not arts.exists(_range_key(job))
    tri_key = job.stage("triangulate").output_key
    with arts.open(tri_key, ".detached.json") as f:
        want = json.loads(f.read())["range.npz"]

    # The job retried with other compress parameters: the compression runs again on a range
    # image made again by the triangulation (its row is not re-run), then dropped again.
    _retry(store, job, {**DROP, "compress": {"quantum": 0.05, "keep_range": False}})
    drive(settings, job.id)
    job = store.get_job(job.id)
    assert job.state == "succeeded", job
    assert job.stage("triangulate").attempts == 1 and job.stage("compress").attempts == 2
    assert job.stage("compress").summary["mode"] == "lossless"
    assert not arts.exists(_range_key(job))

    # Another job of the same capture keeps the range: it reuses the triangulation, and its
    # compress stage gets the range image back, byte for byte the one first stored.
    other_job, _ = store.create_job(owner, NewJob(kind="scan", capture_ref=job.capture_ref, capture_key=job.capture_key,
                                                  graph=graph_for("scan", KEEP), name="c.zip", params=KEEP))  # fmt: skip
    drive(settings, other_job.id)
    other = store.get_job(other_job.id)
    assert other.state == "succeeded", other
    assert other.stage("triangulate").output_key == tri_key and other.stage("triangulate").reused
    kept = arts.fetch(other.stage("compress").output_key, tmp_path / "cache") / "range.npz"
    assert sha256_file(kept) == want["sha256"] and kept.stat().st_size == want["size"]
    assert arts.exists(_range_key(other))  # this job keeps it


@pytest.mark.parametrize("params", [KEEP, {**KEEP, "compress": {"quantum": 0.02, "keep_range": True}}])
def test_keep_range_true_keeps_the_raw_range(pg_env: ServiceEnv, small_capture: Path, tmp_path: Path,
                                             params: dict[str, Any]) -> None:  # fmt: skip
    settings = pg_env.settings
    store, arts, _owner, job = _submit(settings, small_capture, tmp_path, params)
    drive(settings, job.id)
    job = store.get_job(job.id)
    assert job.state == "succeeded", job
    assert arts.exists(_range_key(job))
    raw = arts.fetch(_range_key(job), tmp_path / "cache") / "range.npz"
    published = arts.fetch(job.stage("compress").output_key, tmp_path / "cache") / "range.npz"
    assert sha256_file(raw) == sha256_file(published)


@pytest.mark.slow
def test_a_worker_process_drops_the_raw_range(pg_env: ServiceEnv, small_capture: Path, tmp_path: Path) -> None:
    """The same through the broker: stages published on the real Redis, run by a worker process."""
    settings = pg_env.settings
    worker = start_worker(pg_env, "cpu", concurrency=1)
    store, arts, _owner, job = _submit(settings, small_capture, tmp_path, DROP, publish=True)
    wait_for(lambda: store.get_job(job.id).state in ("succeeded", "failed"), 120, "the job final", worker, interval=0.2)
    job = store.get_job(job.id)
    assert job.state == "succeeded", job
    assert arts.exists(job.stage("compress").output_key) and not arts.exists(_range_key(job))
    assert "range.npz" not in arts.verify(job.stage("triangulate").output_key).files


def test_which_inputs_a_stage_releases() -> None:
    from shared.service.jobs import released_inputs, stage_spec

    compress = stage_spec("scan", "compress")
    assert stage_spec("scan", "triangulate").detach == ("range.npz",)
    assert released_inputs(compress, {"compress": {"max_error": 0.5, "keep_range": False}}) == ("triangulate/range.npz",)
    for params in [{}, {"compress": None}, {"compress": {"quantum": 0.02}}, {"compress": {"keep_range": True}}]:
        assert released_inputs(compress, params) == ()
    assert released_inputs(stage_spec("scan", "export"), {"compress": {"keep_range": False}}) == ()
    key = "ab" * 32
    assert detached_key(key, "range.npz") == detached_key(key, "range.npz") != detached_key(key, "other.npz")
    assert detached_key(key, "range.npz") != key and len(detached_key(key, "range.npz")) == 64
    with pytest.raises(Exception, match="not a relative path"):
        detached_key(key, "../range.npz")
