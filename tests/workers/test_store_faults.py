"""The artifact store failing mid-stage, for real: a store whose filesystem refuses the Nth
write (``faulty://``, the local filesystem behind a write budget, driven through the same code
path as S3), and a local store on a tmpfs too small for a stage's output (a full disk). The
job fails with a clear reason (or, for a transient fault, its stage goes back to the queue and
succeeds when retried), no object is half written, other jobs' objects are untouched, and a
retry after the fault is gone re-runs only what failed. Real database and Redis; the stages
run in this process through the real runner."""

from __future__ import annotations

import errno
import hashlib
import subprocess
from collections.abc import Iterator
from pathlib import Path

import fsspec
import pytest
from fastapi.testclient import TestClient
from fsspec.implementations.local import LocalFileSystem

from services.api.app import create_app
from shared.service.jobstore import JobStore
from tests.support import inprocess, jobsvc
from workers.runner import run_stage

NO_RENDER = '{"render": false}'


class FaultyFS(LocalFileSystem):
    """The local filesystem under the ``faulty://`` protocol, whose writes (``put_file``,
    ``pipe_file``) raise ``error`` once ``budget`` more have succeeded (None: never)."""

    protocol = "faulty"
    budget: int | None = None
    error: BaseException = OSError(errno.ENOSPC, "No space left on device")
    failures = 0

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.pop("auto_mkdir", None)
        super().__init__(*args, auto_mkdir=True, **kwargs)

    @classmethod
    def _strip_protocol(cls, path: str) -> str:
        path = str(path)
        return super()._strip_protocol(path[len("faulty://") :] if path.startswith("faulty://") else path)

    @classmethod
    def arm(cls, budget: int | None, error: BaseException | None = None) -> None:
        cls.budget, cls.failures = budget, 0
        if error is not None:
            cls.error = error

    def _spend(self, path: str) -> None:
        cls = type(self)
        if cls.budget is None:
            return
        if cls.budget <= 0:
            cls.failures += 1
            err = cls.error
            if isinstance(err, OSError) and err.errno is not None:
                raise type(err)(err.errno, err.strerror, path)  # as the OS says it: naming the file
            raise type(err)(*err.args)
        cls.budget -= 1

    def put_file(self, lpath: str, rpath: str, *args: object, **kwargs: object) -> None:
        self._spend(rpath)
        super().put_file(lpath, rpath, *args, **kwargs)

    def pipe_file(self, path: str, value: bytes, *args: object, **kwargs: object) -> None:
        self._spend(path)
        super().pipe_file(path, value, *args, **kwargs)


fsspec.register_implementation("faulty", FaultyFS, clobber=True)


@pytest.fixture(autouse=True)
def _disarmed() -> Iterator[None]:
    FaultyFS.arm(None)
    yield
    FaultyFS.arm(None)


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return jobsvc.simulate_small(tmp_path_factory.mktemp("cap") / "plane")


def snapshot(root: Path) -> dict[str, str]:
    """Every file under the store's objects folder -> its SHA-256."""
    objects = root / "objects"
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(objects.rglob("*")) if p.is_file()} if objects.exists() else {}  # fmt: skip


def submit(client: TestClient, auth: dict[str, str], archive: Path) -> str:
    r = client.post("/v1/jobs", headers=auth, files={"capture": (archive.name, archive.read_bytes(), "application/zip")},
                    data={"params": NO_RENDER})  # fmt: skip
    assert r.status_code == 201, r.text
    return r.json()["id"]


def check_no_partial_object(root: Path, key: str) -> None:
    """The object ``key`` does not exist, and none of its files were left behind."""
    obj = root / "objects" / key[:2] / key
    assert not (obj / "MANIFEST.json").exists()
    assert not obj.exists() or not any(p.is_file() for p in obj.rglob("*")), sorted(obj.rglob("*"))


