"""The durable job store: SQLAlchemy 2.0 models and the repository functions over them.

In: a database URL (SQLite file by default, PostgreSQL via ``GRAYLIGHT_DATABASE_URL``).
Out: :class:`JobStore`, whose methods are each one short transaction. The database is the
source of truth for job state; every state change is a conditional ``UPDATE`` (compare and
set on the old state and the lease token), so two workers, a worker and the reconciler, or
a duplicate message can never both win, on SQLite and PostgreSQL alike. Every change is
also appended to ``events`` (an audit trail: a test can count how often a stage succeeded).

Times are UNIX seconds (float, UTC) so that they compare the same on every backend. The
tables, the records and the engines are in :mod:`shared.service._jobrows`; every name is
importable from here.
"""

from __future__ import annotations

import logging
import secrets
import time
import uuid
from collections.abc import Iterable, Sequence
from typing import Any

from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError, OperationalError, ProgrammingError
from sqlalchemy.orm import Session, sessionmaker

from shared.service._jobrows import (
    _TABLES_READY,
    REJECTED,
    ApiKey,
    ApiKeyRow,
    Base,
    Batch,
    BatchRejectRow,
    BatchRow,
    CaptureSizeRow,
    Claim,
    EventRow,
    Job,
    JobRow,
    NewJob,
    Reject,
    Stage,
    StageRow,
    Upload,
    UploadRow,
    _engine,
    _job,
    _stage,
    dispose_engines,
    hash_key,
)
from shared.service.config import get_settings
from shared.service.jobs import (
    JOB_ACTIVE,
    STAGE_WAITING,
    FanOut,
    JobState,
    StageState,
    StageView,
    base_name,
    can_move_job,
    can_move_stage,
    check_transition,
    job_state_from_stages,
    ready_to_queue,
    stage_sources,
)

__all__ = [
    "FANOUT_SLOTS",
    "REJECTED",
    "ApiKey",
    "ApiKeyRow",
    "Base",
    "Batch",
    "BatchRejectRow",
    "BatchRow",
    "CaptureSizeRow",
    "Claim",
    "EventRow",
    "Job",
    "JobRow",
    "JobStore",
    "NewJob",
    "Reject",
    "Stage",
    "StageRow",
    "Upload",
    "UploadRow",
    "dispose_engines",
    "hash_key",
    "open_store",
]

log = logging.getLogger(__name__)

#: Stage positions are spaced this far apart so a map stage's instances sort right after
#: the stage they fan out from.
FANOUT_SLOTS = 10_000


