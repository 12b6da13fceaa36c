"""A worker's cache of unpacked captures: ``DATA/cache/captures/CAPTURE_KEY``, made by the
first stage that reads a capture, and removed when the capture's last unfinished job ends
(succeeded, failed or cancelled), so a capture's unpacked bytes live on a worker's disk only
while the key's stored-bytes limit counts them (:func:`shared.service.usage.unpacked_bytes`).

:func:`release_capture` removes one job's; :func:`sweep_captures` every capture of this
machine's cache that no unfinished job reads (a job cancelled while queued, or failed by the
reconciler after its worker died, ends without a stage of its own to clean up after it).

In: settings, the job store, a job id. Out: what was removed.
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from pathlib import Path

from sqlalchemy import func, select

from shared.service.config import Settings
from shared.service.jobstore import JobRow, JobStore
from shared.service.usage import UNFINISHED

__all__ = ["capture_dir", "release_capture", "sweep_captures"]

log = logging.getLogger(__name__)


def capture_dir(settings: Settings, capture_key: str) -> Path:
    """Where a worker of ``settings`` unpacks the capture ``capture_key``."""
    return settings.cache_dir / "captures" / capture_key


def _remove(folder: Path) -> bool:
    """Rename ``folder`` aside (so no stage sees it half removed), then delete it."""
    aside = folder.with_name(f".gone.{folder.name[:12]}.{uuid.uuid4().hex[:8]}")
    try:
        os.rename(folder, aside)
    except OSError:
        return False  # another worker process removed it first
    shutil.rmtree(aside, ignore_errors=True)
    return True


def sweep_captures(settings: Settings, store: JobStore) -> list[str]:
    """Remove every unpacked capture in this machine's cache that no queued or running job
    reads; returns their capture keys. Folders being unpacked (dot names) are left alone."""
    root = settings.cache_dir / "captures"
    if not root.is_dir():
        return []
    present = {p.name: p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")}
    if not present:
        return []
    with store.session() as s:
        q = select(JobRow.capture_key).where(JobRow.capture_key.in_(list(present)), JobRow.state.in_(UNFINISHED))
        busy = set(s.scalars(q.distinct()))
    gone = [key for key, folder in sorted(present.items()) if key not in busy and _remove(folder)]
    if gone:
        log.info("removed %d unpacked captures no unfinished job reads", len(gone))
    return gone


def release_capture(settings: Settings, store: JobStore, job_id: str) -> bool:
    """Remove the unpacked capture of job ``job_id`` when the job has ended and no unfinished
    job reads the same capture. The folder is renamed aside first, so a stage never sees it
    half removed."""
    with store.session() as s:
        row = s.get(JobRow, job_id)
        if row is None or row.state in UNFINISHED:
            return False
        key = row.capture_key
        busy = s.scalar(select(func.count()).select_from(JobRow).where(JobRow.capture_key == key,
                                                                        JobRow.state.in_(UNFINISHED)))  # fmt: skip
    folder = capture_dir(settings, key)
    if busy or not folder.is_dir() or not _remove(folder):
        return False
    log.info("job %s ended: removed its unpacked capture %s", job_id, key[:12])
    return True
