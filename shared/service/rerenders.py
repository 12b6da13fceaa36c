"""Preview re-renders: the nightly (or a requested) new preview of a finished job, beside it.

A re-render is a record of its own (:class:`RerenderRow`), not a state of the job: the job stays
``succeeded`` with its ``finished_at``, its preview stage stays ``succeeded`` with its attempts
and times, while a worker renders the new preview from the job's stored tiles into a new
object. When it is stored, :meth:`RerenderStore.finish_rerender` points the preview stage at it
(and gives the job the parameters it was rendered with) in one transaction, so a client sees
the old preview or the new one, never a mix and never a gap. A failed re-render is reported on
its record (and the job's ``rerender`` field in the API) and changes nothing of the job.

One re-render a job at a time (a second one requested meanwhile is refused, not queued); the
reconciler queues again a re-render whose worker died or whose message was lost.
"""

from __future__ import annotations

import threading
import time
import uuid
from dataclasses import dataclass
from typing import Any

from sqlalchemy import JSON, Float, ForeignKey, Index, Integer, String, Text, func, select, update
from sqlalchemy.orm import Mapped, mapped_column

from shared.service.jobs import JobState, StageState
from shared.service.jobstore import Base, EventRow, JobRow, JobStore, StageRow

__all__ = ["RERENDER_ACTIVE", "Rerender", "RerenderStore", "epoch_now", "request_rerender", "rerender_params"]

