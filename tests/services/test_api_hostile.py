"""A hostile tenant at the API (issue 21, findings 3, 4 and 6, and the documented answers of
finding 9): a decompression bomb of many small members, deeply nested JSON everywhere the
service parses JSON, a JSON body far over its limit, long inputs that must not be echoed, and
Range headers the API does not serve. Real database, Redis, API process and runner."""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from services.api.models import ARTIFACT_MEDIA_TYPES
from shared.core.errors import InputError
from shared.service.archive import ArchiveLimits, extract_archive
from shared.service.jobstore import JobStore
from tests.support import inprocess, jobsvc
from tests.support.hostile import deep_json, many_member_bomb, process_rss, stream_body


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return jobsvc.simulate_small(tmp_path_factory.mktemp("cap") / "plane")


@pytest.fixture
def api(tmp_path: Path) -> Iterator[tuple[TestClient, jobsvc.ServiceEnv, dict[str, str]]]:
    with jobsvc.service_env(tmp_path) as senv:
        key = JobStore(senv.settings.database_url).create_key("mallory")[1]
        with TestClient(create_app(senv.settings)) as client:
            yield client, senv, {"Authorization": f"Bearer {key}"}


def _objects(senv: jobsvc.ServiceEnv) -> list[Path]:
    root = Path(senv.settings.storage_url) / "objects"
    return sorted(p for p in root.glob("*/*")) if root.is_dir() else []


def _one_problem(r) -> tuple[list, str]:
    assert r.status_code == 422, (r.status_code, r.text[:300])
    [item] = r.json()["detail"]
    return item["loc"], item["msg"]


# ---- finding 3: a bomb of many small members ----------------------------------------------------
def test_bomb_of_many_small_members_is_refused_at_intake(api, tmp_path: Path) -> None:
    client, senv, auth = api
    bomb = many_member_bomb(tmp_path / "bomb.zip", members=4095, extra={"capture.json": b"{}"})
    assert bomb.stat().st_size < 6 << 20  # 4 GiB of zeros in a few MB, as in the finding
    for path in ("/v1/jobs", "/v1/batches"):
        r = client.post(path, headers=auth, data={"name": "b"}, files=[("capture" if path == "/v1/jobs" else "captures",
                        ("bomb.zip", bomb.read_bytes(), "application/zip"))])  # fmt: skip
        text = r.text
        assert r.status_code in (201, 413, 422), text[:300]
        if path == "/v1/batches":
            assert r.status_code == 201 and r.json()["jobs"] == [], text[:300]
            text = r.json()["rejected"][0]["error"]
        assert "GRAYLIGHT_MAX_COMPRESSION_RATIO" in text and "bomb.zip" in text, text[:300]
    assert _objects(senv) == []  # nothing stored, so nothing for a worker to unpack
    assert client.get("/v1/jobs", headers=auth).json()["total"] == 0
    assert not (senv.settings.cache_dir / "captures").exists()


def test_an_archive_that_inflates_past_its_headers_is_stopped(tmp_path: Path) -> None:
    # Each header claims 1 kB; each member inflates to 1 MiB: the claimed total passes every check.
    liar = many_member_bomb(tmp_path / "liar.zip", members=64, declared=1000, extra={"capture.json": b"{}"})
    with pytest.raises(InputError) as err:
        extract_archive(liar, tmp_path / "out", ArchiveLimits())
    assert "liar.zip" in str(err.value)
    assert not (tmp_path / "out").exists() and [p.name for p in tmp_path.iterdir()] == ["liar.zip"]


