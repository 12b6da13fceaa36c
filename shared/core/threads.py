"""The CPU budget of a process and numba's threading policy.

:func:`cpu_budget` is the one count of CPUs every domain sizes its thread pools by (scan, merge,
compress, render). :func:`pin_threading_layer` is numba's threading policy, one for every process
that runs Graylight's parallel kernels: imported by the kernel modules that launch parallel work
(``shared.scan._bands``, ``shared.render.raster``), so a process that scans, one that only
renders (the preview CLI, a render worker) and the bench all run on the same layer. This module
imports numba, so ``shared.core``'s ``__init__`` exports :func:`cpu_budget` lazily: importing
the package loads no numba.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from collections.abc import Iterable
from pathlib import Path, PurePosixPath

import numba

from shared.core.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["THREADS_ENV", "budget_from", "cgroup_cpu_dirs", "cpu_budget", "cpu_max_quota", "cfs_quota",
           "pin_threading_layer"]  # fmt: skip

#: Environment variable that sets the CPU budget outright (a whole number >= 1).
THREADS_ENV = "GRAYLIGHT_THREADS"


def cpu_max_quota(text: str) -> float | None:
    """CPUs allowed by the contents of a cgroup v2 ``cpu.max`` (``"$MAX $PERIOD"``, both in µs;
    ``"max 100000"`` is no cap), or None when there is no cap or the text is not of that form.
    A period may be left out (the kernel's default, 100000 µs)."""
    parts = text.split()
    if not parts or parts[0] == "max" or len(parts) > 2:
        return None
    try:
        quota = int(parts[0])
        period = int(parts[1]) if len(parts) == 2 else 100_000
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def cfs_quota(quota_text: str, period_text: str) -> float | None:
    """CPUs allowed by the contents of cgroup v1's ``cpu.cfs_quota_us`` and ``cpu.cfs_period_us``
    (µs; a quota of -1 is no cap), or None when there is no cap or the text is not a number."""
    try:
        quota, period = int(quota_text.strip()), int(period_text.strip())
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def cgroup_cpu_dirs(mountinfo: str, proc_cgroup: str) -> list[tuple[int, Path]]:
    """The cgroup directories whose CPU limits bind this process, as ``(version, dir)``: the
    process's own cgroup and its ancestors up to the mount's root, under the cgroup v2 mount and
    the v1 mount of the ``cpu`` controller, from the contents of ``/proc/self/mountinfo`` and
    ``/proc/self/cgroup``.

    A cgroup's path in ``/proc/self/cgroup`` is relative to the hierarchy's root; a container's
    mount shows only its own subtree (the mount's root, field 4 of mountinfo, is that subtree), so
    the directory is the mount point plus the path less the mount's root. A path outside the
    mount's root (a container without a cgroup namespace that sees the host's path) falls back to
    the mount point itself, which in such a container is the container's cgroup.
    """
    paths: dict[int, str] = {}  # version -> cgroup path
    for line in proc_cgroup.splitlines():
        hier, _, rest = line.partition(":")
        controllers, _, path = rest.partition(":")
        if not path:
            continue
        if hier == "0" and controllers == "":
            paths[2] = path
        elif "cpu" in controllers.split(","):
            paths[1] = path
    dirs: list[tuple[int, Path]] = []
    for line in mountinfo.splitlines():
        fields = line.split()
        if " - " not in line or len(fields) < 5:
            continue
        after = line.split(" - ", 1)[1].split()
        if not after:
            continue
        fstype, options = after[0], after[2].split(",") if len(after) > 2 else []
        if fstype == "cgroup2":
            version = 2
        elif fstype == "cgroup" and "cpu" in options:
            version = 1
        else:
            continue
        if version not in paths or any(v == version for v, _ in dirs):
            continue
        root, mount_point = PurePosixPath(fields[3]), Path(fields[4])
        path = PurePosixPath(paths[version])
        rel = path.relative_to(root) if path == root or root in path.parents else PurePosixPath(".")
        parts = [p for p in rel.parts if p not in (".", "/")]
        for depth in range(len(parts), -1, -1):
            dirs.append((version, mount_point.joinpath(*parts[:depth])))
    return dirs


def budget_from(affinity: int, quotas: Iterable[float | None], override: str | None) -> int:
    """The CPU budget from its parts: ``override`` (the text of :data:`THREADS_ENV`, or None)
    wins when set; else the ``affinity`` count capped by the smallest CPU quota (fractional CPUs,
    None for no cap) rounded up, at least 1. Raises :class:`InputError` naming the variable when
    the override is not a whole number >= 1."""
    if override is not None:
        text = override.strip()
        if not text.isdigit() or int(text) < 1:
            raise InputError(THREADS_ENV, f"must be a whole number of threads, at least 1; got {override!r}")
        return int(text)
    limits = [q for q in quotas if q is not None]
    cap = math.ceil(min(limits)) if limits else affinity
    return max(1, min(affinity, cap))


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:
        return None


def _quotas(dirs: Iterable[tuple[int, Path]]) -> list[float | None]:
    quotas: list[float | None] = []
    for version, d in dirs:
        if version == 2:
            text = _read(d / "cpu.max")
            quotas.append(cpu_max_quota(text) if text is not None else None)
        else:
            quota, period = _read(d / "cpu.cfs_quota_us"), _read(d / "cpu.cfs_period_us")
            quotas.append(cfs_quota(quota, period) if quota is not None and period is not None else None)
    return quotas


def _affinity() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


@functools.cache
def cpu_budget() -> int:
    """CPUs this process may use: the threads to size its pools and kernels by (an int >= 1).

    ``os.cpu_count()`` counts the machine's CPUs, not the process's: a container with a CPU quota
    (Docker's ``--cpus``, a Kubernetes CPU limit: cgroup v2 ``cpu.max``, or v1's
    ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``) is throttled once its threads together use
    more than the quota, and one started with a CPU set (``taskset``, ``--cpuset-cpus``,
    Kubernetes' static CPU manager) runs on only those CPUs. A pool sized by the machine's count
    then runs more threads than can run at once: they wait for each other (and a throttled
    cgroup stalls until its next period) while holding their buffers. The budget is the CPUs of
    the affinity mask (``os.sched_getaffinity``), capped by the smallest quota of the process's
    cgroup and its ancestors, rounded up (1.5 CPUs of quota: 2 threads), at least 1.

    ``GRAYLIGHT_THREADS`` (:data:`THREADS_ENV`), when set, is the budget, as given (for a
    machine whose limits are not visible here, or to run on fewer CPUs); a value that is not a
    whole number >= 1 raises :class:`InputError` naming it. The result is cached: the limits and
    the variable are read once a process (``cpu_budget.cache_clear()`` reads them again).
    """
    override = os.environ.get(THREADS_ENV)
    dirs: list[tuple[int, Path]] = []
    if override is None:
        mountinfo, proc_cgroup = _read(Path("/proc/self/mountinfo")), _read(Path("/proc/self/cgroup"))
        if mountinfo is not None and proc_cgroup is not None:
            dirs = cgroup_cpu_dirs(mountinfo, proc_cgroup)
    affinity = _affinity()
    budget = budget_from(affinity, _quotas(dirs), override)
    log.debug("CPU budget %d (affinity %d, %s %s)", budget, affinity, THREADS_ENV, override)
    return budget


def pin_threading_layer() -> None:
    """Prefer OpenMP among numba's threading layers, its workers waiting passively.

    numba picks TBB when a libtbb is installed, else OpenMP, else its own workqueue, so two
    machines of one kind ran the kernels on different layers (whether some package had pulled
    in libtbb). OpenMP is there wherever numba's wheels run (libgomp) and, unlike the
    workqueue, takes launches from several threads at once. Its workers spin for a while after
    each launch by default; on a shared machine that burnt CPU the image readers and other
    processes wanted. Measured on 2 cores: the 1.3 MP 42-frame decode took 60-77 ms of CPU a
    run on two spinning OpenMP threads, against 36-43 ms passive, 35-46 ms on TBB and 34 ms on
    one thread; 1280x720 preview batches (one frame a thread, 1.5 M points a frame, load 6-7)
    9.7-9.9 ms of CPU a frame on TBB (whose idle worker spins while the other frame draws, with
    rounds at twice that), 12.3 ms on OpenMP spinning, 8.3-9.1 ms on OpenMP passive.

    Either environment variable set by the user wins; so does a layer numba has already
    started (the setting is read at its first parallel launch). Idempotent.
    """
    if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
