"""Helpers for the job-service tests: real Redis, real PostgreSQL, real worker processes.

Each test gets its own data folder, SQLite file (or PostgreSQL database), artifact store
and queue-name prefix on Redis database 11, so parallel runs never share a queue. The
context managers here back the fixtures of ``tests/workers/conftest.py`` and of the test
modules elsewhere that need them.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import time
import uuid
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from shared.service.config import Settings, get_settings

REPO = Path(__file__).resolve().parents[2]
GRAYLIGHT = str(REPO / ".venv" / "bin" / "graylight")
TEST_REDIS = os.environ.get("GRAYLIGHT_TEST_REDIS", "redis://127.0.0.1:6379/11")
PG_ADMIN = os.environ.get("GRAYLIGHT_TEST_PG", "postgresql://postgres@127.0.0.1:5432/postgres")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class ServiceEnv:
    """Environment of one test's job service."""

    root: Path
    env: dict[str, str]
    procs: list[Proc] = field(default_factory=list)

    @property
    def settings(self) -> Settings:
        return get_settings(self.env)

    def with_(self, **overrides: str) -> ServiceEnv:
        return ServiceEnv(self.root, {**self.env, **overrides}, self.procs)


def make_env(root: Path, database_url: str | None = None, broker_url: str = TEST_REDIS, **extra: str) -> ServiceEnv:
    root.mkdir(parents=True, exist_ok=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith("GRAYLIGHT_")}
    env.update(
        GRAYLIGHT_DATA_DIR=str(root / "data"),
        GRAYLIGHT_BROKER_URL=broker_url,
        GRAYLIGHT_QUEUE_PREFIX=f"t{uuid.uuid4().hex[:10]}.",
        GRAYLIGHT_LEASE_SECONDS="3",
        GRAYLIGHT_HEARTBEAT_SECONDS="0.3",
        GRAYLIGHT_RECONCILE_SECONDS="1",
        GRAYLIGHT_WORKER_MAX_MEMORY_MB="2048",
        PYTHONUNBUFFERED="1",
    )
    if database_url:
        env["GRAYLIGHT_DATABASE_URL"] = database_url
    env.update(extra)
    return ServiceEnv(root, env)


