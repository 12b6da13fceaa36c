"""The job-service API without workers (stages are driven in-process where a test needs
them): keys and isolation, limits, archive checks at intake, resumable uploads, listing,
batches from storage references, cancel and retry semantics, artifacts."""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from shared.service.jobs import graph_for
from shared.service.jobstore import JobStore
from tests.support import inprocess, jobsvc
from tests.support.images import png_bytes


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return jobsvc.simulate_small(tmp_path_factory.mktemp("cap") / "plane")


@pytest.fixture
def api(tmp_path: Path) -> Iterator[tuple[TestClient, jobsvc.ServiceEnv, dict[str, str], dict[str, str]]]:
    with jobsvc.service_env(tmp_path, GRAYLIGHT_MAX_UPLOAD_BYTES=str(8 << 20), GRAYLIGHT_MAX_ARCHIVE_FILES="200",
                            GRAYLIGHT_MAX_IMAGE_PIXELS="1000000") as senv:  # fmt: skip
        store = JobStore(senv.settings.database_url)
        _a, alice = store.create_key("alice")
        _b, bob = store.create_key("bob")
        with TestClient(create_app(senv.settings)) as client:
            yield client, senv, {"Authorization": f"Bearer {alice}"}, {"Authorization": f"Bearer {bob}"}


def problem(r) -> str:
    """The one-line problem of a 422 answer (its list of errors), ``FIELD: MESSAGE``."""
    items = r.json()["detail"]
    assert isinstance(items, list) and items, items
    return "; ".join(".".join(str(p) for p in i["loc"][1:]) + ": " + i["msg"] for i in items)


def zip_of(capture: Path, tmp: Path, **kw) -> Path:
    return jobsvc.capture_zip(capture, tmp / "c.zip", **kw)


def post_zip(client: TestClient, auth: dict[str, str], archive: Path | bytes, name: str = "c.zip", **data: str):
    body = archive.read_bytes() if isinstance(archive, Path) else archive
    return client.post("/v1/jobs", headers=auth, files={"capture": (name, body, "application/zip")}, data=data)


def drive(senv: jobsvc.ServiceEnv, job_id: str, stop_after: str | None = None) -> None:
    """Run the job's queued stages in-process (no broker), optionally stopping after one."""
    inprocess.drive(senv.settings, job_id, stop_after)


def test_health_is_open_everything_else_needs_a_key(api) -> None:
    client, _senv, alice, _bob = api
    h = client.get("/health")
    assert h.status_code == 200 and (h.json()["status"], h.json()["database"], h.json()["problems"]) == ("ok", True, [])
    assert h.json()["free_bytes"] >= h.json()["min_free_bytes"]
    for method, path in [("get", "/v1/jobs"), ("post", "/v1/jobs"), ("get", "/v1/batches"), ("post", "/v1/uploads"),
                         ("get", "/v1/jobs/00000000-0000-0000-0000-000000000000/artifacts/cloud.ply")]:  # fmt: skip
        assert getattr(client, method)(path).status_code == 401
        assert getattr(client, method)(path, headers={"Authorization": "Bearer gl_wrong"}).status_code == 401
    assert client.get("/v1/jobs", headers=alice).status_code == 200
    assert "/v1/jobs" in client.get("/openapi.json").json()["paths"]
    assert client.get("/docs").status_code == 200


def test_each_key_sees_only_its_own_jobs(api, capture: Path, tmp_path: Path) -> None:
    client, _senv, alice, bob = api
    r = post_zip(client, alice, zip_of(capture, tmp_path), params='{"render": false}')
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["state"] == "queued" and [s["name"] for s in job["stages"]] == [s.name for s in graph_for("scan", {"render": False})]
    assert client.get(f"/v1/jobs/{job['id']}", headers=bob).status_code == 404
    assert client.get(f"/v1/jobs/{job['id']}/artifacts", headers=bob).status_code == 404
    assert client.post(f"/v1/jobs/{job['id']}/cancel", headers=bob).status_code == 404
    assert client.get("/v1/jobs", headers=bob).json()["total"] == 0
    assert client.get("/v1/jobs", headers=alice).json()["total"] == 1