def test_store_failing_at_the_nth_write(capture: Path, tmp_path: Path) -> None:
    root = tmp_path / "store"
    with jobsvc.service_env(tmp_path, GRAYLIGHT_STORAGE_URL=f"faulty://{root}") as senv:
        store = JobStore(senv.settings.database_url)
        key = store.create_key("faults")[1]
        client = TestClient(create_app(senv.settings))
        auth = {"Authorization": f"Bearer {key}"}
        other = submit(client, auth, jobsvc.capture_zip(capture, tmp_path / "other.zip", note="other"))
        inprocess.drive(senv.settings, other)
        assert store.get_job(other).state == "succeeded"
        victim = submit(client, auth, jobsvc.capture_zip(capture, tmp_path / "victim.zip", note="victim"))
        inprocess.drive(senv.settings, victim, stop_after="ingest")
        before = snapshot(root)

        # decode stores several files: the store refuses the second one (a disk filling up).
        FaultyFS.arm(1)
        inprocess.drive(senv.settings, victim)
        assert FaultyFS.failures == 1
        job = store.get_job(victim)
        assert job.state == "failed" and job.stage("decode").state == "failed"
        assert job.error.startswith("decode: storage full: no space left on device while stage decode wrote its output")
        assert "nothing of it was kept" in job.error and "\n" not in job.error
        assert str(root) not in job.error  # the store's path stays in the worker's log, not in a client's message
        check_no_partial_object(root, job.stage("decode").input_key)
        assert snapshot(root) == before  # every stored object (the other job's, this one's ingest) intact
        assert client.get(f"/v1/jobs/{victim}/artifacts/decoded.npz", headers=auth).status_code == 404
        assert client.get(f"/v1/jobs/{other}/artifacts/cloud.ply", headers=auth).status_code == 200

        # The fault is gone: a retry re-runs decode and what follows, not ingest.
        FaultyFS.arm(None)
        assert client.post(f"/v1/jobs/{victim}/retry", headers=auth).status_code == 200
        inprocess.drive(senv.settings, victim)
        done = store.get_job(victim)
        assert done.state == "succeeded"
        assert done.stage("ingest").attempts == 1 and done.stage("decode").attempts == 2


def test_transient_store_fault_is_retried(capture: Path, tmp_path: Path) -> None:
    root = tmp_path / "store"
    with jobsvc.service_env(tmp_path, GRAYLIGHT_STORAGE_URL=f"faulty://{root}") as senv:
        store = JobStore(senv.settings.database_url)
        key = store.create_key("faults")[1]
        client = TestClient(create_app(senv.settings))
        job_id = submit(client, {"Authorization": f"Bearer {key}"}, jobsvc.capture_zip(capture, tmp_path / "c.zip"))
        ingest = store.get_job(job_id).stage("ingest")
        FaultyFS.arm(0, ConnectionError("store connection reset"))
        with pytest.raises(ConnectionError):  # Celery's retry with backoff takes it from here
            run_stage(ingest.id, senv.settings, publish=False)
        st = store.get_job(job_id).stage("ingest")
        assert st.state == "queued" and "transient fault: ConnectionError: store connection reset" in st.error
        check_no_partial_object(root, st.input_key)
        FaultyFS.arm(None)
        assert run_stage(ingest.id, senv.settings, publish=False).status == "succeeded"
        assert store.get_job(job_id).stage("ingest").attempts == 2


@pytest.fixture
def small_tmpfs(tmp_path: Path) -> Iterator[Path]:
    """A tmpfs mounted for the test (root only); its size is set by remounting."""
    with jobsvc.tmpfs(tmp_path / "tmpfs", "64m") as mnt:
        yield mnt


@pytest.mark.slow
def test_local_store_on_a_full_disk(capture: Path, tmp_path: Path, small_tmpfs: Path) -> None:
    root = small_tmpfs / "store"
    with jobsvc.service_env(tmp_path, GRAYLIGHT_STORAGE_URL=str(root)) as senv:
        store = JobStore(senv.settings.database_url)
        key = store.create_key("disk")[1]
        client = TestClient(create_app(senv.settings))
        auth = {"Authorization": f"Bearer {key}"}
        other = submit(client, auth, jobsvc.capture_zip(capture, tmp_path / "other.zip", note="other"))
        inprocess.drive(senv.settings, other)
        assert store.get_job(other).state == "succeeded"
        victim = submit(client, auth, jobsvc.capture_zip(capture, tmp_path / "victim.zip", note="victim"))
        inprocess.drive(senv.settings, victim, stop_after="ingest")
        before = snapshot(root)
        # Shrink the disk to what is used now plus half of what decode stored for the other job:
        # the victim's decode output cannot fit (the work folder is on another filesystem, so
        # the store copies it in and runs out of space in the middle).
        decode_bytes = sum(p.stat().st_size for p in (root / "objects").rglob("*")
                           if p.is_file() and p.parent.parent.name == store.get_job(other).stage("decode").output_key)  # fmt: skip
        used = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
        size_kib = (used + decode_bytes // 2) // 1024 + 64
        subprocess.run(["mount", "-o", f"remount,size={size_kib}k", str(small_tmpfs)], check=True)
        inprocess.drive(senv.settings, victim)
        job = store.get_job(victim)
        assert job.state == "failed" and job.error.startswith("decode: storage full: no space left on device"), job.error
        check_no_partial_object(root, job.stage("decode").input_key)
        assert snapshot(root) == before
        assert client.get(f"/v1/jobs/{other}/artifacts/cloud.ply", headers=auth).status_code == 200
