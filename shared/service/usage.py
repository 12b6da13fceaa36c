"""What an API key uses of the service, for its limits and for the metrics: its unfinished
jobs, and the bytes its captures, upload sessions and stage outputs fill in the store.

The captures of a key's unfinished jobs count once more, with the bytes they unpack to (a
worker's capture cache holds them until the job ends), so a decompression bomb that passed
the archive checks still cannot fill a worker's disk beyond the key's share.

Objects in the store are content-addressed and never change, so the size of each (the sum of
its manifest's file sizes) is read once per process and kept (:class:`ObjectSizes`). An object
shared by two keys (the same capture submitted twice) counts for both; an object counts once
for one key however many of its jobs use it. The files a stage detaches (the raw range image,
:attr:`shared.service.jobs.StageSpec.detach`) are objects that a later stage may delete: they
count while they exist, their sizes read again when older than ``recheck_seconds``.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from shared.service.artifacts import ArtifactStore, detached_key
from shared.service.jobs import JobState, StageState, stage_spec
from shared.service.jobstore import CaptureSizeRow, JobRow, JobStore, StageRow, UploadRow

__all__ = ["LimitReached", "ObjectSizes", "Usage", "detached_keys", "key_usage", "running_jobs", "stored_keys",
           "unpacked_bytes"]

#: Job states that count against a key's limit of running jobs.
UNFINISHED = (JobState.QUEUED, JobState.RUNNING)


class LimitReached(Exception):
    """A key's limit refuses new work: ``limit`` names the setting, ``status`` is the HTTP
    answer (429 for running jobs, 507 for stored bytes), ``retry_after`` the seconds to wait
    (0: no advice). The message names the limit, the key's use and what the request adds."""

    def __init__(self, limit: str, status: int, message: str, retry_after: int = 0) -> None:
        super().__init__(message)
        self.limit = limit
        self.status = status
        self.retry_after = retry_after


@contextlib.contextmanager
def _session(store: JobStore, s: Session | None) -> Iterator[Session]:
    """The caller's session (inside its transaction), or a new one of its own."""
    if s is not None:
        yield s
        return
    with store.session() as own:
        yield own


@dataclass(frozen=True)
class Usage:
    """A key's use: ``running`` jobs queued or running, ``stored_bytes`` in the store."""

    running: int
    stored_bytes: int


class ObjectSizes:
    """Sizes in bytes of stored objects by key, read from their manifests once (thread-safe);
    those of ``deletable`` objects again when older than ``recheck_seconds``."""

    def __init__(self, arts: ArtifactStore, limit: int = 200_000, recheck_seconds: float = 30.0) -> None:
        self.arts = arts
        self.limit = limit
        self.recheck_seconds = recheck_seconds
        self._sizes: dict[str, tuple[int, float]] = {}  # key -> (bytes, time.monotonic() read)
        self._lock = threading.Lock()

    def size(self, key: str, deletable: bool = False) -> int:
        now = time.monotonic()
        with self._lock:
            hit = self._sizes.get(key)
            if hit is not None and (not deletable or now - hit[1] < self.recheck_seconds):
                return hit[0]
        m = self.arts.manifest(key)
        if m is None:
            with self._lock:
                self._sizes.pop(key, None)
            return 0  # not (yet, or no longer) stored: not cached, it may appear
        n = sum(e.size for e in m.files.values())
        with self._lock:
            if len(self._sizes) >= self.limit:
                self._sizes.clear()
            self._sizes[key] = (n, now)
        return n

    def total(self, keys: Iterable[str], deletable: Iterable[str] = ()) -> int:
        """Bytes of the objects ``keys`` and of the ``deletable`` ones that still exist."""
        return sum(self.size(k) for k in set(keys)) + sum(self.size(k, deletable=True) for k in set(deletable))