class RerenderRow(Base):
    """A preview re-render of a finished job, run beside it: the job's state, its stages and their
    timings are not touched; when it succeeds, the job's preview stage points at the new output
    in one transaction (see :meth:`RerenderStore.finish_rerender`)."""

    __tablename__ = "rerenders"
    __table_args__ = (Index("ix_rerenders_job", "job_id"), Index("ix_rerenders_state", "state"))
    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"))
    reason: Mapped[str] = mapped_column(String(32))  # nightly-changed, nightly-all, manual
    state: Mapped[str] = mapped_column(String(16))  # queued, running, succeeded, failed
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # the job's parameters for the new preview
    base_key: Mapped[str | None] = mapped_column(String(64), nullable=True)  # the preview output it replaces
    output_key: Mapped[str | None] = mapped_column(String(64), nullable=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    lease_token: Mapped[str | None] = mapped_column(String(36), nullable=True)
    heartbeat_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    requested_at: Mapped[float] = mapped_column(Float)
    queued_at: Mapped[float] = mapped_column(Float)  # when last queued (or its message last re-sent)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)




@dataclass(frozen=True)
class Rerender:
    """A preview re-render record (:class:`RerenderRow`)."""

    id: str
    job_id: str
    reason: str
    state: str
    params: dict[str, Any]
    base_key: str | None
    output_key: str | None
    progress: float
    attempts: int
    lease_token: str | None
    heartbeat_at: float | None
    requested_at: float
    queued_at: float
    started_at: float | None
    finished_at: float | None
    error: str | None


def _rerender(r: RerenderRow) -> Rerender:
    return Rerender(
        id=r.id, job_id=r.job_id, reason=r.reason, state=r.state, params=dict(r.params or {}), base_key=r.base_key,
        output_key=r.output_key, progress=r.progress, attempts=r.attempts, lease_token=r.lease_token,
        heartbeat_at=r.heartbeat_at, requested_at=r.requested_at, queued_at=r.queued_at, started_at=r.started_at,
        finished_at=r.finished_at, error=r.error,
    )  # fmt: skip


#: Re-render states that hold the job's slot (one active re-render a job).
RERENDER_ACTIVE = ("queued", "running")


_READY: set[str] = set()
_READY_LOCK = threading.Lock()


class RerenderStore:
    """The re-render records of the job database of ``store`` (its engine and sessions)."""

    def __init__(self, store: JobStore) -> None:
        self.url = store.url
        self.session = store.session
        with _READY_LOCK:
            if self.url not in _READY:
                # The job store may have made its tables before this module was imported.
                Base.metadata.create_all(store.engine, tables=[RerenderRow.__table__])
                _READY.add(self.url)

    def create_rerender(self, job_id: str, params: dict[str, Any], reason: str) -> Rerender | None:
        """Record a re-render of a succeeded job's preview with the job parameters ``params``;
        None when the job has no succeeded preview or a re-render of it is already queued or
        running (one at a time: a second would race the first to publish)."""
        now = time.time()
        with self.session() as s, s.begin():
            job = s.get(JobRow, job_id, with_for_update=not self.url.startswith("sqlite"))
            if job is None or job.state != JobState.SUCCEEDED:
                return None
            preview = s.scalar(select(StageRow).where(StageRow.job_id == job_id, StageRow.name == "preview"))
            if preview is None or preview.state != StageState.SUCCEEDED:
                return None
            busy = s.scalar(
                select(func.count()).select_from(RerenderRow)
                .where(RerenderRow.job_id == job_id, RerenderRow.state.in_(RERENDER_ACTIVE))
            )  # fmt: skip
            if busy:
                return None
            row = RerenderRow(id=str(uuid.uuid4()), job_id=job_id, reason=reason[:32], state=StageState.QUEUED,
                              params=dict(params), base_key=preview.output_key, requested_at=now, queued_at=now)  # fmt: skip
            s.add(row)
            s.add(EventRow(job_id=job_id, stage="rerender", old=None, new=StageState.QUEUED, at=now, detail=reason))
            s.flush()
            return _rerender(row)

    def get_rerender(self, rerender_id: str) -> Rerender | None:
        with self.session() as s:
            r = s.get(RerenderRow, rerender_id)
            return _rerender(r) if r is not None else None

    def latest_rerender(self, job_id: str) -> Rerender | None:
        """The job's most recent re-render, or None."""
        with self.session() as s:
            r = s.scalar(select(RerenderRow).where(RerenderRow.job_id == job_id)
                         .order_by(RerenderRow.requested_at.desc()).limit(1))  # fmt: skip
            return _rerender(r) if r is not None else None

    def claim_rerender(self, rerender_id: str) -> Rerender | None:
        """Take the lease of a queued re-render (compare-and-set); None when it is not queued."""
        token = str(uuid.uuid4())
        now = time.time()
        with self.session() as s, s.begin():
            res = s.execute(
                update(RerenderRow)
                .where(RerenderRow.id == rerender_id, RerenderRow.state == StageState.QUEUED)
                .values(state=StageState.RUNNING, lease_token=token, heartbeat_at=now, started_at=now,
                        attempts=RerenderRow.attempts + 1, progress=0.0)
            )  # fmt: skip
            if not res.rowcount:
                return None
            r = s.get(RerenderRow, rerender_id)
            assert r is not None
            s.add(EventRow(job_id=r.job_id, stage="rerender", old=StageState.QUEUED, new=StageState.RUNNING, at=now))
            return _rerender(r)

    def heartbeat_rerender(self, rerender_id: str, token: str, progress: float | None = None) -> bool:
        values: dict[str, Any] = {"heartbeat_at": time.time()}
        if progress is not None:
            values["progress"] = float(min(max(progress, 0.0), 1.0))
        with self.session() as s, s.begin():
            res = s.execute(
                update(RerenderRow)
                .where(RerenderRow.id == rerender_id, RerenderRow.lease_token == token,
                       RerenderRow.state == StageState.RUNNING)
                .values(**values)
            )  # fmt: skip
            return res.rowcount > 0

    def finish_rerender(self, rerender_id: str, token: str, output_key: str, summary: dict[str, Any] | None) -> str | None:
        """Publish a finished re-render, in one transaction: the job's preview stage takes the new
        output (its key, input key and summary) and the job the new parameters, only while the
        stage still holds the output the re-render started from; the job's state, its times and
        the stage's state, attempts and times stay as they are. None when published, else why not
        (the re-render is then failed with that reason and nothing of the job changes)."""
        now = time.time()
        with self.session() as s, s.begin():
            r = s.get(RerenderRow, rerender_id, with_for_update=not self.url.startswith("sqlite"))
            if r is None or r.lease_token != token or r.state != StageState.RUNNING:
                return "lease lost"
            res = s.execute(
                update(StageRow)
                .where(StageRow.job_id == r.job_id, StageRow.name == "preview", StageRow.state == StageState.SUCCEEDED,
                       StageRow.output_key == r.base_key)
                .values(output_key=output_key, input_key=output_key, summary=summary)
            )  # fmt: skip
            why = None
            if res.rowcount:
                job = s.get(JobRow, r.job_id)
                assert job is not None
                job.params = dict(r.params)
            else:
                why = "the job's preview changed while it was re-rendered (a retry?); nothing published"
            r.state = StageState.FAILED if why else StageState.SUCCEEDED
            r.output_key, r.error, r.finished_at, r.lease_token, r.progress = output_key, why, now, None, 1.0 if not why else r.progress
            s.add(EventRow(job_id=r.job_id, stage="rerender", old=StageState.RUNNING, new=r.state, at=now, detail=why))
            return why

    def fail_rerender(self, rerender_id: str, token: str | None, error: str) -> bool:
        """Fail a re-render (held with ``token``, or queued when ``token`` is None); the job is untouched."""
        error = " ".join(str(error).split())[:2000]
        with self.session() as s, s.begin():
            cond = (RerenderRow.lease_token == token) if token else (RerenderRow.state == StageState.QUEUED)
            res = s.execute(
                update(RerenderRow).where(RerenderRow.id == rerender_id, RerenderRow.state.in_(RERENDER_ACTIVE), cond)
                .values(state=StageState.FAILED, error=error, finished_at=time.time(), lease_token=None)
            )  # fmt: skip
            if not res.rowcount:
                return False
            r = s.get(RerenderRow, rerender_id)
            assert r is not None
            s.add(EventRow(job_id=r.job_id, stage="rerender", old=None, new=StageState.FAILED, at=time.time(), detail=error[:500]))
            return True

    def stale_rerenders(self, older_than: float) -> list[Rerender]:
        """Re-renders running with a heartbeat before ``older_than`` (their worker died) or queued
        (or last re-sent) before it (their message may be lost): the reconciler's to look at."""
        with self.session() as s:
            rows = s.scalars(select(RerenderRow).where(
                ((RerenderRow.state == StageState.RUNNING) & (RerenderRow.heartbeat_at < older_than))
                | ((RerenderRow.state == StageState.QUEUED) & (RerenderRow.queued_at < older_than))
            )).all()  # fmt: skip
            return [_rerender(r) for r in rows]

    def requeue_rerender(self, r: Rerender) -> bool:
        """Queue a stale re-render again, or note that its message is sent again (compare-and-set
        on what the reconciler saw, so two reconcilers cannot both)."""
        now = time.time()
        with self.session() as s, s.begin():
            res = s.execute(
                update(RerenderRow)
                .where(RerenderRow.id == r.id, RerenderRow.state == r.state, RerenderRow.heartbeat_at == r.heartbeat_at,
                       RerenderRow.queued_at == r.queued_at)
                .values(state=StageState.QUEUED, lease_token=None, queued_at=now)
            )  # fmt: skip
            if res.rowcount and r.state == StageState.RUNNING:
                s.add(EventRow(job_id=r.job_id, stage="rerender", old=StageState.RUNNING, new=StageState.QUEUED, at=now,
                               detail="its worker stopped renewing the lease"))  # fmt: skip
            return res.rowcount > 0


def rerender_params(job: Any, mode: str, epoch: str) -> dict[str, Any] | None:
    """The job parameters a re-render of ``job``'s preview renders with, or None when there is
    nothing to re-render: ``mode`` ``"all"`` sets a new ``preview_epoch`` (``epoch``; a new
    preview key, so the stored video is not simply found again), ``"changed"`` keeps the
    parameters and re-renders only when the preview's key under them differs from the output
    it holds (the preview stage's version or its parameters changed)."""
    from shared.service.jobs import row_key

    if mode not in ("changed", "all"):
        raise ValueError(f"mode must be 'changed' or 'all', got {mode!r}")
    try:
        preview = job.stage("preview")
    except KeyError:
        return None
    if job.state != JobState.SUCCEEDED or preview.state != StageState.SUCCEEDED:
        return None
    params = dict(job.params)
    if mode == "all":
        params["preview_epoch"] = epoch if params.get("preview_epoch") != epoch else f"{epoch}+"
    upstream = {d: job.stage(d).output_key or "" for d in preview.depends_on}
    if row_key(job.kind, "preview", job.capture_key, params, upstream) == preview.output_key:
        return None
    return params


def epoch_now() -> str:
    """A new ``preview_epoch`` value: the UTC time to the second."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def request_rerender(store: JobStore, job: Any, mode: str, reason: str, settings: Any, epoch: str | None = None) -> Rerender | None:
    """Record and publish a re-render of ``job``'s preview (:func:`rerender_params` decides
    whether there is one to do); None when there is none, or one is already under way."""
    from shared.service.queue import publish_rerender

    params = rerender_params(job, mode, epoch or epoch_now())
    if params is None:
        return None
    rec = RerenderStore(store).create_rerender(job.id, params, reason)
    if rec is not None:
        publish_rerender(rec.id, settings)
    return rec
