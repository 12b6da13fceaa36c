"""The reconciler: makes the broker agree with the database again, every few seconds.

Run by beat every ``GRAYLIGHT_RECONCILE_SECONDS`` (on the ``control`` queue). It

1. re-queues running stages whose lease has expired (no heartbeat for
   ``GRAYLIGHT_LEASE_SECONDS``: the worker died, was killed, or lost its database), and
   fails a stage that has lost ``GRAYLIGHT_MAX_ATTEMPTS`` workers (it keeps killing them);
2. re-publishes queued stages whose message was lost (a Redis restart, a publish while
   the broker was down): those queued for longer than a lease while their queue is empty,
   and any queued for ten leases regardless (a duplicate message is harmless: the claim is
   a compare-and-set, so the second copy finds the stage running or done and does nothing);
3. re-derives the state of jobs that have no queued or running stage (a crash between
   two transactions);
4. deletes upload sessions opened more than ``GRAYLIGHT_UPLOAD_TTL_HOURS`` ago, with their
   chunks: abandoned uploads would otherwise fill the storage (a finished one has already
   become a capture object and lost its chunks).

5. queues again the preview re-renders (:mod:`shared.service.rerenders`) whose worker died
   (no heartbeat for a lease) or whose message was lost (queued for a lease), and publishes them.

The nightly re-render itself is :func:`workers.rerender.enqueue_rerenders`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass

from shared.service.artifacts import ArtifactError, ArtifactStore
from shared.service.config import Settings
from shared.service.jobs import StageState
from shared.service.jobstore import JobStore, Stage
from shared.service.queue import publish_rerender, publish_stages
from shared.service.rerenders import RerenderStore

log = logging.getLogger(__name__)


@dataclass
class ReconcileReport:
    expired: int = 0
    republished: int = 0
    failed: int = 0
    settled: int = 0
    uploads_deleted: int = 0
    rerenders_requeued: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def _queue_lengths(settings: Settings, queues: set[str]) -> dict[str, int] | None:
    """Messages waiting in each broker queue, or None when the broker cannot be asked."""
    if not settings.broker_url.startswith(("redis://", "rediss://")):
        return None
    try:
        import redis

        client = redis.Redis.from_url(settings.broker_url, socket_timeout=2, socket_connect_timeout=2)
        try:
            return {q: int(client.llen(settings.queue(q))) for q in queues}
        finally:
            client.close()
    except Exception as exc:
        log.warning("reconciler: cannot read queue lengths: %s", exc)
        return None


def reconcile_once(settings: Settings, store: JobStore | None = None, now: float | None = None,
                   arts: ArtifactStore | None = None) -> ReconcileReport:  # fmt: skip
    """One pass of the reconciler (see the module docstring)."""
    store = store or JobStore(settings.database_url)
    now = time.time() if now is None else now
    lease = settings.lease_seconds
    report = ReconcileReport()
    to_publish: list[Stage] = []

    for st in store.expired_leases(now - lease):
        if st.attempts >= settings.max_attempts:
            if store.fail_queued_stage(
                st.id, f"worker lost {st.attempts} times while running stage {st.name} (killed or out of memory?)"
            ):
                report.failed += 1
            continue
        if store.requeue_expired(st):
            log.warning("reconciler: stage %s (%s) of job %s lost its worker %s; re-queued",
                        st.id, st.name, st.job_id, st.lease_owner)  # fmt: skip
            report.expired += 1
            to_publish.append(st)

    stale = store.stale_queued(now - lease)
    if stale:
        lengths = _queue_lengths(settings, {s.queue for s in stale})
        requeued = {s.id for s in to_publish}
        for st in stale:
            if st.id in requeued:
                continue
            queue_empty = lengths is not None and lengths.get(st.queue, 1) == 0
            very_old = st.queued_at is not None and st.queued_at < now - 10 * lease
            if queue_empty or very_old:
                store.touch_queued(st.id)
                to_publish.append(st)

    for job_id in store.unsettled_jobs():
        job = store.get_job(job_id)
        if job is None or any(s.state in (StageState.QUEUED, StageState.RUNNING) for s in job.stages):
            continue
        newly = store.settle(job_id)
        report.settled += 1
        to_publish.extend(newly)

    if to_publish:
        report.republished = publish_stages(to_publish, settings)
    report.uploads_deleted = _delete_expired_uploads(settings, store, now, arts)
    report.rerenders_requeued = _repair_rerenders(settings, store, now)
    return report


def _repair_rerenders(settings: Settings, store: JobStore, now: float) -> int:
    """Step 5: a running re-render whose lease expired is queued again; a queued one's message
    is sent again when the render queue is empty (it was lost) or after ten leases (as for
    stages: a nightly run of many re-renders waits in the queue without being re-sent)."""
    lease = settings.lease_seconds
    rr = RerenderStore(store)
    stale = rr.stale_rerenders(now - lease)
    if not stale:
        return 0
    lengths = _queue_lengths(settings, {"render"}) if any(r.state == StageState.QUEUED for r in stale) else None
    count = 0
    for rec in stale:
        if rec.state == StageState.QUEUED:
            queue_empty = lengths is not None and lengths.get("render", 1) == 0
            if not (queue_empty or rec.queued_at < now - 10 * lease):
                continue
        if rr.requeue_rerender(rec):
            publish_rerender(rec.id, settings)
            count += 1
    return count


def _delete_expired_uploads(settings: Settings, store: JobStore, now: float, arts: ArtifactStore | None) -> int:
    """Step 4: chunks first, then the row, so that a pass cut short is finished by the next."""
    expired = store.uploads_created_before(now - settings.upload_ttl_hours * 3600.0)
    if not expired:
        return 0
    arts = arts or ArtifactStore(settings.storage_url, settings.s3_endpoint)
    count = 0
    for upload_id in expired:
        try:
            arts.drop_upload(upload_id)
        except (OSError, ArtifactError) as exc:
            log.warning("reconciler: cannot delete the chunks of upload %s: %s", upload_id, exc)
            continue
        count += store.delete_upload(upload_id)
    if count:
        log.info("reconciler: deleted %d upload sessions older than %g h", count, settings.upload_ttl_hours)
    return count
