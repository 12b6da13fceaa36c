"""The CPU budget: cgroup limits parsed from the files' real contents, the affinity cap, the
GRAYLIGHT_THREADS override and its error."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

import shared.core
from shared.core.errors import InputError
from shared.core.threads import (
    THREADS_ENV,
    _quotas,
    budget_from,
    cfs_quota,
    cgroup_cpu_dirs,
    cpu_budget,
    cpu_max_quota,
)


@pytest.fixture(autouse=True)
def _fresh_budget() -> Iterator[None]:
    cpu_budget.cache_clear()
    yield
    cpu_budget.cache_clear()


@pytest.mark.parametrize(("text", "cpus"), [
    ("max 100000\n", None),  # no cap (the kernel's default)
    ("max\n", None),
    ("150000 100000\n", 1.5),  # docker --cpus=1.5
    ("200000 100000\n", 2.0),
    ("50000 100000\n", 0.5),
    ("400000 200000\n", 2.0),
    ("250000\n", 2.5),  # period left out: 100000 us
    ("", None),
    ("banana 100000\n", None),
    ("0 100000\n", None),
    ("100000 0\n", None),
])  # fmt: skip
def test_cgroup_v2_cpu_max(text: str, cpus: float | None) -> None:
    assert cpu_max_quota(text) == cpus


@pytest.mark.parametrize(("quota", "period", "cpus"), [
    ("-1\n", "100000\n", None),  # no cap
    ("250000\n", "100000\n", 2.5),
    ("100000\n", "100000\n", 1.0),
    ("50000\n", "100000\n", 0.5),
    ("", "100000\n", None),
    ("100000\n", "0\n", None),
])  # fmt: skip
def test_cgroup_v1_cfs_quota(quota: str, period: str, cpus: float | None) -> None:
    assert cfs_quota(quota, period) == cpus


# /proc/self/mountinfo and /proc/self/cgroup as three kinds of machine show them.
V2_CONTAINER_MOUNTS = (
    "1193 1172 0:26 / /sys/fs/cgroup ro,nosuid,nodev,noexec,relatime - cgroup2 cgroup rw,nsdelegate\n"
    "1194 1172 0:60 / /proc rw,nosuid,nodev,noexec,relatime - proc proc rw\n"
)
V2_HOST_MOUNTS = "35 24 0:30 / /sys/fs/cgroup rw,nosuid,nodev,noexec,relatime shared:9 - cgroup2 cgroup2 rw,nsdelegate\n"
V1_DOCKER_MOUNTS = (
    "704 703 0:28 / /sys/fs/cgroup ro,nosuid,nodev,noexec - tmpfs tmpfs ro,mode=755\n"
    "705 704 0:29 /docker/0a1b2c /sys/fs/cgroup/cpu,cpuacct ro,nosuid,nodev,noexec,relatime master:12"
    " - cgroup cgroup rw,cpu,cpuacct\n"
    "706 704 0:30 /docker/0a1b2c /sys/fs/cgroup/memory ro,nosuid,nodev,noexec,relatime master:13"
    " - cgroup cgroup rw,memory\n"
)
HYBRID_MOUNTS = (
    "31 23 0:28 / /sys/fs/cgroup rw,relatime - tmpfs tmpfs rw,mode=755\n"
    "32 31 0:29 / /sys/fs/cgroup/cpu rw,relatime - cgroup cgroup rw,cpu\n"
    "33 31 0:30 / /sys/fs/cgroup/cpuacct rw,relatime - cgroup cgroup rw,cpuacct\n"
    "41 31 0:38 / /sys/fs/cgroup/unified rw,relatime - cgroup2 cgroup2 rw\n"
)


def test_cgroup_dirs_of_a_v2_container_are_the_mount_point() -> None:
    assert cgroup_cpu_dirs(V2_CONTAINER_MOUNTS, "0::/\n") == [(2, Path("/sys/fs/cgroup"))]


def test_cgroup_dirs_of_a_v2_host_run_from_the_process_up_to_the_root() -> None:
    dirs = cgroup_cpu_dirs(V2_HOST_MOUNTS, "0::/system.slice/graylight-worker.service\n")
    assert dirs == [(2, Path("/sys/fs/cgroup/system.slice/graylight-worker.service")),
                    (2, Path("/sys/fs/cgroup/system.slice")), (2, Path("/sys/fs/cgroup"))]  # fmt: skip


def test_cgroup_dirs_of_a_v1_container_strip_the_mount_root() -> None:
    proc = "12:memory:/docker/0a1b2c\n4:cpu,cpuacct:/docker/0a1b2c\n1:name=systemd:/docker/0a1b2c\n"
    assert cgroup_cpu_dirs(V1_DOCKER_MOUNTS, proc) == [(1, Path("/sys/fs/cgroup/cpu,cpuacct"))]
    # A path outside the mount's root (no cgroup namespace): the mount point is the container's.
    assert cgroup_cpu_dirs(V1_DOCKER_MOUNTS, "4:cpu,cpuacct:/other\n") == [(1, Path("/sys/fs/cgroup/cpu,cpuacct"))]


def test_cgroup_dirs_of_a_hybrid_machine_hold_both_versions() -> None:
    proc = "3:cpuset:/\n2:cpuacct:/\n1:cpu:/\n0::/\n"
    assert cgroup_cpu_dirs(HYBRID_MOUNTS, proc) == [(1, Path("/sys/fs/cgroup/cpu")), (2, Path("/sys/fs/cgroup/unified"))]
    assert cgroup_cpu_dirs("", proc) == [] and cgroup_cpu_dirs(HYBRID_MOUNTS, "") == []


def test_quotas_are_read_from_every_dir(tmp_path: Path) -> None:
    leaf, v1 = tmp_path / "leaf", tmp_path / "v1"
    leaf.mkdir(), v1.mkdir()
    (tmp_path / "cpu.max").write_text("300000 100000\n")
    (leaf / "cpu.max").write_text("max 100000\n")
    (v1 / "cpu.cfs_quota_us").write_text("150000\n")
    (v1 / "cpu.cfs_period_us").write_text("100000\n")
    missing = tmp_path / "missing"
    assert _quotas([(2, leaf), (2, tmp_path), (2, missing), (1, v1), (1, missing)]) == [None, 3.0, None, 1.5, None]


@pytest.mark.parametrize(("affinity", "quotas", "budget"), [
    (8, [], 8),
    (8, [None, None], 8),
    (8, [1.5], 2),  # rounded up
    (8, [3.0, None, 1.2], 2),  # the smallest quota binds
    (2, [4.0], 2),  # a quota above the affinity mask does not add CPUs
    (4, [0.2], 1),  # at least one
    (1, [], 1),
])  # fmt: skip
def test_budget_is_the_affinity_capped_by_the_quota(affinity: int, quotas: list[float | None], budget: int) -> None:
    assert budget_from(affinity, quotas, None) == budget


def test_override_wins_and_bad_values_name_the_variable() -> None:
    assert budget_from(2, [1.0], "3") == 3
    assert budget_from(8, [], " 1\n") == 1
    for bad in ["0", "-2", "two", "", "1.5", "2x"]:
        with pytest.raises(InputError, match=THREADS_ENV) as err:
            budget_from(8, [], bad)
        assert repr(bad) in str(err.value)


def test_cpu_budget_of_this_process(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(THREADS_ENV, raising=False)
    n = cpu_budget()
    assert 1 <= n <= len(os.sched_getaffinity(0)) <= (os.cpu_count() or 1)
    assert cpu_budget() == n  # cached
    assert shared.core.cpu_budget is cpu_budget  # exported by the package (lazily)
    assert "cpu_budget" in shared.core.__all__


def test_cpu_budget_reads_the_override_once(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(THREADS_ENV, "5")
    assert cpu_budget() == 5
    monkeypatch.setenv(THREADS_ENV, "7")
    assert cpu_budget() == 5  # cached until cleared
    cpu_budget.cache_clear()
    assert cpu_budget() == 7
    monkeypatch.setenv(THREADS_ENV, "many")
    cpu_budget.cache_clear()
    with pytest.raises(InputError, match=f"^{THREADS_ENV}: .*'many'"):
        cpu_budget()
