"""Job-service overhead: per-stage queue latency and jobs per minute, beside the embedded run.

* Queue overhead per stage (target < 20 ms): a trivial stage (a ``probe`` job sleeping 0 s)
  submitted one at a time to an idle worker; from the database's timestamps, the time from
  enqueue (stage queued and published) to the task's claim of the stage, and from the
  stage function's end to the database recording success (artifact stored, state updated,
  successors queued). The peer is calling the same stage function in-process.
* Jobs per minute on small simulated captures (160x120 camera, scan stages only), with one
  and with two worker processes, beside ``shared.scan.pipeline.scan`` run in-process on the same
  captures one after another.

Real Redis (database 11, a private queue prefix), SQLite, real ``graylight worker`` processes.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from shared.service.artifacts import ArtifactStore, sha256_file
from shared.service.jobs import graph_for
from shared.service.jobstore import JobStore, NewJob
from shared.service.queue import publish_stages
from tests.support import jobsvc

N_PROBES = 30
N_CAPTURES = 10


def _wait(store: JobStore, ids: list[str], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    pending = set(ids)
    while pending and time.monotonic() < deadline:
        for j in list(pending):
            if store.get_job(j).state in ("succeeded", "failed", "cancelled"):
                pending.discard(j)
        time.sleep(0.02)
    if pending:
        raise RuntimeError(f"{len(pending)} jobs did not finish in {timeout} s")


def _ms(xs: list[float]) -> str:
    xs = sorted(xs)
    return f"median {1000 * statistics.median(xs):6.1f} ms, p90 {1000 * xs[int(0.9 * (len(xs) - 1))]:6.1f} ms"


def queue_overhead(senv: jobsvc.ServiceEnv) -> None:
    from workers.stages import StageContext, run_probe

    settings = senv.settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("bench")
    jobsvc.start_worker(senv, "cpu", concurrency=1)
    arts = ArtifactStore(settings.storage_url)
    to_start, to_record = [], []
    for i in range(N_PROBES + 3):
        job, ready = store.create_job(owner.id, NewJob(kind="probe", capture_ref="none:", capture_key=f"{i:064x}",
                                                       graph=graph_for("probe"), params={"seconds": 0}))  # fmt: skip
        publish_stages(ready, settings)
        _wait(store, [job.id], 60)
        if i < 3:
            continue  # warm-up: first tasks import and connect
        st = store.get_job(job.id).stage("probe")
        import json

        with arts.open(st.output_key, "probe.json") as f:
            finished = json.loads(f.read())["finished"]
        to_start.append(st.started_at - st.queued_at)
        to_record.append(st.finished_at - finished)
    # The peer: the same stage function called in-process (no queue, no database).
    peer = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(N_PROBES):
            out = Path(tmp) / str(i)
            out.mkdir()
            t0 = time.perf_counter()
            run_probe(StageContext("j", "probe", "probe", {"seconds": 0}, None, {}, out))
            peer.append(time.perf_counter() - t0)
    total = [a + b for a, b in zip(to_start, to_record, strict=True)]
    print(f"queue overhead per stage ({N_PROBES} trivial stages, one idle worker; target < 20 ms):")
    print(f"  enqueue -> task claims stage      {_ms(to_start)}")
    print(f"  stage end -> state in database    {_ms(to_record)}")
    print(f"  total added per stage             {_ms(total)}")
    print(f"  peer: embedded call of the stage  {_ms(peer)}")
    print(f"  ratio (total / embedded)          {statistics.median(total) / max(statistics.median(peer), 1e-9):.0f}x")


def jobs_per_minute(root: Path, captures: list[Path]) -> None:
    from shared.scan.pipeline import scan

    # Warm up first (imports, compiled kernels), as the workers below are warmed on one job.
    scan(captures[0].parent / "folder", root / "embedded-warm")
    t0 = time.perf_counter()
    for i, cap in enumerate(captures):
        scan(cap.parent / "folder", root / f"embedded{i}")
    embedded = len(captures) / (time.perf_counter() - t0) * 60
    rates = {}
    for workers in (1, 2):
        with jobsvc.service_env(root / f"w{workers}") as senv:
            settings = senv.settings
            store = JobStore(settings.database_url)
            owner, _ = store.create_key("bench")
            arts = ArtifactStore(settings.storage_url)
            for _ in range(workers):
                jobsvc.start_worker(senv, "cpu", concurrency=1)
            # Warm the workers (imports, compiled kernels) on one job first.
            ids = []
            t0 = time.perf_counter()
            for n, cap in enumerate([captures[0], *captures]):
                key = sha256_file(cap)
                arts.put_files(key, {"capture.zip": cap})
                job, ready = store.create_job(owner.id, NewJob(
                    kind="scan", capture_ref=f"object:{key}", capture_key=key, graph=graph_for("scan", {"render": False}),
                    params={"render": False}))  # fmt: skip
                publish_stages(ready, settings)
                if n == 0:
                    _wait(store, [job.id], 180)
                    t0 = time.perf_counter()
                else:
                    ids.append(job.id)
            _wait(store, ids, 600)
            rates[workers] = len(ids) / (time.perf_counter() - t0) * 60
    print(f"jobs per minute ({len(captures)} captures 160x120, ingest+decode+triangulate):")
    print(f"  embedded scan, one process        {embedded:7.1f} jobs/min")
    for w, r in rates.items():
        print(f"  job service, {w} worker(s)          {r:7.1f} jobs/min   ratio to embedded {r / embedded:.2f}")
    print(f"  scaling 1 -> 2 workers            {rates[2] / rates[1]:.2f}x (this machine has 2 cores, shared)")


def main() -> None:
    from shared.sim.simulate import simulate_named

    with tempfile.TemporaryDirectory(prefix="graylight-bench-queue-") as tmp:
        root = Path(tmp)
        with jobsvc.service_env(root / "probe") as senv:
            queue_overhead(senv)
        base = simulate_named("plane", root / "cap" / "folder", size=(160, 120), projector=(64, 48), seed=1).root
        captures = []
        for i in range(N_CAPTURES):
            d = root / f"cap{i}"
            d.mkdir()
            # A distinct note per capture: each job does its own work (no reuse by key).
            captures.append(jobsvc.capture_zip(base, d / "c.zip", note=f"bench {i}"))
            (d / "folder").symlink_to(base)
        jobs_per_minute(root, captures)


if __name__ == "__main__":
    main()
