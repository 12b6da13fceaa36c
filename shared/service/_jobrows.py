"""The job store's tables and records (:mod:`shared.service.jobstore` is the repository over them).

The SQLAlchemy 2.0 rows (:class:`Base` and one ``*Row`` class a table), the plain frozen
records handed to callers (:class:`Job`, :class:`Stage`, :class:`Batch`, ...; no live ORM
object leaves a session) with the functions that copy rows into them, :func:`hash_key` for
API keys, and the per-process engines (:func:`_engine`: SQLite tuned for several writer
processes, or PostgreSQL through psycopg; :func:`dispose_engines`).

Times are UNIX seconds (float, UTC) so that they compare the same on every backend.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    create_engine,
    event,
)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from shared.service.jobs import StageSpec


class Base(DeclarativeBase):
    pass


class ApiKeyRow(Base):
    __tablename__ = "api_keys"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(200))
    prefix: Mapped[str] = mapped_column(String(16))
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[float] = mapped_column(Float)
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)


class BatchRow(Base):
    __tablename__ = "batches"
    __table_args__ = (UniqueConstraint("owner_id", "name"),)
    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    owner_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id"))
    name: Mapped[str] = mapped_column(String(200))
    created_at: Mapped[float] = mapped_column(Float)


class JobRow(Base):
    __tablename__ = "jobs"
    __table_args__ = (Index("ix_jobs_owner_state", "owner_id", "state"), Index("ix_jobs_batch", "batch_id"))
    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    owner_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id"))
    batch_id: Mapped[str | None] = mapped_column(ForeignKey("batches.id"), nullable=True)
    kind: Mapped[str] = mapped_column(String(32))
    name: Mapped[str] = mapped_column(String(300), default="")
    state: Mapped[str] = mapped_column(String(16))
    capture_ref: Mapped[str] = mapped_column(Text)  # artifact-store path of the capture
    capture_key: Mapped[str] = mapped_column(String(64))  # SHA-256 of the capture's bytes
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[float] = mapped_column(Float)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    seq: Mapped[int] = mapped_column(Integer, default=0)  # creation order for stable paging


class StageRow(Base):
    __tablename__ = "stages"
    __table_args__ = (UniqueConstraint("job_id", "name"), Index("ix_stages_state", "state"))
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"))
    name: Mapped[str] = mapped_column(String(64))
    position: Mapped[int] = mapped_column(Integer)
    queue: Mapped[str] = mapped_column(String(32))
    depends_on: Mapped[list[str]] = mapped_column(JSON, default=list)
    state: Mapped[str] = mapped_column(String(16))
    attempts: Mapped[int] = mapped_column(Integer, default=0)  # claims by a worker
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    input_key: Mapped[str | None] = mapped_column(String(64), nullable=True)
    output_key: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_token: Mapped[str | None] = mapped_column(String(36), nullable=True)
    lease_owner: Mapped[str | None] = mapped_column(String(200), nullable=True)
    heartbeat_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    queued_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    summary: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    reused: Mapped[bool] = mapped_column(Boolean, default=False)


class EventRow(Base):
    __tablename__ = "events"
    __table_args__ = (Index("ix_events_job", "job_id"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(String(36))
    stage: Mapped[str | None] = mapped_column(String(64), nullable=True)
    old: Mapped[str | None] = mapped_column(String(16), nullable=True)
    new: Mapped[str] = mapped_column(String(16))
    at: Mapped[float] = mapped_column(Float)
    detail: Mapped[str | None] = mapped_column(Text, nullable=True)


class BatchRejectRow(Base):
    """A file sent with a batch and refused at intake: kept so the batch accounts for it."""

    __tablename__ = "batch_rejects"
    __table_args__ = (Index("ix_batch_rejects_batch", "batch_id"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    batch_id: Mapped[str] = mapped_column(ForeignKey("batches.id"))
    capture: Mapped[str] = mapped_column(Text)  # its name as sent
    error: Mapped[str] = mapped_column(Text)  # the one-line reason
    at: Mapped[float] = mapped_column(Float)


class UploadRow(Base):
    __tablename__ = "uploads"
    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    owner_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id"))
    filename: Mapped[str] = mapped_column(String(300), default="")
    offset: Mapped[int] = mapped_column(Integer, default=0)
    chunks: Mapped[int] = mapped_column(Integer, default=0)
    created_at: Mapped[float] = mapped_column(Float)
    finished: Mapped[bool] = mapped_column(Boolean, default=False)


class CaptureSizeRow(Base):
    """Bytes a capture archive unpacks to (its checked headers, enforced while inflating): its
    unpacked copy in a worker's cache counts against the key's stored bytes while a job of the
    capture is unfinished (:mod:`shared.service.usage`)."""

    __tablename__ = "capture_sizes"
    capture_key: Mapped[str] = mapped_column(String(64), primary_key=True)
    unpacked_bytes: Mapped[int] = mapped_column(BigInteger)


# ---------------------------------------------------------------------------------------
# Plain records handed to callers (no live ORM objects leave a session).


@dataclass(frozen=True)
class ApiKey:
    id: int
    name: str
    prefix: str
    created_at: float


@dataclass(frozen=True)
class Stage:
    id: int
    job_id: str
    name: str
    position: int
    queue: str
    depends_on: tuple[str, ...]
    state: str
    attempts: int
    progress: float
    input_key: str | None
    output_key: str | None
    lease_token: str | None
    lease_owner: str | None
    heartbeat_at: float | None
    queued_at: float | None
    started_at: float | None
    finished_at: float | None
    error: str | None
    summary: dict[str, Any] | None
    reused: bool


@dataclass(frozen=True)
class Job:
    id: str
    owner_id: int
    batch_id: str | None
    kind: str
    name: str
    state: str
    capture_ref: str
    capture_key: str
    params: dict[str, Any]
    error: str | None
    created_at: float
    started_at: float | None
    finished_at: float | None
    stages: tuple[Stage, ...] = field(default_factory=tuple)

    def stage(self, name: str) -> Stage:
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(name)


@dataclass(frozen=True)
class Reject:
    """A file of a batch refused at intake: its name as sent and the one-line reason."""

    capture: str
    error: str
    at: float


#: The count a batch gives its refused files under (beside the job states).
REJECTED = "rejected"


@dataclass(frozen=True)
class Batch:
    """A batch: ``counts`` of its jobs by state plus ``rejected`` files (refused at intake,
    each listed in ``rejects``), so ``total`` is every file sent."""

    id: str
    owner_id: int
    name: str
    created_at: float
    counts: dict[str, int]
    rejects: tuple[Reject, ...] = ()

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    @property
    def job_count(self) -> int:
        """How many jobs the batch has (its files but the rejected ones)."""
        return self.total - self.counts.get(REJECTED, 0)

    @property
    def progress(self) -> float:
        done = sum(self.counts.get(s, 0) for s in ("succeeded", "failed", "cancelled", REJECTED))
        return done / self.total if self.total else 1.0


@dataclass(frozen=True)
class Upload:
    id: str
    owner_id: int
    filename: str
    offset: int
    chunks: int
    created_at: float
    finished: bool


@dataclass(frozen=True)
class Claim:
    """A worker's hold on a running stage: the lease token it must present to finish it."""

    stage: Stage
    job: Job
    token: str


