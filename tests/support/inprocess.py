"""Running a job's stages in the test process, without a broker or a worker: each queued stage
of the job goes through the real runner (:func:`workers.runner.run_stage`) against the test's
own database and artifact store, until nothing is queued."""

from __future__ import annotations

from shared.service.config import Settings
from shared.service.jobstore import JobStore
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
