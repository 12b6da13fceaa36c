"""Preview re-renders beside a finished job (:mod:`shared.service.rerenders`), on a render worker.

:func:`run_rerender` claims a re-render record, renders the job's preview from its stored tiles
with the record's parameters into a new object (or finds it stored), and publishes it with
:meth:`~shared.service.rerenders.RerenderStore.finish_rerender`: the job's preview stage points
at the new output and the job takes the new parameters in one transaction. The job's state,
``finished_at`` and its stages' states, attempts and times are never touched; a failure is
recorded on the re-render alone. :func:`enqueue_rerenders` is the nightly beat entry's work.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import shutil
import tempfile
from pathlib import Path

from shared.core.errors import InputError
from shared.service.artifacts import ArtifactStore
from shared.service.config import Settings
from shared.service.faults import storage_fault
from shared.service.jobs import JobState, row_key, stage_spec
from shared.service.jobstore import Job, JobStore
from shared.service.rerenders import Rerender, RerenderStore, request_rerender
from workers.runner import (
    SUMMARY_FILE,
    TRANSIENT,
    Heartbeat,
    LeaseLost,
    _run_adapter,
    public_summary,
    unexpected_failure,
)

log = logging.getLogger(__name__)


class RerenderBeat(Heartbeat):
    """The heartbeat of a re-render: renews its lease on the re-render record."""

    def __init__(self, rerenders: RerenderStore, rec: Rerender, token: str, interval: float) -> None:
        super().__init__(None, 0, token, interval)  # type: ignore[arg-type]
        self.rerenders = rerenders
        self.rerender_id = rec.id

    def renew(self) -> bool:
        return self.rerenders.heartbeat_rerender(self.rerender_id, self.token, self.progress)


def run_rerender(rerender_id: str, settings: Settings) -> str:
    """Run one re-render (see the module docstring); its outcome: ``skipped`` (not queued),
    ``succeeded``, ``failed`` or ``lost``. Transient faults are re-raised (Celery retries the
    message; the record stays running until its lease expires and the reconciler queues it)."""
    store = JobStore(settings.database_url)
    rr = RerenderStore(store)
    rec = rr.claim_rerender(rerender_id)
    if rec is None:
        return "skipped"
    token = rec.lease_token
    assert token is not None
    if rec.attempts > settings.max_attempts:
        rr.fail_rerender(rec.id, token, f"gave up after {rec.attempts - 1} attempts")
        return "failed"
    beat = RerenderBeat(rr, rec, token, settings.heartbeat_seconds)
    beat.start()
    try:
        job = store.get_job(rec.job_id)
        if job is None or job.state != JobState.SUCCEEDED:
            rr.fail_rerender(rec.id, token, f"job {rec.job_id} is no longer succeeded; nothing re-rendered")
            return "failed"
        preview = job.stage("preview")
        upstream = {d: job.stage(d).output_key or "" for d in preview.depends_on}
        key = row_key(job.kind, "preview", job.capture_key, rec.params, upstream)
        arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
        if arts.exists(key):
            summary = _stored_summary(arts, key)
        else:
            summary = _render(dataclasses.replace(job, params=rec.params), upstream, arts, settings, beat, key)
            if summary is None:
                return "lost"
        why = rr.finish_rerender(rec.id, token, key, summary)
        if why is not None:
            log.warning("re-render %s of job %s: %s", rec.id, job.id, why)
            return "failed"
        log.info("re-render %s of job %s: new preview %s published", rec.id, job.id, key[:12])
        return "succeeded"
    except LeaseLost:
        return "lost"
    except TRANSIENT:
        raise  # the lease expires and the reconciler queues the re-render again
    except Exception as exc:
        if isinstance(exc, InputError):
            msg = str(exc)
        else:  # as a stage's failure reads: no bare exception, no worker path (those go to the log)
            log.exception("re-render %s failed", rec.id)
            msg = storage_fault(exc, "preview") or unexpected_failure(exc, "preview", "the job's tiles")
        rr.fail_rerender(rec.id, token, msg)
        return "failed"
    finally:
        beat.stop()


def _stored_summary(arts: ArtifactStore, key: str) -> dict:
    m = arts.manifest(key)
    if m is None or SUMMARY_FILE not in m.files:
        return {}
    with arts.open(key, SUMMARY_FILE) as f:
        return json.loads(f.read().decode())


def _render(job: Job, upstream: dict[str, str], arts: ArtifactStore, settings: Settings, beat: Heartbeat,
            key: str) -> dict | None:  # fmt: skip
    """Render the preview of ``job`` (with the re-render's parameters) and store it as ``key``;
    its summary, or None when the lease was lost meanwhile (nothing stored)."""
    work = settings.cache_dir / "work"
    work.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="rerender-", dir=work))
    try:
        local = {name: arts.fetch(k, settings.cache_dir) for name, k in upstream.items()}
        out = tmp / "out"
        out.mkdir()
        summary = public_summary(_run_adapter(job, "preview", ("tiles",), local, arts, settings, beat, out), out, work)
        summary["published"] = [n for n in stage_spec(job.kind, "preview").publish if (out / n).is_file()]
        if beat.lost.is_set():
            return None
        (out / SUMMARY_FILE).write_text(json.dumps(summary, default=str))
        arts.put_dir(key, out, move=True)  # atomic: the object appears whole or not at all
        return summary
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def enqueue_rerenders(settings: Settings, mode: str = "changed", store: JobStore | None = None) -> int:
    """The nightly re-render: one re-render record (on the render queue) for each succeeded job
    with a preview that ``mode`` selects (:func:`shared.service.rerenders.rerender_params`);
    returns how many were queued. The jobs themselves are not touched."""
    if mode not in ("changed", "all"):
        raise ValueError(f"mode must be 'changed' or 'all', got {mode!r}")
    store = store or JobStore(settings.database_url)
    epoch = dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M")
    count = 0
    offset = 0
    while True:
        jobs, _total = store.list_jobs(state=JobState.SUCCEEDED, limit=200, offset=offset)
        if not jobs:
            break
        offset += len(jobs)  # the jobs stay succeeded, so the pages do not shift under the walk
        for job in jobs:
            if request_rerender(store, job, mode, f"nightly-{mode}", settings, epoch) is not None:
                count += 1
    log.info("nightly re-render (%s, from beat): %d previews queued beside their jobs", mode, count)
    return count
