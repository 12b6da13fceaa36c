"""A command's wall time, CPU time and peak memory, measured apart from the bench's own process.

Linux carries a process's peak resident size across ``execve``: a child forked (or vforked) by
a bench process that holds 3 GB reports a peak of at least 3 GB, whatever the command itself
used (measured: ``/bin/true`` from a Python holding 2 GB reports 1.93 GB). The bench's parent
has grown large by the time a later section runs, so :func:`run_graylight` starts the command
from a small spawner process (a fresh interpreter importing nothing but ``os``/``sys``/``time``),
which times it, waits for it and hands back its own rusage.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# Runs the command given as its arguments (stdout/stderr inherited), waits with wait4 and
# writes {"status", "wall", "cpu", "maxrss_kb"} to the file named by GRAYLIGHT_BENCH_USAGE.
_SPAWNER = """
import json, os, sys, time
t0 = time.perf_counter()
pid = os.posix_spawnp(sys.argv[1], sys.argv[1:], os.environ)
_, status, u = os.wait4(pid, 0)
wall = time.perf_counter() - t0
with open(os.environ["GRAYLIGHT_BENCH_USAGE"], "w") as f:
    json.dump({"status": os.waitstatus_to_exitcode(status), "wall": wall,
               "cpu": u.ru_utime + u.ru_stime, "maxrss_kb": u.ru_maxrss}, f)
"""


@dataclass(frozen=True)
class ChildRun:
    """wall and cpu (user + system of the command and its children) in seconds, peak resident
    memory in GB (the command's own), its exit code and output."""

    wall: float
    cpu: float
    peak_gb: float
    returncode: int
    stdout: str
    stderr: str


def run_measured(cmd: list[str], env: dict[str, str] | None = None) -> ChildRun:
    """Run ``cmd`` (a program and its arguments) from the small spawner and measure it."""
    os.sync()  # no run pays for the writeback of the one before
    with tempfile.TemporaryDirectory(prefix="graylight-bench-child-") as tmp:
        usage_file = Path(tmp) / "usage.json"
        child_env = dict(os.environ if env is None else env, GRAYLIGHT_BENCH_USAGE=str(usage_file))
        res = subprocess.run([sys.executable, "-S", "-c", _SPAWNER, *cmd], capture_output=True, text=True,
                             env=child_env)  # fmt: skip
        if res.returncode != 0 or not usage_file.is_file():
            raise RuntimeError(f"{Path(cmd[0]).name} could not be run: {res.stderr.strip()[-500:]}")
        usage = json.loads(usage_file.read_text())
    return ChildRun(usage["wall"], usage["cpu"], usage["maxrss_kb"] / 1024**2, usage["status"], res.stdout, res.stderr)


def run_graylight(args: list[str], env: dict[str, str] | None = None) -> ChildRun:
    """``graylight ARGS`` measured by :func:`run_measured`; a failure raises with its last error lines."""
    exe = REPO / ".venv" / "bin" / "graylight"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "services.cli.main"]
    run = run_measured([*cmd, *args], env)
    if run.returncode != 0:
        raise RuntimeError(f"graylight {args[0]} failed: {run.stderr.strip()[-500:]}")
    return run