# ---- finding 4: deeply nested JSON ------------------------------------------------------------
def test_deeply_nested_json_is_a_422_everywhere(api, capture: Path, tmp_path: Path) -> None:
    client, senv, auth = api
    deep = deep_json(10_000)
    archive = jobsvc.capture_zip(capture, tmp_path / "c.zip")
    cases = [
        ("/v1/jobs", {"data": {"params": deep}, "files": {"capture": ("c.zip", archive.read_bytes(), "application/zip")}}),
        ("/v1/batches", {"data": {"name": "b", "params": deep},
                         "files": [("captures", ("c.zip", archive.read_bytes(), "application/zip"))]}),
        ("/v1/jobs", {"files": {"capture": ("c.zip", archive.read_bytes(), "application/zip"),
                                "rig": ("myrig.json", deep.encode(), "application/json")}}),
        ("/v1/jobs", {"content": deep, "headers": {"Content-Type": "application/json"}}),
        ("/v1/batches", {"content": '{"name": "b", "params": ' + deep + "}", "headers": {"Content-Type": "application/json"}}),
        ("/v1/uploads", {"content": deep, "headers": {"Content-Type": "application/json"}}),
    ]  # fmt: skip
    for path, kw in cases:
        headers = {**auth, **kw.pop("headers", {})}
        loc, msg = _one_problem(client.post(path, headers=headers, **kw))
        assert "JSON nested 100" in msg and "levels deep (at most 64)" in msg, (path, loc, msg)
        assert loc in (["body"], ["body", "params"], ["body", "myrig.json"]), (path, loc)
    # A rig over the 1 MiB bound is refused as too large, never cut and then called malformed.
    big = b'{"pad": "' + b"x" * (1 << 20) + b'"}'
    loc, msg = _one_problem(client.post("/v1/jobs", headers=auth, files={
        "capture": ("c.zip", archive.read_bytes(), "application/zip"), "rig": ("big.json", big, "application/json")}))
    assert loc == ["body", "big.json"] and "too large" in msg and str(len(big)) in msg, msg
    assert _objects(senv) == [] and client.get("/v1/jobs", headers=auth).json()["total"] == 0
    # Inside an archive: the job fails naming the file, never with a bare RecursionError.
    bad = tmp_path / "deep.zip"
    with zipfile.ZipFile(archive) as src, zipfile.ZipFile(bad, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            dst.writestr(info, deep.encode() if info.filename.endswith("capture.json") else data)
    r = client.post("/v1/jobs", headers=auth, files={"capture": ("deep.zip", bad.read_bytes(), "application/zip")})
    assert r.status_code == 201, r.text
    inprocess.drive(senv.settings, r.json()["id"])
    job = client.get(f"/v1/jobs/{r.json()['id']}", headers=auth).json()
    assert job["state"] == "failed" and "capture.json" in job["error"] and "nested" in job["error"], job["error"]
    assert "Recursion" not in job["error"]


# ---- finding 6: a JSON body far over the limit ------------------------------------------------------
@pytest.mark.slow
def test_json_body_is_refused_before_it_is_held(tmp_path: Path) -> None:
    with jobsvc.service_env(tmp_path) as senv:
        key = JobStore(senv.settings.database_url).create_key("k")[1]
        proc, url = jobsvc.start_api(senv)
        auth = {"Authorization": f"Bearer {key}"}
        before = process_rss(proc.popen.pid)
        for path in ("/v1/jobs", "/v1/uploads"):
            status, body, sent = stream_body(url, path, auth, total=300 << 20)
            assert status == 413, (path, status, body[:300])
            assert "JSON request body larger than the limit of 4194304 bytes" in body.decode(), body[:300]
            assert sent < 300 << 20  # the API stopped reading long before the end
        grown = process_rss(proc.popen.pid) - before
        assert grown < 48 << 20, f"the API grew by {grown >> 20} MiB for refused bodies"


# ---- documented answers: no echo of long inputs, one shape ------------------------------------------
def test_long_inputs_are_not_echoed(api) -> None:
    client, _senv, auth = api
    huge = "x" * 1_000_000
    answers = [
        client.post("/v1/uploads", headers=auth, json={"filename": huge}),
        client.post("/v1/jobs", headers=auth, data={"capture_ref": huge}, files={"unused": ("u", b"", "text/plain")}),
        client.post("/v1/jobs", headers=auth, json={"capture_ref": huge}),
        client.post("/v1/batches", headers=auth, json={"name": "echo", "captures": [huge]}),
        client.get("/v1/jobs", headers=auth, params={"batch": "y" * 4000}),
    ]
    for r in answers:
        # 400: a form part over the multipart parser's 64 KiB bound, named, not echoed.
        assert r.status_code in (400, 422) and len(r.content) < 2000, (r.status_code, len(r.content))
        detail = r.json()["detail"]
        assert isinstance(detail, str) if r.status_code == 400 else all({"loc", "msg", "type"} == set(i) for i in detail)
    assert client.get("/v1/batches", headers=auth).json() == []  # the refused batch was not created


@pytest.mark.parametrize("store", ["local", "s3"])
def test_unknown_range_units_are_ignored_alike(store: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import contextlib
    import uuid

    extra: dict[str, str] = {}
    with contextlib.ExitStack() as stack:
        if store == "s3":
            import boto3

            for k, v in {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}.items():
                monkeypatch.setenv(k, v)
            endpoint = stack.enter_context(jobsvc.moto_server())
            bucket = f"b{uuid.uuid4().hex[:12]}"
            boto3.client("s3", endpoint_url=endpoint).create_bucket(Bucket=bucket)
            extra = {"GRAYLIGHT_STORAGE_URL": f"s3://{bucket}/gl", "GRAYLIGHT_S3_ENDPOINT": endpoint}
        senv = stack.enter_context(jobsvc.service_env(tmp_path, **extra))
        auth = {"Authorization": f"Bearer {JobStore(senv.settings.database_url).create_key('r')[1]}"}
        client = stack.enter_context(TestClient(create_app(senv.settings)))
        job = client.post("/v1/jobs", headers=auth, json={"kind": "probe", "params": {"seconds": 0}}).json()
        inprocess.drive(senv.settings, job["id"])
        url = f"/v1/jobs/{job['id']}/artifacts/probe.json"
        whole = client.get(url, headers=auth)
        assert whole.status_code == 200 and whole.headers["content-type"].startswith("application/json")
        for rng in ("items=0-9", "bytes=0-1,4-5", "bytes=9-2", "bytes=-", "bytes=abc"):
            r = client.get(url, headers={**auth, "Range": rng})
            assert (r.status_code, r.content) == (200, whole.content), (store, rng, r.status_code, r.text[:200])
        part = client.get(url, headers={**auth, "Range": "bytes=0-9"})
        assert (part.status_code, part.content) == (206, whole.content[:10])
        outside = client.get(url, headers={**auth, "Range": f"bytes={len(whole.content)}-"})
        assert outside.status_code == 416 and "outside the file" in outside.json()["detail"], outside.text


def test_every_served_media_type_is_documented(api) -> None:
    client, _senv, _auth = api
    op = client.get("/openapi.json").json()["paths"]["/v1/jobs/{job_id}/artifacts/{name}"]["get"]
    for status in ("200", "206"):
        assert set(ARTIFACT_MEDIA_TYPES.values()) | {"application/octet-stream"} <= set(op["responses"][status]["content"])
    assert json.loads(io.BytesIO(client.get("/health").content).read())["free_bytes"] > 0