def test_archive_checks_before_anything_is_stored(api, capture: Path, tmp_path: Path) -> None:
    client, senv, alice, _bob = api
    store_root = Path(senv.settings.storage_url)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("capture.json", "{}")
        z.writestr("../../evil.png", b"x")
    r = post_zip(client, alice, buf.getvalue(), name="evil.zip")
    assert r.status_code == 422 and problem(r).startswith("evil.zip:../../evil.png: member name contains '..'")
    r = post_zip(client, alice, b"just some bytes", name="junk.zip")
    assert r.status_code == 422 and "junk.zip: not a zip or tar archive" in problem(r)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("capture.json", "{}")
        for i in range(250):
            z.writestr(f"f{i}.txt", "x")
    r = post_zip(client, alice, buf.getvalue(), name="many.zip")
    assert r.status_code == 422 and "more than 200 members" in problem(r)


    big = zip_of(capture, tmp_path, replace={"col_00.png": png_bytes(2000, 2000)})
    r = post_zip(client, alice, big, name="big.zip")
    assert r.status_code == 422 and "big.zip:col_00.png: image is 2000x2000" in problem(r)
    assert not (store_root / "objects").exists()  # nothing was stored for any of them
    assert client.get("/v1/jobs", headers=alice).json()["total"] == 0


def test_upload_size_limit(api) -> None:
    client, _senv, alice, _bob = api
    r = client.post("/v1/jobs", headers=alice, files={"capture": ("big.zip", b"\0" * (10 << 20), "application/zip")})
    assert r.status_code == 413

    def stream():  # chunked, no Content-Length: counted as it arrives
        for _ in range(200):
            yield b"\0" * 65536

    r = client.post("/v1/jobs", headers={**alice, "Content-Type": "multipart/form-data; boundary=b"}, content=stream())
    assert r.status_code == 413 and "limit" in r.json()["detail"]


def test_resumable_upload(api, capture: Path, tmp_path: Path) -> None:
    client, _senv, alice, bob = api
    data = zip_of(capture, tmp_path).read_bytes()
    up = client.post("/v1/uploads", headers=alice, json={"filename": "plane.zip"}).json()
    assert up["offset"] == 0
    url = f"/v1/uploads/{up['id']}"
    half = len(data) // 2
    r = client.patch(url, headers={**alice, "Upload-Offset": "0"}, content=data[:half])
    assert r.status_code == 200 and r.json()["offset"] == half
    # A retried chunk at a stale offset is refused with the offset to resume from.
    r = client.patch(url, headers={**alice, "Upload-Offset": "0"}, content=data[:half])
    assert r.status_code == 409 and str(half) in r.json()["detail"]
    assert client.get(url, headers=bob).status_code == 404
    resume = client.get(url, headers=alice).json()["offset"]
    r = client.patch(url, headers={**alice, "Upload-Offset": str(resume)}, content=data[resume:])
    assert r.json()["offset"] == len(data)
    job = client.post("/v1/jobs", headers=alice, json={"upload_id": up["id"], "params": {"render": False}})
    assert job.status_code == 201, job.text
    assert job.json()["name"] == "plane.zip"
    assert client.post("/v1/jobs", headers=alice, json={"upload_id": up["id"]}).status_code == 409


