"""Admission of new work against an API key's limits, atomically.

Two limits per key, from configuration (0 disables one): how many jobs it may have queued or
running at once (``GRAYLIGHT_KEY_MAX_RUNNING_JOBS``, refused 429 with ``Retry-After``) and how
many bytes its captures, rig files, upload sessions, stage outputs and unpacked captures may
fill (``GRAYLIGHT_KEY_MAX_STORED_BYTES``, refused 507). Each refusal is a
:class:`~shared.service.usage.LimitReached` naming its limit.

The check and the write it admits are one database transaction that first locks the key's row
(``SELECT ... FOR UPDATE`` on PostgreSQL; on SQLite every transaction begins ``IMMEDIATE``,
which takes the database's write lock), so two submissions of one key serialise there: the
second counts the first's jobs. A batch's jobs are inserted in the same transaction, all or
none. :meth:`Admission.admit` is the same check without the lock, for an early refusal before a
request stores anything (the atomic check still decides).

In: the job store, the artifact store (object sizes), settings. Out: created jobs and their
ready stages, or advanced upload offsets; :class:`LimitReached` otherwise.
"""

from __future__ import annotations

import dataclasses
import time
import uuid
from collections.abc import Iterable, Sequence

from sqlalchemy import select, update
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.orm import Session

from shared.service.artifacts import ArtifactStore
from shared.service.config import Settings
from shared.service.jobstore import (
    ApiKey,
    ApiKeyRow,
    BatchRow,
    CaptureSizeRow,
    Job,
    JobStore,
    NewJob,
    Stage,
    UploadRow,
)
from shared.service.usage import LimitReached, ObjectSizes, key_usage

__all__ = ["RETRY_AFTER", "Admission", "UploadTaken"]

#: Seconds a client refused for running jobs is told to wait before trying again.
RETRY_AFTER = 30


def _record_size(s: Session, capture_key: str, unpacked: int) -> None:
    """Record a capture's unpacked size once (two keys may submit the same capture at once:
    the second insert does nothing instead of failing the transaction)."""
    dialect = s.get_bind().dialect.name
    insert = {"postgresql": pg_insert, "sqlite": sqlite_insert}.get(dialect)
    if insert is None:  # another database: look first (a concurrent duplicate fails one request)
        if s.get(CaptureSizeRow, capture_key) is None:
            s.add(CaptureSizeRow(capture_key=capture_key, unpacked_bytes=unpacked))
        return
    s.execute(insert(CaptureSizeRow).values(capture_key=capture_key, unpacked_bytes=unpacked).on_conflict_do_nothing())


class UploadTaken(Exception):
    """The upload session a job was to be made from was used by another request first."""