class JobStore:
    """Repository over the job database. Thread-safe; each method is one transaction."""

    def __init__(self, url: str, create: bool = True) -> None:
        self.url = url
        self.engine = _engine(url)
        self._session = sessionmaker(self.engine, expire_on_commit=False)
        if create:
            self.create_tables()

    def create_tables(self) -> None:
        """Create missing tables (once a process for each database). Several processes may start
        at once: a loser of the race retries."""
        if self.url in _TABLES_READY:
            return
        for attempt in range(5):
            try:
                Base.metadata.create_all(self.engine)
                _TABLES_READY.add(self.url)
                return
            except (IntegrityError, ProgrammingError, OperationalError):
                if attempt == 4:
                    raise
                time.sleep(0.2 * (attempt + 1))

    def session(self) -> Session:
        return self._session()

    def ping(self) -> bool:
        """Whether the database answers a trivial query."""
        with self.engine.connect() as conn:
            conn.exec_driver_sql("SELECT 1")
        return True

    # ---- events ----------------------------------------------------------------------
    @staticmethod
    def _event(s: Session, job_id: str, stage: str | None, old: str | None, new: str, detail: str | None = None) -> None:
        # Every state change is recorded here, so this is where the declared transitions hold.
        check_transition(stage, old, new)
        s.add(EventRow(job_id=job_id, stage=stage, old=old, new=new, at=time.time(), detail=detail))

    def events(self, job_id: str) -> list[tuple[str | None, str | None, str, str | None]]:
        """``(stage, old, new, detail)`` of every recorded change of a job, oldest first."""
        with self.session() as s:
            rows = s.scalars(select(EventRow).where(EventRow.job_id == job_id).order_by(EventRow.id)).all()
            return [(r.stage, r.old, r.new, r.detail) for r in rows]

    # ---- API keys --------------------------------------------------------------------
    def create_key(self, name: str) -> tuple[ApiKey, str]:
        """A new API key named ``name``: its record and the key itself (shown once, stored hashed)."""
        secret = "gl_" + secrets.token_urlsafe(32)
        with self.session() as s, s.begin():
            row = ApiKeyRow(name=name, prefix=secret[:10], key_hash=hash_key(secret), created_at=time.time())
            s.add(row)
            s.flush()
            rec = ApiKey(row.id, row.name, row.prefix, row.created_at)
        return rec, secret

    def authenticate(self, secret: str) -> ApiKey | None:
        """The key record whose hash matches ``secret``, or None."""
        with self.session() as s:
            row = s.scalar(select(ApiKeyRow).where(ApiKeyRow.key_hash == hash_key(secret), ApiKeyRow.revoked.is_(False)))
            return ApiKey(row.id, row.name, row.prefix, row.created_at) if row else None

    def list_keys(self) -> list[ApiKey]:
        with self.session() as s:
            rows = s.scalars(select(ApiKeyRow).where(ApiKeyRow.revoked.is_(False)).order_by(ApiKeyRow.id)).all()
            return [ApiKey(r.id, r.name, r.prefix, r.created_at) for r in rows]

    def key_active(self, key_id: int) -> bool:
        """Whether key ``key_id`` exists and is not revoked (one row, for a request's check)."""
        with self.session() as s:
            return s.scalar(select(ApiKeyRow.id).where(ApiKeyRow.id == key_id, ApiKeyRow.revoked.is_(False))) is not None

    def revoke_key(self, prefix: str) -> bool:
        with self.session() as s, s.begin():
            res = s.execute(update(ApiKeyRow).where(ApiKeyRow.prefix == prefix).values(revoked=True))
            return res.rowcount > 0

    # ---- batches ---------------------------------------------------------------------
    def batch_for(self, owner_id: int, name: str) -> str:
        """The id of ``owner_id``'s batch called ``name``, created when new."""
        with self.session() as s, s.begin():
            bid = s.scalar(select(BatchRow.id).where(BatchRow.owner_id == owner_id, BatchRow.name == name))
            if bid:
                return bid
            bid = str(uuid.uuid4())
            s.add(BatchRow(id=bid, owner_id=owner_id, name=name, created_at=time.time()))
        return bid

    def find_batch(self, owner_id: int, name_or_id: str) -> str | None:
        """The id of ``owner_id``'s batch with this id or name, or None."""
        with self.session() as s:
            return s.scalar(
                select(BatchRow.id).where(
                    BatchRow.owner_id == owner_id, (BatchRow.name == name_or_id) | (BatchRow.id == name_or_id)
                )
            )

    def get_batch(self, batch_id: str, owner_id: int | None = None) -> Batch | None:
        """A batch with its job counts by state and its refused files (count ``rejected``)."""
        with self.session() as s:
            row = s.get(BatchRow, batch_id)
            if row is None or (owner_id is not None and row.owner_id != owner_id):
                return None
            counts = dict(
                s.execute(select(JobRow.state, func.count()).where(JobRow.batch_id == batch_id).group_by(JobRow.state)).all()
            )
            rejects = tuple(
                Reject(r.capture, r.error, r.at)
                for r in s.scalars(select(BatchRejectRow).where(BatchRejectRow.batch_id == batch_id).order_by(BatchRejectRow.id))
            )
            counts = {k: int(v) for k, v in counts.items()}
            if rejects:
                counts[REJECTED] = len(rejects)
            return Batch(row.id, row.owner_id, row.name, row.created_at, counts, rejects)

    def add_rejects(self, batch_id: str, rejects: Iterable[tuple[str, str]]) -> None:
        """Keep the files of a batch refused at intake, ``(name as sent, one-line reason)``."""
        now = time.time()
        with self.session() as s, s.begin():
            for capture, error in rejects:
                s.add(BatchRejectRow(batch_id=batch_id, capture=capture[:1000], error=" ".join(error.split())[:2000], at=now))

    def batch_job_ids(self, batch_id: str, limit: int = 100, offset: int = 0) -> tuple[list[str], int]:
        """A page of the ids of a batch's jobs, oldest first, and how many it has."""
        with self.session() as s:
            total = int(s.scalar(select(func.count()).select_from(JobRow).where(JobRow.batch_id == batch_id)) or 0)
            ids = s.scalars(
                select(JobRow.id).where(JobRow.batch_id == batch_id).order_by(JobRow.seq).limit(limit).offset(offset)
            ).all()
            return list(ids), total

    def list_batches(self, owner_id: int) -> list[Batch]:
        with self.session() as s:
            ids = s.scalars(select(BatchRow.id).where(BatchRow.owner_id == owner_id).order_by(BatchRow.created_at)).all()
        return [b for b in (self.get_batch(i) for i in ids) if b is not None]

    # ---- jobs ------------------------------------------------------------------------
    def create_job(self, owner_id: int, new: NewJob) -> tuple[Job, list[Stage]]:
        """Insert a job and its stages; stages with no upstream start ``queued``. Returns the job
        and the stages to publish."""
        with self.session() as s, s.begin():
            return self.insert_job(s, owner_id, new)

    def insert_job(self, s: Session, owner_id: int, new: NewJob) -> tuple[Job, list[Stage]]:
        """:meth:`create_job` inside the caller's transaction ``s`` (admission checks the key's
        limits and inserts in one, :mod:`shared.service.admission`)."""
        now = time.time()
        jid = str(uuid.uuid4())
        seq = (s.scalar(select(func.max(JobRow.seq))) or 0) + 1
        job = JobRow(
            id=jid, owner_id=owner_id, batch_id=new.batch_id, kind=new.kind, name=new.name[:300],
            state=JobState.QUEUED, capture_ref=new.capture_ref, capture_key=new.capture_key,
            params=dict(new.params), created_at=now, seq=seq,
        )  # fmt: skip
        s.add(job)
        s.flush()
        rows = []
        for i, spec in enumerate(new.graph):
            if spec.is_map:
                continue  # its rows appear when the stage it fans out from finishes
            st = StageState.QUEUED if not spec.depends_on else StageState.PENDING
            row = StageRow(
                job_id=jid, name=spec.name, position=i * FANOUT_SLOTS, queue=spec.queue,
                depends_on=list(spec.depends_on),
                state=st, queued_at=now if st == StageState.QUEUED else None,
            )  # fmt: skip
            s.add(row)
            rows.append(row)
        s.flush()
        self._event(s, jid, None, None, JobState.QUEUED, new.kind)
        out = _job(job, rows)
        return out, [st for st in out.stages if st.state == StageState.QUEUED]

    def get_job(self, job_id: str, owner_id: int | None = None) -> Job | None:
        """A job with its stages; None when absent or owned by another key."""
        with self.session() as s:
            row = s.get(JobRow, job_id)
            if row is None or (owner_id is not None and row.owner_id != owner_id):
                return None
            stages = s.scalars(select(StageRow).where(StageRow.job_id == job_id)).all()
            return _job(row, stages)

    def list_jobs(
        self,
        owner_id: int | None = None,
        state: str | None = None,
        batch_id: str | None = None,
        limit: int = 50,
        offset: int = 0,
        with_stages: bool = True,
    ) -> tuple[list[Job], int]:
        """A page of jobs, newest first, and the total count matching the filters."""
        with self.session() as s:
            q = select(JobRow)
            cq = select(func.count()).select_from(JobRow)
            conds = []
            if owner_id is not None:
                conds.append(JobRow.owner_id == owner_id)
            if state is not None:
                conds.append(JobRow.state == state)
            if batch_id is not None:
                conds.append(JobRow.batch_id == batch_id)
            for c in conds:
                q = q.where(c)
                cq = cq.where(c)
            total = int(s.scalar(cq) or 0)
            rows = s.scalars(q.order_by(JobRow.seq.desc()).limit(limit).offset(offset)).all()
            by_job: dict[str, list[StageRow]] = {r.id: [] for r in rows}
            if with_stages and rows:
                for st in s.scalars(select(StageRow).where(StageRow.job_id.in_(list(by_job)))).all():
                    by_job[st.job_id].append(st)
            return [_job(r, by_job[r.id]) for r in rows], total

    def _refresh_job_state(self, s: Session, job_id: str) -> list[int]:
        """Queue pending stages whose inputs are done (fan-in counted here, in the database) and
        set the job's state from its stages. Returns ids of stages newly queued (to publish)."""
        return self._refresh(s, job_id)[0]

    def _refresh(self, s: Session, job_id: str) -> tuple[list[int], JobRow | None, list[StageRow]]:
        """:meth:`_refresh_job_state`, also handing back the job row and its stage rows."""
        job = s.get(JobRow, job_id, with_for_update=not self.url.startswith("sqlite"))
        if job is None:
            return [], None, []
        stages = s.scalars(select(StageRow).where(StageRow.job_id == job_id)).all()
        now = time.time()
        newly: list[int] = []
        if job.state != JobState.CANCELLED:
            names = ready_to_queue(StageView(r.name, r.state, tuple(r.depends_on or ())) for r in stages)
            for r in stages:
                if r.name in names:
                    res = s.execute(
                        update(StageRow)
                        .where(StageRow.id == r.id, StageRow.state == StageState.PENDING)
                        .values(state=StageState.QUEUED, queued_at=now, progress=0.0, error=None)
                    )
                    if res.rowcount:
                        r.state = StageState.QUEUED
                        newly.append(r.id)
                        self._event(s, job_id, r.name, StageState.PENDING, StageState.QUEUED)
            if any(r.state == StageState.FAILED for r in stages):
                # A failed stage ends the job: what waits downstream will never run.
                for r in stages:
                    if r.state in STAGE_WAITING:
                        old = r.state  # the ORM update below also changes r.state in the session
                        s.execute(update(StageRow).where(StageRow.id == r.id).values(state=StageState.CANCELLED))
                        self._event(s, job_id, r.name, old, StageState.CANCELLED, "an earlier stage failed")
                        r.state = StageState.CANCELLED
                        if r.id in newly:
                            newly.remove(r.id)
        new_state = job_state_from_stages([r.state for r in stages], cancelled=job.state == JobState.CANCELLED)
        if new_state != job.state:
            self._event(s, job_id, None, job.state, new_state)
            job.state = new_state
            if new_state == JobState.RUNNING and job.started_at is None:
                job.started_at = now
            if new_state in (JobState.SUCCEEDED, JobState.FAILED):
                job.finished_at = now
                failed = [r for r in stages if r.state == StageState.FAILED]
                job.error = f"{failed[0].name}: {failed[0].error}" if failed else None
        return newly, job, list(stages)

    def _stages_by_id(self, s: Session, ids: Sequence[int]) -> list[Stage]:
        if not ids:
            return []
        return [_stage(r) for r in s.scalars(select(StageRow).where(StageRow.id.in_(list(ids)))).all()]

    # ---- the worker's side -----------------------------------------------------------
    def claim_stage(self, stage_id: int, worker: str) -> Claim | None:
        """Take the lease of a queued stage. None when it is not queued (a duplicate or stale
        message, a finished or cancelled job): the caller then does nothing."""
        token = str(uuid.uuid4())
        now = time.time()
        with self.session() as s, s.begin():
            res = s.execute(
                update(StageRow)
                .where(StageRow.id == stage_id, StageRow.state == StageState.QUEUED)
                .values(
                    state=StageState.RUNNING, lease_token=token, lease_owner=worker[:200], heartbeat_at=now,
                    started_at=now, attempts=StageRow.attempts + 1, progress=0.0, error=None,
                )
            )  # fmt: skip
            if not res.rowcount:
                return None
            row = s.get(StageRow, stage_id)
            assert row is not None
            self._event(s, row.job_id, row.name, StageState.QUEUED, StageState.RUNNING, worker[:200])
            # The refresh loads the job and its stages anyway: no second query.
            _newly, job, stages = self._refresh(s, row.job_id)
            assert job is not None
            j = _job(job, stages)
        return Claim(stage=j.stage(row.name), job=j, token=token)

    def heartbeat(self, stage_id: int, token: str, progress: float | None = None) -> bool:
        """Renew a lease; False when it was lost (reconciled, cancelled): the holder should stop."""
        values: dict[str, Any] = {"heartbeat_at": time.time()}
        if progress is not None:
            values["progress"] = float(min(max(progress, 0.0), 1.0))
        with self.session() as s, s.begin():
            res = s.execute(
                update(StageRow)
                .where(StageRow.id == stage_id, StageRow.lease_token == token, StageRow.state == StageState.RUNNING)
                .values(**values)
            )
            return res.rowcount > 0

    def set_input_key(self, stage_id: int, token: str, key: str) -> bool:
        with self.session() as s, s.begin():
            res = s.execute(
                update(StageRow).where(StageRow.id == stage_id, StageRow.lease_token == token).values(input_key=key)
            )
            return res.rowcount > 0

    def _expand(self, s: Session, parent: StageRow, fan: FanOut) -> None:
        """Add the map-stage instances of ``fan`` (:func:`shared.service.jobs.fan_out` of
        ``parent``), replacing any earlier ones (a re-run of the parent), and make every other
        stage that reads one of those map stages read all its instances (the fan-in; none when
        the parent counted no items)."""
        if len(fan.rows) >= FANOUT_SLOTS - 1:  # the instances sit between the parent and the next stage
            raise ValueError(f"stage {parent.name} fans out into {len(fan.rows)} rows, more than {FANOUT_SLOTS - 2}")
        maps = set(fan.maps)
        rows = s.scalars(select(StageRow).where(StageRow.job_id == parent.job_id)).all()
        for r in rows:
            if base_name(r.name) in maps and r.name not in maps:
                s.delete(r)
        s.flush()
        for k, r in enumerate(fan.rows):
            s.add(StageRow(job_id=parent.job_id, name=r.name, position=parent.position + 1 + k, queue=r.queue,
                           depends_on=list(r.depends_on), state=StageState.PENDING))  # fmt: skip
        instances: dict[str, list[str]] = {m: [r.name for r in fan.rows if base_name(r.name) == m] for m in maps}
        for r in rows:
            if base_name(r.name) in maps:
                continue  # deleted above: an instance reads its own item of a sibling (fan_out said which)
            deps = list(r.depends_on or ())
            if any(base_name(d) in maps for d in deps):
                kept = [d for d in deps if base_name(d) not in maps]
                read = [n for m in sorted(maps) if any(base_name(d) == m for d in deps) for n in instances[m]]
                r.depends_on = kept + read  # a new list, so the JSON column is written
        for m in sorted(maps):
            self._event(s, parent.job_id, m, None, StageState.PENDING, f"{len(instances[m])} pieces")
        s.flush()

    def complete_stage(
        self,
        stage_id: int,
        token: str,
        output_key: str,
        summary: dict[str, Any] | None = None,
        reused: bool = False,
        expand: FanOut | None = None,
    ) -> tuple[bool, list[Stage]]:
        """Mark a held stage succeeded, queue what it unblocks. ``expand`` is what this stage
        fans out into (:func:`shared.service.jobs.fan_out`). Returns (whether the lease was
        still ours, stages to publish)."""
        now = time.time()
        with self.session() as s, s.begin():
            res = s.execute(
                update(StageRow)
                .where(StageRow.id == stage_id, StageRow.lease_token == token, StageRow.state == StageState.RUNNING)
                .values(
                    state=StageState.SUCCEEDED, output_key=output_key, input_key=output_key, summary=summary,
                    progress=1.0, finished_at=now, lease_token=None, reused=reused, error=None,
                )
            )  # fmt: skip
            if not res.rowcount:
                return False, []
            row = s.get(StageRow, stage_id)
            assert row is not None
            self._event(s, row.job_id, row.name, StageState.RUNNING, StageState.SUCCEEDED, "reused" if reused else None)
            if expand is not None and expand.maps:
                self._expand(s, row, expand)
            newly = self._refresh_job_state(s, row.job_id)
            return True, self._stages_by_id(s, newly)

    def fail_stage(self, stage_id: int, token: str, error: str) -> bool:
        """Mark a held stage failed with a one-line reason (the job fails with it)."""
        error = " ".join(str(error).split())[:2000]
        with self.session() as s, s.begin():
            res = s.execute(
                update(StageRow)
                .where(StageRow.id == stage_id, StageRow.lease_token == token, StageRow.state == StageState.RUNNING)
                .values(state=StageState.FAILED, error=error, finished_at=time.time(), lease_token=None)
            )
            if not res.rowcount:
                return False
            row = s.get(StageRow, stage_id)
            assert row is not None
            self._event(s, row.job_id, row.name, StageState.RUNNING, StageState.FAILED, error)
            self._refresh_job_state(s, row.job_id)
            return True

    def release_stage(self, stage_id: int, token: str, reason: str) -> bool:
        """Give a held stage back to the queue (a transient fault; it will be retried)."""
        with self.session() as s, s.begin():
            res = s.execute(
                update(StageRow)
                .where(StageRow.id == stage_id, StageRow.lease_token == token, StageRow.state == StageState.RUNNING)
                .values(state=StageState.QUEUED, lease_token=None, queued_at=time.time(), error=reason[:2000])
            )
            if not res.rowcount:
                return False
            row = s.get(StageRow, stage_id)
            assert row is not None
            self._event(s, row.job_id, row.name, StageState.RUNNING, StageState.QUEUED, reason[:500])
            return True

    def fail_queued_stage(self, stage_id: int, error: str) -> bool:
        """Fail a queued stage outright (the reconciler's verdict on a stage that keeps killing workers)."""
        with self.session() as s, s.begin():
            res = s.execute(
                update(StageRow)
                .where(StageRow.id == stage_id, StageRow.state.in_(stage_sources(StageState.FAILED)))
                .values(state=StageState.FAILED, error=error[:2000], finished_at=time.time(), lease_token=None)
            )
            if not res.rowcount:
                return False
            row = s.get(StageRow, stage_id)
            assert row is not None
            self._event(s, row.job_id, row.name, None, StageState.FAILED, error[:500])
            self._refresh_job_state(s, row.job_id)
            return True

    # ---- the reconciler's side -------------------------------------------------------
    def expired_leases(self, older_than: float) -> list[Stage]:
        """Running stages whose last heartbeat is before ``older_than`` (UNIX seconds)."""
        with self.session() as s:
            rows = s.scalars(
                select(StageRow).where(StageRow.state == StageState.RUNNING, StageRow.heartbeat_at < older_than)
            ).all()
            return [_stage(r) for r in rows]

    def requeue_expired(self, stage: Stage) -> bool:
        """Take an expired lease away (compare-and-set on its token and heartbeat) and queue the stage."""
        with self.session() as s, s.begin():
            res = s.execute(
                update(StageRow)
                .where(
                    StageRow.id == stage.id, StageRow.state == StageState.RUNNING,
                    StageRow.lease_token == stage.lease_token, StageRow.heartbeat_at == stage.heartbeat_at,
                )
                .values(state=StageState.QUEUED, lease_token=None, queued_at=time.time())
            )  # fmt: skip
            if not res.rowcount:
                return False
            self._event(s, stage.job_id, stage.name, StageState.RUNNING, StageState.QUEUED,
                        f"lease of {stage.lease_owner} expired")  # fmt: skip
            return True

    def stale_queued(self, older_than: float) -> list[Stage]:
        """Queued stages queued (or last re-published) before ``older_than``."""
        with self.session() as s:
            rows = s.scalars(
                select(StageRow).where(StageRow.state == StageState.QUEUED, StageRow.queued_at < older_than)
            ).all()
            return [_stage(r) for r in rows]

    def touch_queued(self, stage_id: int) -> None:
        with self.session() as s, s.begin():
            s.execute(
                update(StageRow)
                .where(StageRow.id == stage_id, StageRow.state == StageState.QUEUED)
                .values(queued_at=time.time())
            )

    def unsettled_jobs(self) -> list[str]:
        """Ids of jobs not in a final state (the reconciler re-derives their state)."""
        with self.session() as s:
            return list(
                s.scalars(select(JobRow.id).where(JobRow.state.in_(JOB_ACTIVE))).all()
            )

    def settle(self, job_id: str) -> list[Stage]:
        """Re-derive a job's state and queue what its finished stages unblock; stages to publish."""
        with self.session() as s, s.begin():
            return self._stages_by_id(s, self._refresh_job_state(s, job_id))

    # ---- the user's side -------------------------------------------------------------
    def cancel_job(self, job_id: str) -> Job | None:
        """Cancel a job: unfinished stages become cancelled; a worker still running one loses its
        lease and its result is dropped. None when the job is already final."""
        now = time.time()
        with self.session() as s, s.begin():
            job = s.get(JobRow, job_id)
            if job is None or not can_move_job(job.state, JobState.CANCELLED):
                return None
            for r in s.scalars(select(StageRow).where(StageRow.job_id == job_id)).all():
                if can_move_stage(r.state, StageState.CANCELLED):
                    self._event(s, job_id, r.name, r.state, StageState.CANCELLED)
                    r.state = StageState.CANCELLED
                    r.lease_token = None
                    r.finished_at = now
            self._event(s, job_id, None, job.state, JobState.CANCELLED)
            job.state = JobState.CANCELLED
            job.finished_at = now
        return self.get_job(job_id)

    def reset_stages(self, job_id: str, names: Iterable[str], params: dict[str, Any] | None = None) -> list[Stage]:
        """Put the named stages (and nothing else) back to ``pending``, make the job ``queued``
        again (optionally with new parameters) and queue whatever is ready. Stages to publish."""
        with self.session() as s, s.begin():
            return self.reset_stages_in(s, job_id, names, params)

    def reset_stages_in(self, s: Session, job_id: str, names: Iterable[str],
                        params: dict[str, Any] | None = None) -> list[Stage]:  # fmt: skip
        """:meth:`reset_stages` inside the caller's transaction ``s`` (admission runs it under the
        key's lock, so that a retry counts against the running-jobs limit atomically)."""
        names = set(names)
        job = s.get(JobRow, job_id)
        if job is None:
            return []
        for r in s.scalars(select(StageRow).where(StageRow.job_id == job_id)).all():
            if r.name in names and can_move_stage(r.state, StageState.PENDING):
                self._event(s, job_id, r.name, r.state, StageState.PENDING, "retry")
                r.state = StageState.PENDING
                r.error = None
                r.progress = 0.0
                r.finished_at = None
                r.started_at = None
                r.reused = False
        if params is not None:
            job.params = dict(params)
        if job.state != JobState.QUEUED:
            self._event(s, job_id, None, job.state, JobState.QUEUED, "retry")
        job.state = JobState.QUEUED
        job.error = None
        job.finished_at = None
        s.flush()
        return self._stages_by_id(s, self._refresh_job_state(s, job_id))

    # ---- uploads ---------------------------------------------------------------------
    def create_upload(self, owner_id: int, filename: str) -> Upload:
        row = UploadRow(id=str(uuid.uuid4()), owner_id=owner_id, filename=filename[:300], created_at=time.time())
        with self.session() as s, s.begin():
            s.add(row)
        return self.get_upload(row.id, owner_id)  # type: ignore[return-value]

    def get_upload(self, upload_id: str, owner_id: int | None = None) -> Upload | None:
        with self.session() as s:
            r = s.get(UploadRow, upload_id)
            if r is None or (owner_id is not None and r.owner_id != owner_id):
                return None
            return Upload(r.id, r.owner_id, r.filename, r.offset, r.chunks, r.created_at, r.finished)

    def advance_upload(self, upload_id: str, old_offset: int, new_offset: int) -> bool:
        """Record a chunk appended at ``old_offset`` (compare-and-set, so two racing clients cannot both)."""
        with self.session() as s, s.begin():
            res = s.execute(
                update(UploadRow)
                .where(UploadRow.id == upload_id, UploadRow.offset == old_offset, UploadRow.finished.is_(False))
                .values(offset=new_offset, chunks=UploadRow.chunks + 1)
            )
            return res.rowcount > 0

    def finish_upload(self, upload_id: str) -> bool:
        with self.session() as s, s.begin():
            res = s.execute(
                update(UploadRow).where(UploadRow.id == upload_id, UploadRow.finished.is_(False)).values(finished=True)
            )
            return res.rowcount > 0

    def uploads_created_before(self, before: float, limit: int = 500) -> list[str]:
        """Ids of upload sessions opened before ``before`` (epoch seconds), oldest first."""
        with self.session() as s:
            rows = s.execute(
                select(UploadRow.id).where(UploadRow.created_at < before).order_by(UploadRow.created_at).limit(limit)
            )
            return [r[0] for r in rows]

    def delete_upload(self, upload_id: str) -> bool:
        """Forget an upload session (its chunks in storage are the caller's to remove first)."""
        with self.session() as s, s.begin():
            return s.execute(delete(UploadRow).where(UploadRow.id == upload_id)).rowcount > 0


def open_store(url: str | None = None) -> JobStore:
    """The job store at ``url`` (default: the configured ``GRAYLIGHT_DATABASE_URL``)."""
    if url is None:

        url = get_settings().database_url
    return JobStore(url)
