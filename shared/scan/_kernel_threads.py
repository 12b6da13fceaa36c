"""How many threads the scan's numba kernels get: as many as there are cores free right now.

:func:`kernel_threads` counts the cores other processes leave free at this moment (from
/proc/loadavg's runnable tasks less this process's own runnable threads, read from
/proc/self/task), and :func:`kernel_thread_scope` runs the enclosed kernels with that many
threads. The decoder (:mod:`shared.scan.decode`, which re-exports both) and the triangulation
use them.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import numba

from shared.core.threads import cpu_budget


def _read_proc(path: str) -> bytes | None:
    """The bytes of a /proc file (one read: these are under a page), or None when it cannot be
    read. Raw ``os`` calls: ``Path.read_text`` cost ~15 us a file, and :func:`kernel_threads`
    reads one per thread of the process every decode."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        return os.read(fd, 4096)
    except OSError:
        return None
    finally:
        os.close(fd)


def _own_running() -> int:
    """Runnable threads of this process right now (the caller among them), from
    /proc/self/task; 1 when unknown."""
    n = 0
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return 1
    for task in tasks:
        stat = _read_proc(f"/proc/self/task/{task}/stat")
        if stat is None:
            continue  # the thread has ended
        # The state letter follows the command name, which may itself hold ") ".
        end = stat.rfind(b")")
        n += stat[end + 2 : end + 3] == b"R"
    return max(n, 1)


def _running_tasks() -> int | None:
    """Runnable tasks of the whole machine right now (the caller among them), from
    /proc/loadavg, or None when unknown."""
    loadavg = _read_proc("/proc/loadavg")
    try:
        return int(loadavg.split()[3].split(b"/")[0]) if loadavg is not None else None
    except (ValueError, IndexError):
        return None


def _others_running() -> int | None:
    """Runnable threads of other processes right now (from /proc/loadavg's count of runnable
    tasks, less this process's own: its image readers and kernel workers are no competition),
    or None when unknown."""
    # Own threads first: one that stops running before loadavg is read then errs towards
    # "free", which is what this count is for.
    own = _own_running()
    running = _running_tasks()
    if running is None:
        return None
    return max(running - own, 0)


def kernel_threads() -> int:
    """Threads for the numba kernels: as many as there are cores free right now (cores less
    the runnable threads of other processes at this moment), at least one, at most numba's.

    Two costs decide it. A thread that another process deschedules mid-launch used to hold
    up the whole launch with a fixed split of the rows (numba's prange); the kernels now hand bands out
    dynamically (:mod:`shared.scan._bands`), so the others take its work. But every launch
    still ends when all its threads have arrived, and a worker waiting for a core holds up
    the end by a scheduler time slice: on 2 cores beside 4-5 busy processes, two threads
    took 28-52 ms for the bench's 1.3 MP decode against 29 ms on one. The count is the
    current one, not the 1-minute load average, which lags: on a shared machine that has
    just come free the average kept one thread for a minute (half the speed), and on one
    that has just filled it kept two.
    """
    limit = int(numba.config.NUMBA_NUM_THREADS)
    budget = cpu_budget()
    # The caller is one of the runnable tasks, so other processes have at most one fewer: when
    # even that many leave every thread a core (a quiet machine), this process's own threads
    # need not be counted, a read of /proc per thread (40-150 us, 2 % of the bench's decode).
    running = _running_tasks()
    if running is not None and budget - (running - 1) >= limit:
        return limit
    others = _others_running()
    if others is None:
        return limit
    return max(1, min(limit, budget - others))


@contextmanager
def kernel_thread_scope() -> Iterator[None]:
    """Run the enclosed numba kernels with :func:`kernel_threads` threads, then restore."""
    before = numba.get_num_threads()
    numba.set_num_threads(kernel_threads())
    try:
        yield
    finally:
        numba.set_num_threads(before)
