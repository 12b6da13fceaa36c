"""Running a job's stages in the test process, without a broker or a worker: each queued stage
of the job goes through the real runner (:func:`workers.runner.run_stage`) against the test's
own database and artifact store, until nothing is queued."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from shared.service.artifacts import ArtifactStore, sha256_file
from shared.service.config import Settings
from shared.service.jobs import graph_for
from shared.service.jobstore import Job, JobStore, NewJob
from tests.support.jobsvc import capture_zip
from workers.runner import run_stage


def drive(settings: Settings, job_id: str, stop_after: str | None = None, rounds: int = 20) -> None:
    """Run the job's queued stages in-process (no broker), optionally stopping after one."""
    store = JobStore(settings.database_url)
    for _ in range(rounds):
        job = store.get_job(job_id)
        queued = [s for s in job.stages if s.state == "queued"]
        if not queued:
            return
        for st in queued:
            run_stage(st.id, settings, publish=False)
            if st.name == stop_after:
                return


def submit_scan_job(settings: Settings, capture: Path, tmp: Path,
                    params: dict[str, Any]) -> tuple[JobStore, ArtifactStore, int, Job, list]:  # fmt: skip
    """Store ``capture`` as an archive under a new key and record a scan job of it with
    ``params``: the job store, the artifact store, the key's owner id, the job and its queued
    stages (not published)."""
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("t")
    arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
    archive = capture_zip(capture, tmp / "c.zip")
    key = sha256_file(archive)
    arts.put_files(key, {"capture.zip": archive})
    job, queued = store.create_job(owner.id, NewJob(kind="scan", capture_ref=f"object:{key}", capture_key=key,
                                                   graph=graph_for("scan", params), name="c.zip", params=params))  # fmt: skip
    return store, arts, owner.id, job, queued


def run_scan_job(settings: Settings, capture: Path, tmp: Path, params: dict[str, Any]) -> tuple[ArtifactStore, Job]:
    """Store ``capture`` as an archive, make a scan job of it with ``params`` and run it to its
    end in-process; returns the artifact store and the finished job (asserted succeeded)."""
    store, arts, _owner, job, _ = submit_scan_job(settings, capture, tmp, params)
    drive(settings, job.id)
    job = store.get_job(job.id)
    assert job.state == "succeeded", job
    return arts, job
