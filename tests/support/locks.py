"""A file lock the test processes of a run share (xdist workers, and the tests' subprocesses)."""

from __future__ import annotations

import fcntl
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def held(path: Path) -> Iterator[None]:
    """Hold the exclusive lock of the file ``path`` (created if missing) while the block runs: the
    first process to come builds a shared artefact, the others wait for it. The kernel releases
    the lock if the holder dies."""
    with open(path, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
