"""Schemathesis against the API's own OpenAPI schema, with a valid key: no input it can
generate (within a small, bounded number of examples per operation) makes the API answer 500."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from services.api.app import create_app
from shared.service.jobstore import JobStore
from tests.support import jobsvc

# Schemathesis reads the schema when the module is collected, so the app is built here, in
# a temporary service environment of its own, removed when the module's tests end.
_ROOT = Path(tempfile.mkdtemp(prefix="graylight-schema-"))
_ENV = jobsvc.make_env(_ROOT, GRAYLIGHT_MAX_UPLOAD_BYTES=str(4 << 20))
_KEY = JobStore(_ENV.settings.database_url).create_key("fuzz")[1]
schema = schemathesis.openapi.from_asgi("/openapi.json", create_app(_ENV.settings))


@pytest.fixture(scope="module", autouse=True)
def _cleanup() -> Iterator[None]:
    yield
    jobsvc.cleanup_redis(_ENV.env["GRAYLIGHT_QUEUE_PREFIX"], _ENV.env["GRAYLIGHT_BROKER_URL"])
    shutil.rmtree(_ROOT, ignore_errors=True)


@pytest.mark.slow
@schema.parametrize()
@settings(max_examples=6, deadline=None, database=None, suppress_health_check=list(HealthCheck))
def test_no_server_errors(case) -> None:
    case.call_and_validate(headers={"Authorization": f"Bearer {_KEY}"}, checks=[not_a_server_error])