@pytest.mark.slow
def test_cancel_then_retry_reruns_only_unfinished_stages(api, capture: Path, tmp_path: Path) -> None:
    client, senv, alice, _bob = api
    job = post_zip(client, alice, zip_of(capture, tmp_path), params='{"render": false}').json()
    drive(senv, job["id"], stop_after="ingest")
    r = client.post(f"/v1/jobs/{job['id']}/cancel", headers=alice)
    assert r.json()["state"] == "cancelled"
    states = {s["name"]: s["state"] for s in r.json()["stages"]}
    assert states == {s.name: "succeeded" if s.name == "ingest" else "cancelled" for s in graph_for("scan", {"render": False})}
    assert client.post(f"/v1/jobs/{job['id']}/cancel", headers=alice).status_code == 409
    before = client.get(f"/v1/jobs/{job['id']}", headers=alice).json()["stages"][0]
    r = client.post(f"/v1/jobs/{job['id']}/retry", headers=alice)
    assert r.status_code == 200, r.text
    assert {s["name"]: s["state"] for s in r.json()["stages"]} == {
        s: {"ingest": "succeeded", "decode": "queued"}.get(s, "pending") for s in states
    }
    drive(senv, job["id"])
    done = client.get(f"/v1/jobs/{job['id']}", headers=alice).json()
    assert done["state"] == "succeeded"
    assert done["stages"][0]["finished_at"] == before["finished_at"] and done["stages"][0]["attempts"] == 1
    assert client.post(f"/v1/jobs/{job['id']}/retry", headers=alice).status_code == 409  # nothing changed
    cloud = client.get(f"/v1/jobs/{job['id']}/artifacts/cloud.ply", headers=alice)
    assert cloud.status_code == 200 and cloud.content.startswith(b"ply\n")
    assert cloud.headers["x-checksum-sha256"]
    names = {a["name"] for a in client.get(f"/v1/jobs/{job['id']}/artifacts", headers=alice).json()["artifacts"]}
    assert {"cloud.ply", "triangulate/cloud.ply", "decoded.npz", "range.npz"} <= names
    assert client.get(f"/v1/jobs/{job['id']}/artifacts/nope.bin", headers=alice).status_code == 404
    assert client.get(f"/v1/jobs/{job['id']}/artifacts/triangulate/../../x", headers=alice).status_code == 404


def test_retry_reruns_stages_whose_inputs_changed(api) -> None:
    client, senv, alice, _bob = api
    job = client.post("/v1/jobs", headers=alice, json={"kind": "probe", "params": {"seconds": 0}}).json()
    drive(senv, job["id"])
    first = client.get(f"/v1/jobs/{job['id']}", headers=alice).json()
    assert first["state"] == "succeeded"
    assert client.post(f"/v1/jobs/{job['id']}/retry", headers=alice).status_code == 409
    r = client.post(f"/v1/jobs/{job['id']}/retry", headers=alice, json={"params": {"seconds": 0.01}})
    assert r.status_code == 200 and r.json()["stages"][0]["state"] == "queued"
    drive(senv, job["id"])
    second = client.get(f"/v1/jobs/{job['id']}", headers=alice).json()
    assert second["state"] == "succeeded" and second["stages"][0]["attempts"] == 2
    probe = json.loads(client.get(f"/v1/jobs/{job['id']}/artifacts/probe.json", headers=alice).content)
    assert probe["seconds"] == 0.01


def test_batch_from_storage_references_and_manifest(api, capture: Path, tmp_path: Path) -> None:
    client, senv, alice, bob = api
    root = Path(senv.settings.storage_url)
    inbox = root / "inbox"
    inbox.mkdir(parents=True)
    zip_of(capture, tmp_path, note="a").rename(inbox / "a.zip")
    (inbox / "m.txt").write_text("# museum run\ninbox/a.zip\ninbox/missing.zip\n")
    r = client.post("/v1/batches", headers=alice, json={"name": "museum", "manifest": "inbox/m.txt",
                                                        "captures": ["objects/ab"], "params": {"render": False}})  # fmt: skip
    assert r.status_code == 201, r.text
    b = r.json()
    # Every reference sent is accounted for: the refused ones count, as "rejected" (issue 24).
    assert len(b["jobs"]) == 1 and b["total"] == 3
    assert sorted(x["capture"] for x in b["rejected"]) == ["inbox/missing.zip", "objects/ab"]
    drive(senv, b["jobs"][0])
    prog = client.get(f"/v1/batches/{b['id']}", headers=alice).json()
    assert prog["counts"] == {"succeeded": 1, "rejected": 2} and prog["progress"] == 1.0
    assert client.get(f"/v1/batches/{b['id']}", headers=bob).status_code == 404
    listed = client.get("/v1/jobs", headers=alice, params={"batch": "museum", "state": "succeeded"}).json()
    assert [j["id"] for j in listed["jobs"]] == b["jobs"]
    # A reference works in a multipart form too; the same capture has the same key.
    r = client.post("/v1/jobs", headers=alice, data={"capture_ref": "inbox/a.zip", "params": '{"render": false}'},
                    files={"unused": ("x", b"", "text/plain")})  # fmt: skip
    assert r.status_code == 201 and r.json()["name"] == "a.zip"
    assert client.post("/v1/jobs", headers=alice, json={"capture_ref": "../etc/passwd"}).status_code == 422


