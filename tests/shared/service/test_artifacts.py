"""The artifact store on a local folder and on S3 (moto's server on loopback): atomic,
content-addressed objects with checksums; duplicates find the first result."""

from __future__ import annotations

import hashlib
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from shared.service.artifacts import ArtifactError, ArtifactStore
from tests.support.jobsvc import moto_server


@pytest.fixture(scope="module")
def moto_endpoint() -> Iterator[str]:
    with moto_server() as url:
        yield url


@pytest.fixture(params=["local", "s3"])
def arts(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> ArtifactStore:
    if request.param == "local":
        return ArtifactStore(str(tmp_path / "store"))
    endpoint = request.getfixturevalue("moto_endpoint")
    for k, v in {
        "AWS_ACCESS_KEY_ID": "test",
        "AWS_SECRET_ACCESS_KEY": "test",
        "AWS_DEFAULT_REGION": "us-east-1",
    }.items():
        monkeypatch.setenv(k, v)
    import boto3

    bucket = f"b{uuid.uuid4().hex[:12]}"
    boto3.client("s3", endpoint_url=endpoint).create_bucket(Bucket=bucket)
    return ArtifactStore(f"s3://{bucket}/graylight", s3_endpoint=endpoint)


def key_of(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def sample(folder: Path, payload: bytes = b"cloud bytes") -> Path:
    (folder / "sub").mkdir(parents=True, exist_ok=True)
    (folder / "cloud.ply").write_bytes(payload)
    (folder / "sub" / "n.bin").write_bytes(bytes(range(256)) * 10)
    return folder


def test_put_fetch_verify(arts: ArtifactStore, tmp_path: Path) -> None:
    key = key_of("stage inputs 1")
    assert not arts.exists(key)
    m = arts.put_dir(key, sample(tmp_path / "out"))
    assert set(m.files) == {"cloud.ply", "sub/n.bin"}
    assert m.files["cloud.ply"].sha256 == hashlib.sha256(b"cloud bytes").hexdigest()
    assert arts.exists(key)
    local = arts.fetch(key, tmp_path / "cache")
    assert (local / "sub" / "n.bin").read_bytes() == bytes(range(256)) * 10
    assert b"".join(arts.iter_bytes(key, "cloud.ply")) == b"cloud bytes"
    assert arts.verify(key) == m


def test_duplicate_writer_finds_first_result(arts: ArtifactStore, tmp_path: Path) -> None:
    key = key_of("dup")
    first = arts.put_dir(key, sample(tmp_path / "a", b"first"))
    second = arts.put_dir(key, sample(tmp_path / "b", b"second"))
    assert second == first
    assert b"".join(arts.iter_bytes(key, "cloud.ply")) == b"first"


def test_concurrent_writers_leave_one_consistent_object(arts: ArtifactStore, tmp_path: Path) -> None:
    key = key_of("race")
    folders = [sample(tmp_path / f"w{i}", f"writer {i}".encode()) for i in range(4)]
    barrier = threading.Barrier(4)
    results: list = []

    def write(f: Path) -> None:
        barrier.wait()
        results.append(arts.put_dir(key, f))

    threads = [threading.Thread(target=write, args=(f,)) for f in folders]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    m = arts.verify(key)  # files and manifest agree, whoever won
    assert len(results) == 4  # no writer failed
    assert all(arts.verify(key) == m for _ in range(2))


def test_corruption_detected(arts: ArtifactStore, tmp_path: Path) -> None:
    key = key_of("corrupt")
    m = arts.put_dir(key, sample(tmp_path / "out"))
    path = f"{arts._obj(key)}/{m.prefix}/cloud.ply"
    arts.fs.pipe_file(path, b"cloud bytez")  # same size, other bytes
    with pytest.raises(ArtifactError, match="checksum mismatch"):
        arts.verify(key)


def test_missing_object_and_bad_names(arts: ArtifactStore) -> None:
    with pytest.raises(ArtifactError, match="does not exist"):
        arts.open(key_of("nothing"), "cloud.ply")
    with pytest.raises(ArtifactError, match="not a hex digest"):
        arts.exists("../../etc")
    with pytest.raises(ArtifactError, match="relative path"):
        arts.ref_path("../outside")


def test_resumable_upload_chunks_assemble(arts: ArtifactStore, tmp_path: Path) -> None:
    upload = str(uuid.uuid4())
    parts = [b"a" * 1000, b"b" * 10, b"c" * 333]
    for i, data in enumerate(parts):
        p = tmp_path / f"chunk{i}"
        p.write_bytes(data)
        arts.put_chunk(upload, i, p)
    out = tmp_path / "whole"
    arts.assemble_upload(upload, len(parts), out)
    assert out.read_bytes() == b"".join(parts)
    arts.drop_upload(upload)


def test_references_read_within_limits(arts: ArtifactStore, tmp_path: Path) -> None:
    arts.fs.pipe_file(arts.ref_path("inbox/cap1/capture.json"), b"{}")
    arts.fs.pipe_file(arts.ref_path("inbox/cap1/white.png"), b"png")
    fp = arts.ref_fingerprint("inbox/cap1")
    assert len(fp) == 64
    got = arts.ref_read("inbox/cap1", tmp_path / "got", max_bytes=1000, max_files=10)
    assert sorted(p.name for p in got.iterdir()) == ["capture.json", "white.png"]
    with pytest.raises(ArtifactError, match="more than the limit of 1"):
        arts.ref_read("inbox/cap1", tmp_path / "got2", max_bytes=1000, max_files=1)
    arts.fs.pipe_file(arts.ref_path("inbox/cap1/white.png"), b"png, changed")
    assert arts.ref_fingerprint("inbox/cap1") != fp


def test_put_dir_by_move_on_a_local_store(tmp_path: Path) -> None:
    arts = ArtifactStore(str(tmp_path / "store"))
    src = sample(tmp_path / "work" / "out")
    m = arts.put_dir(key_of("moved"), src, move=True)
    assert not src.exists()  # renamed into the store, not copied
    assert arts.verify(key_of("moved")) == m
    again = arts.put_dir(key_of("moved"), sample(tmp_path / "work" / "out2", b"other"), move=True)
    assert again == m and b"".join(arts.iter_bytes(key_of("moved"), "cloud.ply")) == b"cloud bytes"
