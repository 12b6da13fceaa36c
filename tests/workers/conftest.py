"""Fixtures of the job-service tests (helpers in :mod:`tests.support.jobsvc`)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.support import jobsvc


@pytest.fixture(scope="session")
def small_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return jobsvc.simulate_small(tmp_path_factory.mktemp("capture") / "plane")


@pytest.fixture
def svc_env(tmp_path: Path) -> Iterator[jobsvc.ServiceEnv]:
    with jobsvc.service_env(tmp_path) as senv:
        yield senv


@pytest.fixture(scope="session")
def moto_endpoint() -> Iterator[str]:
    with jobsvc.moto_server() as url:
        yield url


@pytest.fixture
def redis_server(tmp_path: Path) -> Iterator[Any]:
    with jobsvc.private_redis(tmp_path) as ctl:
        yield ctl


@pytest.fixture(scope="session")
def pg_url() -> Iterator[str]:
    """A PostgreSQL database for this session (dropped after)."""
    with jobsvc.pg_database() as url:
        yield url


@pytest.fixture
def pg_env(tmp_path: Path, pg_url: str) -> Iterator[jobsvc.ServiceEnv]:
    """A job-service environment whose job store is the real PostgreSQL."""
    with jobsvc.service_env(tmp_path, GRAYLIGHT_DATABASE_URL=pg_url) as senv:
        yield senv
