"""The reconciler against a real Redis (private queue names): expired leases are re-queued
and re-published, lost messages are re-published, a stage that keeps killing workers fails,
and the nightly re-render queues a re-render beside the job, touching none of its stages."""

from __future__ import annotations

import time
from pathlib import Path

import redis

from shared.service.jobs import StageSpec, fan_out, fanout_index, graph_for, stage_key, stage_spec
from shared.service.jobstore import JobStore, NewJob
from shared.service.rerenders import RerenderStore
from tests.support.jobsvc import ServiceEnv
from workers.reconciler import reconcile_once
from workers.rerender import enqueue_rerenders, run_rerender


def queue_len(senv: ServiceEnv, queue: str) -> int:
    s = senv.settings
    return int(redis.Redis.from_url(s.broker_url).llen(s.queue(queue)))


def probe_job(store: JobStore, owner: int, i: int = 0):
    return store.create_job(owner, NewJob(kind="probe", capture_ref="none:", capture_key=f"{i:064x}",
                                          graph=graph_for("probe"), params={"seconds": 0}))  # fmt: skip


def test_expired_lease_requeued_and_published(svc_env: ServiceEnv) -> None:
    settings = svc_env.settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("r")
    job, ready = probe_job(store, owner.id)
    claim = store.claim_stage(ready[0].id, "doomed-worker")
    assert reconcile_once(settings, store).expired == 0  # the lease is fresh
    report = reconcile_once(settings, store, now=time.time() + settings.lease_seconds + 1)
    assert report.expired == 1 and report.republished == 1
    assert store.get_job(job.id).stage("probe").state == "queued"
    assert queue_len(svc_env, "cpu") == 1
    assert not store.heartbeat(claim.stage.id, claim.token)


def test_lost_message_republished_only_when_queue_is_empty(svc_env: ServiceEnv) -> None:
    settings = svc_env.settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("r")
    probe_job(store, owner.id, 1)  # queued in the database, never published (a lost message)
    later = time.time() + settings.lease_seconds + 1
    assert reconcile_once(settings, store, now=later).republished == 1
    assert queue_len(svc_env, "cpu") == 1
    # Its message now waits in the queue: no duplicate while it does.
    assert reconcile_once(settings, store, now=later + settings.lease_seconds + 1).republished == 0
    assert queue_len(svc_env, "cpu") == 1


def test_stage_that_keeps_killing_workers_fails(svc_env: ServiceEnv) -> None:
    settings = svc_env.with_(GRAYLIGHT_MAX_ATTEMPTS="2").settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("r")
    job, ready = probe_job(store, owner.id, 2)
    for _ in range(2):
        store.claim_stage(ready[0].id, "oom")
        reconcile_once(settings, store, now=time.time() + settings.lease_seconds + 1)
    j = store.get_job(job.id)
    assert j.state == "failed" and "worker lost 2 times" in j.error


def finished_scan_job(store: JobStore, owner: int):
    """A scan job every stage of which completed with the key it would really have (two map
    pieces), none of them stored."""
    graph = graph_for("scan")
    job, ready = store.create_job(owner, NewJob(kind="scan", capture_ref="object:x", capture_key="c" * 64, graph=graph))
    keys: dict[str, str] = {}
    while True:
        queued = [s for s in store.get_job(job.id).stages if s.state == "queued"]
        if not queued:
            break
        for st in queued:
            spec = stage_spec("scan", st.name)
            keys[st.name] = stage_key(spec, "c" * 64, {}, {d: keys[d] for d in st.depends_on}, fanout_index(st.name))
            expand = fan_out(graph, spec.name, 2)
            c = store.claim_stage(st.id, "w")
            assert store.complete_stage(st.id, c.token, keys[st.name], expand=expand)[0]
    return store.get_job(job.id), graph


