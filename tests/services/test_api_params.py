"""Job parameters are checked at intake: a bad one is a 422 naming the field, and nothing is
stored or queued (before, a bad preview size failed the job after decode, triangulate and tiles)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from shared.service.jobstore import JobStore
from tests.support import jobsvc


@pytest.fixture
def client(tmp_path: Path) -> Iterator[tuple[TestClient, dict[str, str], Path]]:
    with jobsvc.service_env(tmp_path) as senv:
        _k, secret = JobStore(senv.settings.database_url).create_key("p")
        cap = jobsvc.simulate_small(tmp_path / "plane")
        archive = jobsvc.capture_zip(cap, tmp_path / "c.zip")
        with TestClient(create_app(senv.settings)) as c:
            yield c, {"Authorization": f"Bearer {secret}"}, archive


@pytest.mark.parametrize(
    ("params", "loc"),
    [
        ({"preview": {"size": [641, 480]}}, ["params", "preview", "size"]),
        ({"preview": {"fps": 0}}, ["params", "preview", "fps"]),
        ({"tiles": {"max_leaf": 3}}, ["params", "tiles", "max_leaf"]),
        ({"rendr": False}, ["params", "rendr"]),
    ],
)
def test_bad_params_are_refused_before_anything_runs(client, params: dict, loc: list[str]) -> None:
    c, auth, archive = client
    r = c.post("/v1/jobs", headers=auth, files={"capture": ("c.zip", archive.read_bytes(), "application/zip")},
               data={"params": json.dumps(params)})  # fmt: skip
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert isinstance(detail, list) and any(d["loc"][-len(loc):] == loc for d in detail), detail
    assert c.get("/v1/jobs", headers=auth).json()["total"] == 0


def test_good_params_make_a_job(client) -> None:
    c, auth, archive = client
    params = {"preview": {"size": [320, 240], "seconds": 1}, "tiles": {"max_leaf": 2000}}
    r = c.post("/v1/jobs", headers=auth, files={"capture": ("c.zip", archive.read_bytes(), "application/zip")},
               data={"params": json.dumps(params)})  # fmt: skip
    assert r.status_code == 201, r.text
    assert c.get("/v1/jobs", headers=auth).json()["total"] == 1