@dataclass(frozen=True)
class NewJob:
    """What a caller needs to create a job."""

    kind: str
    capture_ref: str
    capture_key: str
    graph: Sequence[StageSpec]
    name: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    batch_id: str | None = None


def _stage(r: StageRow) -> Stage:
    return Stage(
        id=r.id, job_id=r.job_id, name=r.name, position=r.position, queue=r.queue,
        depends_on=tuple(r.depends_on or ()), state=r.state, attempts=r.attempts, progress=r.progress,
        input_key=r.input_key, output_key=r.output_key, lease_token=r.lease_token, lease_owner=r.lease_owner,
        heartbeat_at=r.heartbeat_at, queued_at=r.queued_at, started_at=r.started_at, finished_at=r.finished_at,
        error=r.error, summary=r.summary, reused=bool(r.reused),
    )  # fmt: skip


def _job(r: JobRow, stages: Iterable[StageRow] = ()) -> Job:
    return Job(
        id=r.id, owner_id=r.owner_id, batch_id=r.batch_id, kind=r.kind, name=r.name, state=r.state,
        capture_ref=r.capture_ref, capture_key=r.capture_key, params=dict(r.params or {}), error=r.error,
        created_at=r.created_at, started_at=r.started_at, finished_at=r.finished_at,
        stages=tuple(_stage(s) for s in sorted(stages, key=lambda s: s.position)),
    )  # fmt: skip


def hash_key(key: str) -> str:
    """SHA-256 hex of an API key (keys are 256-bit random, so a plain hash is enough)."""
    return hashlib.sha256(key.encode()).hexdigest()


_ENGINES: dict[str, Engine] = {}
_ENGINES_LOCK = threading.Lock()
#: Databases whose tables this process has created or found: a worker opens the store once a
#: stage, and checking every table again cost about a quarter of the CPU a trivial stage adds.
_TABLES_READY: set[str] = set()


def _engine(url: str) -> Engine:
    with _ENGINES_LOCK:
        eng = _ENGINES.get(url)
        if eng is not None:
            return eng
        if url.startswith("sqlite"):
            path = url.split("///", 1)[-1]
            if path and path != ":memory:":
                from pathlib import Path

                Path(path).parent.mkdir(parents=True, exist_ok=True)
            eng = create_engine(url, connect_args={"timeout": 60, "check_same_thread": False})

            @event.listens_for(eng, "connect")
            def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
                # WAL lets readers run beside the one writer; the busy timeout makes writers
                # from several worker processes wait for each other instead of failing.
                dbapi_conn.isolation_level = None
                cur = dbapi_conn.cursor()
                cur.execute("PRAGMA journal_mode=WAL")
                cur.execute("PRAGMA busy_timeout=60000")
                cur.execute("PRAGMA synchronous=NORMAL")
                cur.close()

            @event.listens_for(eng, "begin")
            def _sqlite_begin(conn: Any) -> None:
                # IMMEDIATE takes the write lock up front: a deferred transaction that read
                # first and then writes fails at once (SQLITE_BUSY_SNAPSHOT) when another
                # process wrote in between, and no busy timeout helps it.
                conn.exec_driver_sql("BEGIN IMMEDIATE")
        else:
            url = url.replace("postgresql://", "postgresql+psycopg://", 1) if url.startswith("postgresql://") else url
            url = url.replace("postgres://", "postgresql+psycopg://", 1) if url.startswith("postgres://") else url
            eng = create_engine(url, pool_pre_ping=True, pool_size=5, max_overflow=5)
        _ENGINES[url] = eng
        return eng


def dispose_engines() -> None:
    """Close every pooled connection (after a fork, and in tests that drop a database)."""
    with _ENGINES_LOCK:
        for eng in _ENGINES.values():
            eng.dispose()
        _ENGINES.clear()
        _TABLES_READY.clear()
