"""Limits per API key, from configuration: how many jobs a key may have queued or running
at once (``GRAYLIGHT_KEY_MAX_RUNNING_JOBS``, answered 429) and how many bytes its captures,
upload sessions and stage outputs may fill in the store (``GRAYLIGHT_KEY_MAX_STORED_BYTES``,
answered 507). Each answer names its limit. A submission is admitted whole or not at all:
a batch is checked for all of its captures before the first is stored.

Two submissions of one key racing each other can both pass the check (it reads, then the
intake writes): the limits bound a key's share of the service, they are not a ledger.
"""

from __future__ import annotations

from fastapi import HTTPException

from shared.service.artifacts import ArtifactStore
from shared.service.config import Settings
from shared.service.jobstore import ApiKey, JobStore
from shared.service.usage import ObjectSizes, key_usage

__all__ = ["Quota"]

#: Seconds a client refused for running jobs is told to wait before trying again.
RETRY_AFTER = 30


class Quota:
    """Admission of new work against a key's limits (0 disables a limit)."""

    def __init__(self, settings: Settings, store: JobStore, arts: ArtifactStore) -> None:
        self.max_jobs = settings.key_max_running_jobs
        self.max_bytes = settings.key_max_stored_bytes
        self.store = store
        self.sizes = ObjectSizes(arts)

    def admit(self, key: ApiKey, jobs: int = 0, adding_bytes: int = 0) -> None:
        """Raise 429 when ``jobs`` more would pass the key's running-jobs limit, 507 when
        ``adding_bytes`` more would pass its stored-bytes limit (a key already over it gets no
        new work: its outputs would grow further); else return."""
        if not (self.max_jobs and jobs) and not self.max_bytes:
            return  # nothing to check: no database query
        use = key_usage(self.store, self.sizes, key.id)
        if self.max_jobs and jobs and use.running + jobs > self.max_jobs:
            raise HTTPException(
                429,
                f"limit GRAYLIGHT_KEY_MAX_RUNNING_JOBS reached: key {key.name!r} may have {self.max_jobs} jobs "
                f"queued or running at once; {use.running} are, and this request adds {jobs}",
                headers={"Retry-After": str(RETRY_AFTER)},
            )
        if self.max_bytes and use.stored_bytes + adding_bytes > self.max_bytes:
            raise HTTPException(
                507,
                f"limit GRAYLIGHT_KEY_MAX_STORED_BYTES reached: key {key.name!r} may store {self.max_bytes} bytes; "
                f"it stores {use.stored_bytes}, and this request adds {adding_bytes}",
            )