@dataclass
class Proc:
    """A service process started for a test (its own session, so its children die with it)."""

    popen: subprocess.Popen
    log: Path
    name: str

    def text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def kill9(self) -> None:
        """SIGKILL the whole process group: the worker and its pool children, no goodbye."""
        try:
            os.killpg(self.popen.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.popen.wait(timeout=10)

    def stop(self, timeout: float = 15) -> None:
        stop_all([self], timeout)


def stop_all(procs: list[Proc], timeout: float = 15) -> None:
    """Stop ``procs`` together, each as :meth:`Proc.stop` does: SIGTERM to every main process
    first, then wait for each (its group SIGKILLed past ``timeout``). A Celery worker's warm
    shutdown takes about 2 s (its pool child, then its consumer's threads); one process after
    the other, a test's teardown waited for the sum."""
    live = [p for p in procs if p.popen.poll() is None]
    for p in live:
        try:
            # Only the main process: a Celery worker then shuts down warmly (finishes its
            # running task, hands prefetched messages back) and stops its own children.
            os.kill(p.popen.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    deadline = time.monotonic() + timeout
    for p in live:
        try:
            p.popen.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill9()


def _spawn(senv: ServiceEnv, args: list[str], name: str) -> Proc:
    log = senv.root / f"{name}-{len(senv.procs)}.log"
    fh = open(log, "wb")
    popen = subprocess.Popen([GRAYLIGHT, *args], env=senv.env, stdout=fh, stderr=subprocess.STDOUT,
                             start_new_session=True, cwd=senv.root)  # fmt: skip
    fh.close()
    proc = Proc(popen, log, name)
    senv.procs.append(proc)
    return proc


def wait_for(cond: Callable[[], object], timeout: float, what: str, proc: Proc | None = None, interval: float = 0.05) -> object:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        if proc is not None and proc.popen.poll() is not None:
            raise AssertionError(f"{proc.name} exited ({proc.popen.returncode}) waiting for {what}:\n{proc.text()[-3000:]}")
        time.sleep(interval)
    tail = f"\n{proc.name} log:\n{proc.text()[-3000:]}" if proc else ""
    raise AssertionError(f"timed out after {timeout} s waiting for {what}{tail}")


def start_worker(senv: ServiceEnv, queues: str = "cpu,render", concurrency: int = 1) -> Proc:
    p = _spawn(senv, ["-v", "worker", "--queues", queues, "--concurrency", str(concurrency), "--loglevel", "INFO"], "worker")
    wait_for(lambda: " ready." in p.text(), 90, "worker ready", p, interval=0.2)
    return p


def start_beat(senv: ServiceEnv) -> Proc:
    p = _spawn(senv, ["beat", "--loglevel", "INFO"], "beat")
    wait_for(lambda: "beat: Starting" in p.text() or "Scheduler: Sending" in p.text(), 60, "beat started", p, interval=0.2)
    return p


def start_api(senv: ServiceEnv, port: int | None = None) -> tuple[Proc, str]:
    import httpx

    port = port or free_port()
    p = _spawn(senv, ["serve", "--host", "127.0.0.1", "--port", str(port)], "api")
    url = f"http://127.0.0.1:{port}"

    def up() -> bool:
        try:
            return httpx.get(f"{url}/health", timeout=1).status_code == 200
        except httpx.HTTPError:
            return False

    wait_for(up, 60, "API up", p, interval=0.2)
    return p, url


@contextlib.contextmanager
def tmpfs(mnt: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` (``64m``) mounted at the new folder ``mnt`` for a test (root only;
    the test is skipped where mounting is not allowed), unmounted after."""
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


@contextlib.contextmanager
def pg_database() -> Iterator[str]:
    """A fresh PostgreSQL database for this test session, dropped at the end."""
    import psycopg

    name = f"graylight_test_{uuid.uuid4().hex[:12]}"
    try:
        admin = psycopg.connect(PG_ADMIN, autocommit=True, connect_timeout=5)
    except psycopg.OperationalError as exc:
        pytest.fail(f"PostgreSQL is not reachable at {PG_ADMIN}: {exc}")
    admin.execute(f'CREATE DATABASE "{name}"')
    try:
        yield PG_ADMIN.rsplit("/", 1)[0].replace("postgresql://", "postgresql+psycopg://") + f"/{name}"
    finally:
        from shared.service.jobstore import dispose_engines

        dispose_engines()
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.close()


def cleanup_redis(prefix: str, url: str) -> None:
    import redis

    try:
        r = redis.Redis.from_url(url, socket_timeout=2)
        for k in r.scan_iter(match=f"{prefix}*", count=500):
            r.delete(k)
        for k in r.scan_iter(match=f"_kombu.binding.{prefix}*", count=500):
            r.delete(k)
        r.close()
    except Exception:
        pass


@contextlib.contextmanager
def service_env(tmp_path: Path, **extra: str) -> Iterator[ServiceEnv]:
    """A job-service environment on SQLite; its processes are stopped and its queues deleted after."""
    senv = make_env(tmp_path / "svc", **extra)
    try:
        yield senv
    finally:
        stop_all(senv.procs)
        cleanup_redis(senv.env["GRAYLIGHT_QUEUE_PREFIX"], senv.env["GRAYLIGHT_BROKER_URL"])


def simulate_small(out: Path) -> Path:
    """A small simulated capture (plane, 160x120 camera, 64x48 projector) with its rig."""
    from shared.sim.simulate import simulate_named

    simulate_named("plane", out, size=(160, 120), projector=(64, 48), seed=3)
    return out


@contextlib.contextmanager
def moto_server() -> Iterator[str]:
    """moto's S3 server on a free loopback port; yields its endpoint URL."""
    from moto.server import ThreadedMotoServer

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.stop()


def capture_zip(folder: Path, out: Path, note: str | None = None, drop: tuple[str, ...] = (),
                replace: dict[str, bytes] | None = None) -> Path:  # fmt: skip
    """Zip a capture folder; ``note`` adds a distinct file (a distinct capture key), ``drop``
    leaves files out and ``replace`` swaps their bytes (broken captures)."""
    replace = replace or {}
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as z:
        for p in sorted(folder.rglob("*")):
            rel = p.relative_to(folder).as_posix()
            if not p.is_file() or rel in drop or rel == "truth.npz":
                continue
            if rel in replace:
                z.writestr(rel, replace[rel])
            else:
                z.write(p, rel)
        if note is not None:
            z.writestr("note.txt", note)
    return out


@contextlib.contextmanager
def private_redis(tmp_path: Path) -> Iterator[Any]:
    """Start (and restart) a private redis-server on a free port; yields a controller."""

    class Ctl:
        port = free_port()
        proc: subprocess.Popen | None = None

        @property
        def url(self) -> str:
            return f"redis://127.0.0.1:{self.port}/0"

        def start(self) -> None:
            self.proc = subprocess.Popen(
                ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                 "--dir", str(tmp_path)],  # fmt: skip
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
            )
            import redis

            wait_for(lambda: _ping(redis, self.url), 20, "redis-server up")

        def stop(self) -> None:
            if self.proc is not None and self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait(timeout=10)

    ctl = Ctl()
    ctl.start()
    try:
        yield ctl
    finally:
        ctl.stop()


def _ping(redis_mod: object, url: str) -> bool:
    try:
        return bool(redis_mod.Redis.from_url(url, socket_timeout=0.5).ping())  # type: ignore[attr-defined]
    except Exception:
        return False
