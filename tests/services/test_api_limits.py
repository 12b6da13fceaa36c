"""A key's limits under a race, a full data folder, and a worker's unpacked captures (issue 21,
findings 3, 5 and 7), against a live API process (real concurrency), Redis, SQLite and
PostgreSQL, a tmpfs that really fills, and a real worker."""

from __future__ import annotations

import shutil
import threading
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from shared.service.jobstore import JobStore
from tests.support import jobsvc

RACERS = 12


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return jobsvc.simulate_small(tmp_path_factory.mktemp("cap") / "plane")


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request: pytest.FixtureRequest) -> Iterator[str | None]:
    if request.param == "sqlite":
        yield None
    else:
        with jobsvc.pg_database() as url:
            yield url


def _race(url: str, requests: list[dict]) -> list[httpx.Response]:
    """Send every request at once (threads released together), each on its own connection."""
    gate = threading.Barrier(len(requests))
    out: list[httpx.Response | BaseException] = [None] * len(requests)  # type: ignore[list-item]

    def go(i: int) -> None:
        with httpx.Client(base_url=url, timeout=120) as c:
            gate.wait()
            try:
                out[i] = c.post(**requests[i])
            except BaseException as exc:  # reported below
                out[i] = exc

    threads = [threading.Thread(target=go, args=(i,)) for i in range(len(requests))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(180)
    assert all(isinstance(r, httpx.Response) for r in out), out
    return out  # type: ignore[return-value]


def _stored_objects(senv: jobsvc.ServiceEnv) -> set[str]:
    root = Path(senv.settings.storage_url) / "objects"
    return {p.name for p in root.glob("*/*")} if root.is_dir() else set()


@pytest.mark.slow
def test_running_jobs_limit_holds_under_a_race(database: str | None, capture: Path, tmp_path: Path) -> None:
    archives = [jobsvc.capture_zip(capture, tmp_path / f"c{i}.zip", note=str(i)).read_bytes() for i in range(RACERS)]
    senv = jobsvc.make_env(tmp_path / "svc", database_url=database, GRAYLIGHT_KEY_MAX_RUNNING_JOBS="1")
    try:
        store = JobStore(senv.settings.database_url)
        keys = {n: {"Authorization": f"Bearer {store.create_key(n)[1]}"} for n in ("json", "form", "batch", "retry")}
        inbox = Path(senv.settings.storage_url) / "inbox"
        inbox.mkdir(parents=True)
        (inbox / "cap.zip").write_bytes(archives[0])
        _proc, url = jobsvc.start_api(senv)
        # JSON submissions (no worker runs: the winner stays queued and holds the one slot).
        answers = _race(url, [{"url": "/v1/jobs", "headers": keys["json"], "json": {"kind": "probe"}}] * RACERS)
        assert sorted(r.status_code for r in answers) == [201] + [429] * (RACERS - 1), [r.text[:200] for r in answers]
        assert all("GRAYLIGHT_KEY_MAX_RUNNING_JOBS" in r.json()["detail"] and r.headers["retry-after"]
                   for r in answers if r.status_code == 429)  # fmt: skip
        # Multipart submissions with captures: one stored, the others' archives taken back.
        answers = _race(url, [{"url": "/v1/jobs", "headers": keys["form"], "data": {"params": '{"render": false}'},
                               "files": {"capture": (f"c{i}.zip", a, "application/zip")}}
                              for i, a in enumerate(archives)])  # fmt: skip
        assert sorted(r.status_code for r in answers) == [201] + [429] * (RACERS - 1), [r.text[:200] for r in answers]
        [won] = [r.json() for r in answers if r.status_code == 201]
        won_key = store.get_job(won["id"]).capture_key
        assert _stored_objects(senv) == {won_key}  # nothing of the refused submissions is stored
        # Batches of one: the whole batch or nothing, and no empty batch left by a loser.
        answers = _race(url, [{"url": "/v1/batches", "headers": keys["batch"],
                               "json": {"name": f"b{i}", "kind": "probe", "captures": ["inbox/cap.zip"]}}
                              for i in range(RACERS)])  # fmt: skip
        assert sorted(r.status_code for r in answers) == [201] + [429] * (RACERS - 1), [r.text[:200] for r in answers]
        for name, auth in keys.items():
            if name == "retry":
                continue
            with httpx.Client(base_url=url, headers=auth) as c:
                assert c.get("/v1/jobs").json()["total"] == 1, name
                assert len(c.get("/v1/batches").json()) == (1 if name == "batch" else 0)
        # Retries: twelve cancelled jobs of one key retried at once, one at a time allowed back in.
        with httpx.Client(base_url=url, headers=keys["retry"]) as c:
            ids = []
            for _ in range(RACERS):
                made = c.post("/v1/jobs", json={"kind": "probe"})
                assert made.status_code == 201, made.text[:200]
                ids.append(made.json()["id"])
                assert c.post(f"/v1/jobs/{ids[-1]}/cancel").status_code == 200
        answers = _race(url, [{"url": f"/v1/jobs/{i}/retry", "headers": keys["retry"]} for i in ids])
        assert sorted(r.status_code for r in answers) == [200] + [429] * (RACERS - 1), [r.text[:200] for r in answers]
        states = sorted(store.get_job(i).state for i in ids)
        assert states == ["cancelled"] * (RACERS - 1) + ["queued"], states
    finally:
        jobsvc.stop_all(senv.procs)
        jobsvc.cleanup_redis(senv.env["GRAYLIGHT_QUEUE_PREFIX"], senv.env["GRAYLIGHT_BROKER_URL"])


# ---- finding 7: a full data folder ------------------------------------------------------------------
@pytest.fixture
def small_tmpfs(tmp_path: Path) -> Iterator[Path]:
    """A 32 MiB tmpfs mounted for the test (root only)."""
    with jobsvc.tmpfs(tmp_path / "tmpfs", "32m") as mnt:
        yield mnt


def _fill(folder: Path) -> Path:
    """Fill ``folder``'s filesystem to the last byte with one file."""
    filler = folder / "filler"
    with open(filler, "wb", buffering=0) as f:
        for block in (1 << 20, 4096, 1):
            try:
                while True:
                    f.write(bytes(block))
            except OSError:
                pass
    return filler


def test_full_data_folder_is_507_and_leaves_nothing(capture: Path, tmp_path: Path, small_tmpfs: Path) -> None:
    archive = jobsvc.capture_zip(capture, tmp_path / "c.zip").read_bytes()
    with jobsvc.service_env(tmp_path, GRAYLIGHT_DATA_DIR=str(small_tmpfs / "data"),
                            GRAYLIGHT_MIN_FREE_BYTES=str(1 << 20)) as senv:  # fmt: skip
        auth = {"Authorization": f"Bearer {JobStore(senv.settings.database_url).create_key('k')[1]}"}
        with TestClient(create_app(senv.settings)) as client:
            h = client.get("/health")
            assert h.status_code == 200 and h.json()["free_bytes"] > 1 << 20
            up = client.post("/v1/uploads", headers=auth, json={"filename": "c.zip"}).json()
            filler = _fill(small_tmpfs)
            h = client.get("/health")
            assert h.status_code == 503 and h.json()["status"] == "degraded", h.text
            assert h.json()["free_bytes"] < 1 << 20 and "GRAYLIGHT_MIN_FREE_BYTES" in h.json()["problems"][0]
            answers = {
                "capture": client.post("/v1/jobs", headers=auth, files={"capture": ("c.zip", archive, "application/zip")}),
                "chunk": client.patch(f"/v1/uploads/{up['id']}", headers={**auth, "Upload-Offset": "0"}, content=archive),
                "probe": client.post("/v1/jobs", headers=auth, json={"kind": "probe"}),
            }
            for what, r in answers.items():
                assert r.status_code == 507, (what, r.status_code, r.text[:300])
                assert r.json()["detail"].startswith("storage full") and r.headers["retry-after"], (what, r.text)
            store = Path(senv.settings.storage_url)
            leftovers = [p for p in (store / "objects").glob("*/*")] if (store / "objects").exists() else []
            assert leftovers == []  # no object folder without its manifest
            assert [p for p in (store / "uploads").rglob("*") if p.is_file()] == []  # no partial chunk
            filler.unlink()
            assert client.get("/health").status_code == 200
            r = client.post("/v1/jobs", headers=auth, files={"capture": ("c.zip", archive, "application/zip")},
                            data={"params": '{"render": false}'})  # fmt: skip
            assert r.status_code == 201, r.text
            assert client.get(f"/v1/uploads/{up['id']}", headers=auth).json()["offset"] == 0


# ---- finding 3: a worker's unpacked captures go when their jobs end -------------------------------------
@pytest.mark.slow
def test_unpacked_captures_are_removed_when_jobs_end(capture: Path, tmp_path: Path) -> None:
    good = jobsvc.capture_zip(capture, tmp_path / "good.zip").read_bytes()
    broken = jobsvc.capture_zip(capture, tmp_path / "broken.zip", note="b", drop=("rig.json",)).read_bytes()
    with jobsvc.service_env(tmp_path) as senv:
        store = JobStore(senv.settings.database_url)
        auth = {"Authorization": f"Bearer {store.create_key('k')[1]}"}
        jobsvc.start_worker(senv, queues="cpu")
        with TestClient(create_app(senv.settings)) as client:
            ids = [client.post("/v1/jobs", headers=auth, files={"capture": (n, a, "application/zip")},
                               data={"params": '{"render": false}'}).json()["id"]
                   for n, a in (("good.zip", good), ("broken.zip", broken))]  # fmt: skip

            def ended() -> bool:
                return all(client.get(f"/v1/jobs/{i}", headers=auth).json()["state"] in ("succeeded", "failed") for i in ids)

            jobsvc.wait_for(ended, 240, "both jobs ended", senv.procs[0], interval=0.3)
        states = [store.get_job(i).state for i in ids]
        assert states == ["succeeded", "failed"], [store.get_job(i).error for i in ids]
        cache = senv.settings.cache_dir / "captures"
        assert not any(cache.iterdir()) if cache.is_dir() else True, sorted(cache.iterdir())


def test_a_capture_refs_unpacked_size_counts_against_the_key(capture: Path, tmp_path: Path) -> None:
    """A capture in the store's inbox is unpacked by a worker as an upload is: what it inflates to
    counts against the key's stored bytes (read from the archive's headers at intake), so a small
    archive of a large capture is refused 507 when the key cannot hold what it unpacks to."""
    archive = jobsvc.capture_zip(capture, tmp_path / "cap.zip")
    with zipfile.ZipFile(archive, "a", zipfile.ZIP_DEFLATED) as z:  # notes that deflate about 10:1
        z.writestr("notes.txt", "".join(f"turn {i:07d}: plate level, lamp warm\n" for i in range(60_000)))
    with zipfile.ZipFile(archive) as z:
        inflated = sum(i.file_size for i in z.infolist())
    packed = archive.stat().st_size
    assert inflated > 2 * packed  # the test means something: the packed size alone would pass
    for limit, expected in ((packed + (inflated - packed) // 2, 507), (inflated + packed + (1 << 20), 201)):
        senv = jobsvc.make_env(tmp_path / f"svc{limit}", GRAYLIGHT_KEY_MAX_STORED_BYTES=str(limit))
        inbox = Path(senv.settings.storage_url) / "inbox"
        inbox.mkdir(parents=True)
        shutil.copyfile(archive, inbox / "cap.zip")
        with TestClient(create_app(senv.settings)) as client:
            auth = {"Authorization": f"Bearer {JobStore(senv.settings.database_url).create_key('k')[1]}"}
            r = client.post("/v1/jobs", headers=auth, json={"capture_ref": "inbox/cap.zip", "params": {"render": False}})
            assert r.status_code == expected, (limit, r.status_code, r.text[:300])
            if expected == 507:
                assert "GRAYLIGHT_KEY_MAX_STORED_BYTES" in r.json()["detail"]