class Admission:
    """A service's admission of new work against its keys' limits."""

    def __init__(self, settings: Settings, store: JobStore, arts: ArtifactStore) -> None:
        self.max_jobs = settings.key_max_running_jobs
        self.max_bytes = settings.key_max_stored_bytes
        self.store = store
        self.sizes = ObjectSizes(arts)

    # ---- the check -----------------------------------------------------------------------
    def _check(self, key: ApiKey, jobs: int, adding_bytes: int, objects: Iterable[str], s: Session | None) -> None:
        if not (self.max_jobs and jobs) and not self.max_bytes:
            return  # nothing to check: no query
        use = key_usage(self.store, self.sizes, key.id, s, adding=objects)
        if self.max_jobs and jobs and use.running + jobs > self.max_jobs:
            raise LimitReached(
                "GRAYLIGHT_KEY_MAX_RUNNING_JOBS", 429,
                f"limit GRAYLIGHT_KEY_MAX_RUNNING_JOBS reached: key {key.name!r} may have {self.max_jobs} jobs "
                f"queued or running at once; {use.running} are, and this request adds {jobs}",
                RETRY_AFTER,
            )  # fmt: skip
        if self.max_bytes and use.stored_bytes + adding_bytes > self.max_bytes:
            raise LimitReached(
                "GRAYLIGHT_KEY_MAX_STORED_BYTES", 507,
                f"limit GRAYLIGHT_KEY_MAX_STORED_BYTES reached: key {key.name!r} may store {self.max_bytes} bytes; "
                f"with this request it would store {use.stored_bytes + adding_bytes}",
            )  # fmt: skip

    def admit(self, key: ApiKey, jobs: int = 0, adding_bytes: int = 0) -> None:
        """Raise :class:`LimitReached` when ``jobs`` more would pass the key's running-jobs limit,
        or ``adding_bytes`` more its stored-bytes limit (a key already over it gets no new work:
        its outputs would grow further). Not atomic: an early refusal before anything is stored."""
        self._check(key, jobs, adding_bytes, (), None)

    @staticmethod
    def _lock(s: Session, key: ApiKey) -> None:
        # Serialises this key's admissions (SQLite's IMMEDIATE transaction already holds the lock).
        s.execute(select(ApiKeyRow.id).where(ApiKeyRow.id == key.id).with_for_update())

    # ---- atomic writes -------------------------------------------------------------------
    def create_jobs(self, key: ApiKey, news: Sequence[NewJob], batch: str | None = None,
                    objects: Iterable[str] = (), unpacked: dict[str, int] | None = None,
                    upload_id: str | None = None) -> list[tuple[Job, list[Stage]]]:  # fmt: skip
        """Check the key's limits with ``news`` added (and the stored ``objects`` they hold,
        whose bytes count from now on; ``unpacked``: capture key -> bytes its archive unpacks
        to), then insert the jobs (into the key's batch ``batch``, created when new) and mark the
        upload session ``upload_id`` they come from used (:class:`UploadTaken` when it already
        was), all in one transaction under the key's lock. Returns each job with its stages to
        publish."""
        objects = set(objects)
        with self.store.session() as s, s.begin():
            self._lock(s, key)
            for ckey, n in (unpacked or {}).items():
                _record_size(s, ckey, int(n))
            if upload_id is not None:
                # Used up first, so its bytes count once (as the object made of it), not twice.
                res = s.execute(update(UploadRow).where(UploadRow.id == upload_id, UploadRow.finished.is_(False))
                                .values(finished=True))  # fmt: skip
                if res.rowcount == 0:
                    raise UploadTaken(upload_id)
            s.flush()  # the new jobs' unpacked captures count in the check below
            pending = {n.capture_key for n in news} & set(unpacked or {})
            self._check(key, len(news), sum((unpacked or {})[k] for k in pending), objects, s)
            batch_id = self._batch(s, key, batch) if batch else None
            return [self.store.insert_job(s, key.id, dataclasses.replace(n, batch_id=batch_id)) for n in news]

    @staticmethod
    def _batch(s: Session, key: ApiKey, name: str) -> str:
        bid = s.scalar(select(BatchRow.id).where(BatchRow.owner_id == key.id, BatchRow.name == name))
        if bid:
            return bid
        bid = str(uuid.uuid4())
        s.add(BatchRow(id=bid, owner_id=key.id, name=name, created_at=time.time()))
        s.flush()
        return bid

    def advance_upload(self, key: ApiKey, upload_id: str, old_offset: int, new_offset: int) -> bool:
        """Record a chunk of ``new_offset - old_offset`` bytes appended at ``old_offset`` when the
        key's stored-bytes limit allows it (compare-and-set on the offset, under the key's lock).
        False when another chunk moved the upload on first; :class:`LimitReached` when over."""
        with self.store.session() as s, s.begin():
            self._lock(s, key)
            self._check(key, 0, new_offset - old_offset, (), s)
            res = s.execute(
                update(UploadRow)
                .where(UploadRow.id == upload_id, UploadRow.offset == old_offset, UploadRow.finished.is_(False))
                .values(offset=new_offset, chunks=UploadRow.chunks + 1)
            )
            return res.rowcount > 0
