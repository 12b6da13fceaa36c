"""Storage faults of a running stage, told apart from bugs, in one line a user can act on.

A full disk (the worker's work folder or a local store), a quota, a store mounted read-only
or an I/O error are not the stage's fault and not the input's: :func:`storage_fault` gives
the reason the job fails with (``storage full: no space left on device while stage decode
wrote its output; nothing of it was kept``). Transient faults of a remote store
(connections, timeouts) are not here: the runner gives those stages back to the queue.
"""

from __future__ import annotations

import errno

__all__ = ["STORAGE_ERRNOS", "storage_fault"]

#: errno -> what the reason says.
STORAGE_ERRNOS: dict[int, str] = {
    errno.ENOSPC: "storage full: no space left on device",
    errno.EDQUOT: "storage full: disk quota exceeded",
    errno.EROFS: "storage is read-only",
    errno.EIO: "storage I/O error",
}


def storage_fault(exc: BaseException, stage: str) -> str | None:
    """The one-line reason of a storage fault raised while ``stage`` ran, or None when
    ``exc`` is something else."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:  # the OSError may be wrapped (a library's own error)
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in STORAGE_ERRNOS:
            # The file's path stays in the worker's log: a client's message never names a worker path.
            return f"{STORAGE_ERRNOS[exc.errno]} while stage {stage} wrote its output; nothing of it was kept"
        exc = exc.__cause__ or exc.__context__
    return None
