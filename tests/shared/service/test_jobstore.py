"""The job store on SQLite and on a real PostgreSQL: keys, jobs, the stage state machine,
fan-in counted in the database, leases, cancellation, retries, paging."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from shared.service.jobs import (
    CAPTURE,
    JOB_TRANSITIONS,
    STAGE_TRANSITIONS,
    FanOut,
    StageSpec,
    fan_out,
    graph_for,
    stage_key,
)
from shared.service.jobstore import JobStore, NewJob
from tests.support.jobsvc import pg_database

DIAMOND = (
    StageSpec("a", "cpu", (CAPTURE,), 10),
    StageSpec("b", "cpu", ("a",), 10),
    StageSpec("c", "render", ("a",), 10),
    StageSpec("d", "cpu", ("b", "c"), 10),
)


@pytest.fixture(scope="session")
def pg_url() -> Iterator[str]:
    with pg_database() as url:
        yield url


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> JobStore:
    if request.param == "sqlite":
        return JobStore(f"sqlite:///{tmp_path / 'jobs.db'}")
    url = request.getfixturevalue("pg_url")
    s = JobStore(url)
    # One database per session: start each test from empty tables.
    from shared.service.jobstore import Base

    with s.engine.begin() as conn:
        for table in reversed(Base.metadata.sorted_tables):
            conn.execute(table.delete())
    return s


def new_job(store: JobStore, owner: int, graph=DIAMOND, **kw) -> tuple:
    return store.create_job(
        owner, NewJob(kind="scan", capture_ref="object:ab", capture_key="ab" * 32, graph=graph, **kw)
    )


def run(store: JobStore, stage_id: int, key: str = "k" * 64) -> list:
    claim = store.claim_stage(stage_id, "test")
    assert claim is not None
    ok, newly = store.complete_stage(stage_id, claim.token, key)
    assert ok
    return newly


def test_keys_are_stored_hashed_and_authenticate(store: JobStore) -> None:
    rec, secret = store.create_key("alice")
    assert store.authenticate(secret) == rec
    assert store.authenticate(secret + "x") is None
    with store.session() as s:
        from shared.service.jobstore import ApiKeyRow

        row = s.get(ApiKeyRow, rec.id)
        assert secret not in (row.key_hash, row.prefix) and len(row.key_hash) == 64
    assert store.revoke_key(rec.prefix)
    assert store.authenticate(secret) is None


def test_fan_in_counted_in_database(store: JobStore) -> None:
    owner, _ = store.create_key("o")
    job, ready = new_job(store, owner.id)
    assert [s.name for s in ready] == ["a"]
    newly = run(store, ready[0].id)
    assert sorted(s.name for s in newly) == ["b", "c"]
    st = {s.name: s for s in store.get_job(job.id).stages}
    assert store.get_job(job.id).state == "running"
    assert run(store, st["b"].id) == []  # d still waits for c
    assert store.get_job(job.id).stage("d").state == "pending"
    newly = run(store, st["c"].id)
    assert [s.name for s in newly] == ["d"]
    run(store, st["d"].id)
    done = store.get_job(job.id)
    assert done.state == "succeeded" and done.finished_at is not None
    events = [e for e in store.events(job.id) if e[0] is None]
    assert [e[2] for e in events] == ["queued", "running", "succeeded"]


#: A plan fanning out into a per-item chain (x, then y reading its own x) and a join of every y.
CHAIN = (
    StageSpec("plan", "cpu", (CAPTURE,), 10),
    StageSpec("x", "cpu", (CAPTURE, "plan"), 10, fanout_from="plan"),
    StageSpec("y", "cpu", ("x",), 10, fanout_from="plan"),
    StageSpec("join", "cpu", ("plan", "y"), 10),
)


def _complete(store: JobStore, stage_id: int, expand: FanOut | None = None) -> list:
    claim = store.claim_stage(stage_id, "test")
    assert claim is not None
    ok, newly = store.complete_stage(stage_id, claim.token, "k" * 64, expand=expand)
    assert ok
    return newly


def test_chained_fan_out_runs_item_by_item(store: JobStore) -> None:
    owner, _ = store.create_key("o")
    job, ready = new_job(store, owner.id, graph=CHAIN)
    assert [s.name for s in ready] == ["plan"]
    newly = _complete(store, ready[0].id, fan_out(CHAIN, "plan", 3))
    assert sorted(s.name for s in newly) == ["x#0", "x#1", "x#2"]  # y#i waits for its own x#i
    j = store.get_job(job.id)
    assert j.stage("y#1").depends_on == ("x#1",)
    assert sorted(j.stage("join").depends_on) == ["plan", "y#0", "y#1", "y#2"]
    assert [s.name for s in _complete(store, j.stage("x#1").id)] == ["y#1"]
    assert _complete(store, j.stage("y#1").id) == []  # the join waits for every y
    for i in (0, 2):
        assert [s.name for s in _complete(store, j.stage(f"x#{i}").id)] == [f"y#{i}"]
    assert _complete(store, j.stage("y#0").id) == []
    assert [s.name for s in _complete(store, j.stage("y#2").id)] == ["join"]
    # Rows sort in graph order: every x, then every y, then the join.
    order = [s.name for s in sorted(store.get_job(job.id).stages, key=lambda s: s.position)]
    assert order == ["plan", "x#0", "x#1", "x#2", "y#0", "y#1", "y#2", "join"]
    _complete(store, store.get_job(job.id).stage("join").id)
    assert store.get_job(job.id).state == "succeeded"
    # A re-run of the plan replaces the instances (two items now) and the join's fan-in with them.
    store.reset_stages(job.id, [s.name for s in store.get_job(job.id).stages])
    _complete(store, store.get_job(job.id).stage("plan").id, fan_out(CHAIN, "plan", 2))
    j = store.get_job(job.id)
    assert sorted(s.name for s in j.stages) == ["join", "plan", "x#0", "x#1", "y#0", "y#1"]
    assert sorted(j.stage("join").depends_on) == ["plan", "y#0", "y#1"]
    # A plan that counts no items: the instances go, and the join reads the plan alone and runs.
    store.reset_stages(job.id, [s.name for s in store.get_job(job.id).stages])
    newly = _complete(store, store.get_job(job.id).stage("plan").id, fan_out(CHAIN, "plan", 0))
    j = store.get_job(job.id)
    assert sorted(s.name for s in j.stages) == ["join", "plan"] and j.stage("join").depends_on == ("plan",)
    assert [s.name for s in newly] == ["join"]


def test_concurrent_completions_queue_join_once(store: JobStore) -> None:
    owner, _ = store.create_key("o")
    job, ready = new_job(store, owner.id)
    run(store, ready[0].id)
    j = store.get_job(job.id)
    claims = [store.claim_stage(j.stage(n).id, n) for n in ("b", "c")]
    results: list = []
    barrier = threading.Barrier(2)

    def finish(c) -> None:
        barrier.wait()
        results.append(store.complete_stage(c.stage.id, c.token, "f" * 64))

    threads = [threading.Thread(target=finish, args=(c,)) for c in claims]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    queued = [s.name for ok, newly in results for s in newly]
    assert queued == ["d"]  # exactly one completer saw both parents done


def test_claim_is_exclusive_under_contention(store: JobStore) -> None:
    owner, _ = store.create_key("o")
    _job, ready = new_job(store, owner.id)
    wins: list = []
    barrier = threading.Barrier(6)

    def grab(i: int) -> None:
        barrier.wait()
        c = store.claim_stage(ready[0].id, f"w{i}")
        if c is not None:
            wins.append(c)

    threads = [threading.Thread(target=grab, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(wins) == 1
    assert store.claim_stage(ready[0].id, "late") is None  # a duplicate message does nothing


def test_failure_cancels_downstream_and_names_reason(store: JobStore) -> None:
    owner, _ = store.create_key("o")
    job, ready = new_job(store, owner.id)
    c = store.claim_stage(ready[0].id, "w")
    assert store.fail_stage(c.stage.id, c.token, "white.png: image file is missing\nsecond line")
    j = store.get_job(job.id)
    assert j.state == "failed"
    assert j.error == "a: white.png: image file is missing second line"
    assert {s.name: s.state for s in j.stages} == {
        "a": "failed",
        "b": "cancelled",
        "c": "cancelled",
        "d": "cancelled",
    }
    assert not store.complete_stage(c.stage.id, c.token, "x" * 64)[0]  # no second verdict


def test_expired_lease_is_requeued_once_and_old_holder_loses(store: JobStore) -> None:
    owner, _ = store.create_key("o")
    _job, ready = new_job(store, owner.id)
    c = store.claim_stage(ready[0].id, "dead")
    assert store.expired_leases(time.time() - 60) == []
    expired = store.expired_leases(time.time() + 1)
    assert [s.id for s in expired] == [c.stage.id]
    assert store.requeue_expired(expired[0])
    assert not store.requeue_expired(expired[0])  # compare-and-set: only one reconciler wins
    assert not store.heartbeat(c.stage.id, c.token)  # the old holder learns it lost the lease
    c2 = store.claim_stage(c.stage.id, "alive")
    assert c2 is not None and c2.stage.attempts == 2
    assert not store.complete_stage(c.stage.id, c.token, "a" * 64)[0]
    assert store.complete_stage(c.stage.id, c2.token, "a" * 64)[0]


def test_cancel_and_retry_only_resets_named_stages(store: JobStore) -> None:
    owner, _ = store.create_key("o")
    job, ready = new_job(store, owner.id)
    run(store, ready[0].id)
    j = store.get_job(job.id)
    held = store.claim_stage(j.stage("b").id, "w")
    cancelled = store.cancel_job(job.id)
    assert cancelled.state == "cancelled"
    assert {s.name: s.state for s in cancelled.stages} == {
        "a": "succeeded",
        "b": "cancelled",
        "c": "cancelled",
        "d": "cancelled",
    }
    assert not store.heartbeat(held.stage.id, held.token)
    assert store.cancel_job(job.id) is None
    newly = store.reset_stages(job.id, ["b", "c", "d"])
    assert sorted(s.name for s in newly) == ["b", "c"]
    j = store.get_job(job.id)
    # Work already done counts: the job is running again, its finished stage untouched.
    assert j.state == "running" and j.stage("a").state == "succeeded" and j.stage("a").attempts == 1


def test_list_filters_and_pages_and_owner_isolation(store: JobStore) -> None:
    alice, _ = store.create_key("alice")
    bob, _ = store.create_key("bob")
    batch = store.batch_for(alice.id, "museum")
    assert store.batch_for(alice.id, "museum") == batch
    ids = [new_job(store, alice.id, batch_id=batch if i % 2 else None)[0].id for i in range(7)]
    new_job(store, bob.id)
    page, total = store.list_jobs(alice.id, limit=3, offset=0)
    assert total == 7 and [j.id for j in page] == ids[::-1][:3]
    page2, _ = store.list_jobs(alice.id, limit=3, offset=3)
    assert [j.id for j in page2] == ids[::-1][3:6]
    in_batch, n = store.list_jobs(alice.id, batch_id=batch)
    assert n == 3 and all(j.batch_id == batch for j in in_batch)
    assert store.get_job(ids[0], bob.id) is None
    b = store.get_batch(batch, alice.id)
    assert b.total == 3 and b.counts == {"queued": 3} and b.progress == 0.0
    assert store.get_batch(batch, bob.id) is None
    assert store.list_jobs(alice.id, state="running")[1] == 0


def test_upload_offsets_compare_and_set(store: JobStore) -> None:
    owner, _ = store.create_key("o")
    up = store.create_upload(owner.id, "cap.zip")
    assert store.advance_upload(up.id, 0, 100)
    assert not store.advance_upload(up.id, 0, 100)  # a stale client cannot append twice
    assert store.get_upload(up.id, owner.id).offset == 100
    assert store.finish_upload(up.id) and not store.finish_upload(up.id)


def test_transition_tables_and_graph_keys() -> None:
    # Every state has an entry, and no terminal job state leads anywhere but back to queued.
    assert set(JOB_TRANSITIONS) == {"queued", "running", "succeeded", "failed", "cancelled"}
    assert set(STAGE_TRANSITIONS) == {"pending", "queued", "running", "succeeded", "failed", "cancelled"}
    spec = graph_for("scan")[1]
    k1 = stage_key(spec, "c1", {}, {"ingest": "x"})
    assert k1 != stage_key(spec, "c2", {}, {"ingest": "x"})
    assert k1 != stage_key(spec, "c1", {}, {"ingest": "y"})
    assert k1 == stage_key(spec, "c1", {"unrelated": 1}, {"ingest": "x"})


def test_tables_checked_once_a_process_until_engines_are_disposed(tmp_path: Path) -> None:
    # A worker opens the store once a stage: the tables are created once, and a database that
    # lost them (dropped, restored from elsewhere) gets them back after dispose_engines(),
    # which a worker calls when it starts.
    from shared.service.jobstore import Base, dispose_engines

    url = f"sqlite:///{tmp_path / 'once.db'}"
    first = JobStore(url)
    Base.metadata.drop_all(first.engine)
    with pytest.raises(Exception, match="no such table"):
        JobStore(url).create_key("after the drop")  # not checked again in this process
    dispose_engines()
    owner, _ = JobStore(url).create_key("after dispose")
    assert owner.id