def running_jobs(store: JobStore, owner_id: int, s: Session | None = None) -> int:
    """How many of ``owner_id``'s jobs are queued or running (in session ``s`` when given)."""
    with _session(store, s) as s:
        q = select(func.count()).select_from(JobRow).where(JobRow.owner_id == owner_id, JobRow.state.in_(UNFINISHED))
        return int(s.scalar(q) or 0)


def stored_keys(store: JobStore, owner_id: int | None = None, s: Session | None = None) -> tuple[set[str], int]:
    """The object keys ``owner_id``'s jobs hold (captures stored as objects, rig files, outputs
    of succeeded stages; everyone's when None) and the bytes of its unfinished upload sessions."""
    with _session(store, s) as s:
        jq = select(JobRow.capture_ref)
        sq = select(StageRow.output_key).join(JobRow, JobRow.id == StageRow.job_id).where(
            StageRow.state == StageState.SUCCEEDED, StageRow.output_key.is_not(None)
        )
        uq = select(func.coalesce(func.sum(UploadRow.offset), 0)).where(UploadRow.finished.is_(False))
        if owner_id is not None:
            jq, sq, uq = jq.where(JobRow.owner_id == owner_id), sq.where(JobRow.owner_id == owner_id), uq.where(
                UploadRow.owner_id == owner_id
            )
        keys = {ref.split(":", 1)[1] for ref in s.scalars(jq.distinct()) if ref.startswith("object:")}
        rq = select(JobRow.params)
        rq = rq.where(JobRow.owner_id == owner_id) if owner_id is not None else rq
        keys |= {p["rig"] for p in s.scalars(rq) if isinstance(p, dict) and isinstance(p.get("rig"), str)}
        keys |= {k for k in s.scalars(sq.distinct()) if k}
        uploads = int(s.scalar(uq) or 0)
    return keys, uploads


def unpacked_bytes(store: JobStore, owner_id: int, s: Session | None = None) -> int:
    """Bytes the captures of ``owner_id``'s unfinished jobs unpack to in a worker's capture
    cache (each capture once; the cache is removed when its last job ends)."""
    with _session(store, s) as s:
        busy = select(JobRow.capture_key).where(JobRow.owner_id == owner_id, JobRow.state.in_(UNFINISHED)).distinct()
        q = select(func.coalesce(func.sum(CaptureSizeRow.unpacked_bytes), 0)).where(CaptureSizeRow.capture_key.in_(busy))
        return int(s.scalar(q) or 0)


def detached_keys(store: JobStore, owner_id: int | None = None, s: Session | None = None) -> set[str]:
    """The keys of the objects detached from the outputs of ``owner_id``'s succeeded stages
    (everyone's when None): whether each still exists is the store's to say."""
    with _session(store, s) as s:
        q = select(JobRow.kind, StageRow.name, StageRow.output_key).join(JobRow, JobRow.id == StageRow.job_id).where(
            StageRow.state == StageState.SUCCEEDED, StageRow.output_key.is_not(None)
        )
        if owner_id is not None:
            q = q.where(JobRow.owner_id == owner_id)
        rows = s.execute(q.distinct()).all()
    keys: set[str] = set()
    for kind, name, key in rows:
        try:
            spec = stage_spec(kind, name)
        except KeyError:  # a stage of a graph that no longer has it
            continue
        keys.update(detached_key(key, f) for f in spec.detach)
    return keys


def key_usage(store: JobStore, sizes: ObjectSizes, owner_id: int, s: Session | None = None,
              adding: Iterable[str] = ()) -> Usage:  # fmt: skip
    """``owner_id``'s :class:`Usage` (read in session ``s`` when given), as it would be with the
    objects ``adding`` held too (one the key holds already is not counted twice)."""
    keys, uploads = stored_keys(store, owner_id, s)
    stored = sizes.total(keys | set(adding), deletable=detached_keys(store, owner_id, s)) + uploads
    stored += unpacked_bytes(store, owner_id, s)
    return Usage(running=running_jobs(store, owner_id, s), stored_bytes=stored)