def test_listing_pages(api) -> None:
    client, _senv, alice, _bob = api
    ids = [client.post("/v1/jobs", headers=alice, json={"kind": "probe"}).json()["id"] for _ in range(5)]
    p1 = client.get("/v1/jobs", headers=alice, params={"limit": 2}).json()
    assert p1["total"] == 5 and p1["next_offset"] == 2 and [j["id"] for j in p1["jobs"]] == ids[::-1][:2]
    p3 = client.get("/v1/jobs", headers=alice, params={"limit": 2, "offset": 4}).json()
    assert p3["next_offset"] is None and [j["id"] for j in p3["jobs"]] == [ids[0]]
    assert client.get("/v1/jobs", headers=alice, params={"state": "nonsense"}).status_code == 422


def test_viewer_is_mounted(api) -> None:
    client, _senv, _alice, _bob = api
    r = client.get("/viewer/assets/does-not-exist.js")
    assert r.status_code == 404  # the viewer's router answers (no 401: its page carries no secrets)


@pytest.mark.slow
def test_uploaded_rig_replaces_a_missing_one(api, capture: Path, tmp_path: Path) -> None:
    client, senv, alice, _bob = api
    no_rig = jobsvc.capture_zip(capture, tmp_path / "norig.zip", drop=("rig.json",))
    bad = post_zip(client, alice, no_rig, name="norig.zip", params='{"render": false}').json()
    drive(senv, bad["id"])
    failed = client.get(f"/v1/jobs/{bad['id']}", headers=alice).json()
    assert failed["state"] == "failed" and "norig.zip:rig.json" in failed["error"], failed["error"]
    r = client.post("/v1/jobs", headers=alice, data={"params": '{"render": false}'},
                    files={"capture": ("norig.zip", no_rig.read_bytes(), "application/zip"),
                           "rig": ("rig.json", (capture / "rig.json").read_bytes(), "application/json")})  # fmt: skip
    assert r.status_code == 201, r.text
    drive(senv, r.json()["id"])
    assert client.get(f"/v1/jobs/{r.json()['id']}", headers=alice).json()["state"] == "succeeded"
    r = client.post("/v1/jobs", headers=alice, files={"capture": ("norig.zip", no_rig.read_bytes(), "application/zip"),
                                                      "rig": ("rig.json", b'{"units": "mm"}', "application/json")})  # fmt: skip
    assert r.status_code == 422 and problem(r).startswith("rig.json: missing field")


@pytest.mark.slow
def test_calibrate_job(api, tmp_path: Path) -> None:
    from shared.formats.rig import load_rig
    from shared.service.archive import pack_folder
    from shared.sim.calibration import simulate_session

    client, senv, alice, _bob = api
    session = simulate_session(tmp_path / "session", n_poses=5, camera_size=(320, 240), projector_size=(128, 96),
                               seed=1, inverses=False).root  # fmt: skip
    archive = pack_folder(session, tmp_path / "session.zip")
    r = post_zip(client, alice, archive, name="session.zip", kind="calibrate")
    assert r.status_code == 201, r.text
    drive(senv, r.json()["id"])
    job = client.get(f"/v1/jobs/{r.json()['id']}", headers=alice).json()
    assert job["state"] == "succeeded", job
    rig = client.get(f"/v1/jobs/{job['id']}/artifacts/rig.json", headers=alice)
    (tmp_path / "rig.json").write_bytes(rig.content)
    assert load_rig(tmp_path / "rig.json").camera.width == 320
    # A calibration session is not a scan capture (it holds one capture per pose).
    r = post_zip(client, alice, archive, name="session.zip", kind="scan")
    assert r.status_code == 422 and "one capture per archive" in problem(r)


