"""A worker's cache of unpacked captures: ``DATA/cache/captures/CAPTURE_KEY``, made by the
first stage that reads a capture, and removed when the capture's last unfinished job ends
(succeeded, failed or cancelled), so a capture's unpacked bytes live on a worker's disk only
while the key's stored-bytes limit counts them (:func:`shared.service.usage.unpacked_bytes`).

In: settings, the job store, a job id. Out: whether the folder was removed.
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

__all__ = ["capture_dir", "release_capture"]

log = logging.getLogger(__name__)


def capture_dir(settings: Settings, capture_key: str) -> Path:
    """Where a worker of ``settings`` unpacks the capture ``capture_key``."""
    return settings.cache_dir / "captures" / capture_key


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
    if busy or not folder.is_dir():
        return False
    aside = folder.with_name(f".gone.{key[:12]}.{uuid.uuid4().hex[:8]}")
    try:
        os.rename(folder, aside)
    except OSError:
        return False  # another worker process released it first
    shutil.rmtree(aside, ignore_errors=True)
    log.info("job %s ended: removed its unpacked capture %s", job_id, key[:12])
    return True
