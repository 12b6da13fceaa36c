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


@pytest.fixture
def pg_env(tmp_path: Path) -> Iterator[jobsvc.ServiceEnv]:
    """A job-service environment whose job store is the real PostgreSQL: a database of the test's
    own (dropped after), as its SQLite file is. One database for the session let a test's rows count
    in another's: the capture size test_service's API records for the small capture counted in
    test_keep_range's stored bytes when it ran after it on the same xdist worker."""
    with jobsvc.pg_database() as url, jobsvc.service_env(tmp_path, GRAYLIGHT_DATABASE_URL=url) as senv:
        yield senv