@pytest.mark.slow
def test_artifacts_from_s3_with_ranges(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import uuid

    import boto3

    for k, v in {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}.items():
        monkeypatch.setenv(k, v)
    with jobsvc.moto_server() as endpoint:
        bucket = f"b{uuid.uuid4().hex[:12]}"
        boto3.client("s3", endpoint_url=endpoint).create_bucket(Bucket=bucket)
        with jobsvc.service_env(tmp_path, GRAYLIGHT_STORAGE_URL=f"s3://{bucket}/gl", GRAYLIGHT_S3_ENDPOINT=endpoint) as senv:
            key = JobStore(senv.settings.database_url).create_key("s3")[1]
            auth = {"Authorization": f"Bearer {key}"}
            client = TestClient(create_app(senv.settings))
            job = client.post("/v1/jobs", headers=auth, json={"kind": "probe", "params": {"seconds": 0}}).json()
            drive(senv, job["id"])
            url = f"/v1/jobs/{job['id']}/artifacts/probe.json"
            whole = client.get(url, headers=auth)
            assert whole.status_code == 200 and json.loads(whole.content)["job"] == job["id"]
            part = client.get(url, headers={**auth, "Range": "bytes=2-9"})
            assert part.status_code == 206 and part.content == whole.content[2:10]
            assert part.headers["content-range"] == f"bytes 2-9/{len(whole.content)}"
            tail = client.get(url, headers={**auth, "Range": "bytes=-5"})
            assert tail.content == whole.content[-5:]
            assert client.get(url, headers={**auth, "Range": f"bytes={len(whole.content)}-"}).status_code == 416


def test_cli_client_uploads_in_chunks_and_resumes(api, capture: Path, tmp_path: Path) -> None:
    from services.cli.jobs import Client

    client, _senv, alice, _bob = api
    key = alice["Authorization"].split()[1]
    cli = Client(url="http://testserver", key=key, http=client)
    archive = zip_of(capture, tmp_path)
    job = cli.submit_archive(archive, "plane.zip", params={"render": False}, session_threshold=0, chunk=100_000)
    assert job["state"] == "queued" and job["name"] == "plane.zip"
    # An interrupted upload (first chunk only) is resumed from the server's offset.
    data = archive.read_bytes()
    up = client.post("/v1/uploads", headers=alice, json={"filename": "again.zip"}).json()
    client.patch(f"/v1/uploads/{up['id']}", headers={**alice, "Upload-Offset": "0"}, content=data[:70_000])
    assert cli.upload(archive, "again.zip", chunk=100_000, resume=up["id"]) == up["id"]
    assert client.get(f"/v1/uploads/{up['id']}", headers=alice).json()["offset"] == len(data)
    again = client.post("/v1/jobs", headers=alice, json={"upload_id": up["id"], "params": {"render": False}})
    assert again.status_code == 201 and again.json()["name"] == "again.zip"


def test_error_answers_have_the_documented_shapes(api) -> None:
    client, _senv, alice, _bob = api
    r = client.delete("/v1/jobs", headers=alice)
    assert r.status_code == 405 and r.headers["allow"] == "GET, POST"  # both routes of the path
    r = client.put("/v1/uploads/00000000-0000-0000-0000-000000000000", headers=alice)
    assert r.status_code == 405 and r.headers["allow"] == "GET, PATCH"
    r = client.post("/v1/jobs", headers=alice, json={"kind": "probe", "params": {"seconds": 99}})
    assert r.status_code == 422
    [item] = r.json()["detail"]
    assert item["loc"] == ["body", "params", "seconds"] and "0..60" in item["msg"] and item["type"] == "value_error"
    r = client.post("/v1/batches", headers=alice, json={"name": ""})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "name"]
    r = client.post("/v1/batches", headers=alice, data={"name": "x", "params": "{nope"},
                    files={"unused": ("x", b"", "text/plain")})  # fmt: skip
    assert r.status_code == 422 and problem(r).startswith("params: malformed JSON")
    r = client.post("/v1/jobs", headers=alice, json={"capture_ref": "inbox/none.zip"})
    assert r.status_code == 404 and "no such file or folder in storage" in r.json()["detail"]
    doc = client.get("/openapi.json").json()
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            if path.startswith("/v1/") and "{token}" in path:
                # A scene's files are authorised by the signed token in their path (Voyager sends no
                # header): a bad token is 403, never 401.
                assert {"403", "422"} <= set(op["responses"]), (method, path)
            elif path.startswith("/v1/"):
                assert {"401", "422"} <= set(op["responses"]), (method, path)