def test_nightly_rerender_queues_beside_the_job(svc_env: ServiceEnv, tmp_path: Path) -> None:
    settings = svc_env.settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("r")
    done, graph = finished_scan_job(store, owner.id)
    job = done
    assert done.state == "succeeded"
    if any(m.is_map for m in graph):
        assert {"tiles_chunk#0", "tiles_chunk#1"} <= {s.name for s in done.stages}
        assert sorted(done.stage("tiles").depends_on) == ["tiles_chunk#0", "tiles_chunk#1", "tiles_plan"]
    assert enqueue_rerenders(settings, "changed", store) == 0  # nothing changed
    assert enqueue_rerenders(settings, "all", store) == 1
    assert enqueue_rerenders(settings, "all", store) == 0  # one at a time a job
    j = store.get_job(job.id)
    # The job is untouched: its state, its end, every stage and its attempts.
    assert j.state == "succeeded" and j.finished_at == done.finished_at and "preview_epoch" not in j.params
    assert [(s.name, s.state, s.attempts, s.output_key) for s in j.stages] == [
        (s.name, s.state, s.attempts, s.output_key) for s in done.stages]
    rec = RerenderStore(store).latest_rerender(job.id)
    assert rec.state == "queued" and rec.params["preview_epoch"] and rec.base_key == done.stage("preview").output_key
    assert queue_len(svc_env, "render") == 1 and queue_len(svc_env, "cpu") == 0
    assert isinstance(stage_spec("scan", "preview"), StageSpec)
    # Its worker dies mid-render: after a lease the reconciler queues it again (and publishes
    # it); the job is still untouched.
    rr = RerenderStore(store)
    held = rr.claim_rerender(rec.id)
    assert held is not None and rr.claim_rerender(rec.id) is None  # a duplicate message does nothing
    assert reconcile_once(settings, store).rerenders_requeued == 0  # its lease is fresh
    report = reconcile_once(settings, store, now=time.time() + settings.lease_seconds + 1)
    assert report.rerenders_requeued == 1 and rr.get_rerender(rec.id).state == "queued"
    assert queue_len(svc_env, "render") == 2
    assert not rr.heartbeat_rerender(rec.id, held.lease_token)  # the dead worker's lease is gone
    # Queued behind other messages, it is not re-sent every pass (a nightly run of thousands
    # would pile up duplicates), only after ten leases.
    later = time.time() + settings.lease_seconds + 1
    assert reconcile_once(settings, store, now=later).rerenders_requeued == 0
    assert reconcile_once(settings, store, now=later + 10 * settings.lease_seconds).rerenders_requeued == 1
    assert queue_len(svc_env, "render") == 3
    assert store.get_job(job.id).state == "succeeded"


def test_a_rerender_that_fails_unexpectedly_says_so_without_the_bare_exception(svc_env: ServiceEnv) -> None:
    """A re-render whose job's tiles are gone from the store (its keys were never stored here):
    it fails, and its reason reads as a stage's does -- the stage and what it was reading --
    not the exception's name and text, which may carry a worker's paths (they go to the log)."""
    settings = svc_env.settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("r")
    done, _ = finished_scan_job(store, owner.id)
    assert enqueue_rerenders(settings, "all", store) == 1
    rec = RerenderStore(store).latest_rerender(done.id)
    assert run_rerender(rec.id, settings) == "failed"
    error = RerenderStore(store).get_rerender(rec.id).error
    assert error.startswith("stage preview ") and "the worker's log has the details" in error, error
    assert "Error" not in error and str(settings.cache_dir) not in error, error
    assert store.get_job(done.id).state == "succeeded"  # the job is untouched


def test_abandoned_upload_sessions_are_deleted_with_their_chunks(svc_env: ServiceEnv, tmp_path: Path) -> None:
    from shared.service.artifacts import ArtifactStore

    settings = svc_env.settings
    store = JobStore(settings.database_url)
    arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
    owner, _ = store.create_key("u")
    chunk = tmp_path / "chunk"
    chunk.write_bytes(b"x" * 1000)
    old = store.create_upload(owner.id, "old.zip")
    time.sleep(0.05)
    new = store.create_upload(owner.id, "new.zip")
    for up in (old, new):
        arts.put_chunk(up.id, 0, chunk)
        assert store.advance_upload(up.id, 0, 1000)
    ttl = settings.upload_ttl_hours * 3600
    assert reconcile_once(settings, store, arts=arts).uploads_deleted == 0  # both are fresh
    # The moment the older session passes its lifetime and the newer has not.
    report = reconcile_once(settings, store, now=new.created_at - 0.01 + ttl, arts=arts)
    assert report.uploads_deleted == 1
    assert store.get_upload(old.id) is None
    assert not arts.fs.exists(arts._upload_dir(old.id))
    kept = store.get_upload(new.id)
    assert kept is not None and kept.offset == 1000 and arts.fs.exists(arts._upload_dir(new.id))
