"""The point-cloud PLY contract: what Graylight writes, what it reads, and one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.ply import (
    CLOUD_DTYPE,
    iter_ply_chunks,
    read_header,
    read_ply,
    write_ply,
    write_ply_records,
)


def _cloud(n: int = 1000, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return {
        "xyz": rng.uniform(-500, 1500, (n, 3)).astype(np.float32),
        "rgb": rng.integers(0, 256, (n, 3), dtype=np.uint8),
        "normals": normals,
        "size": rng.uniform(0.1, 1.0, n).astype(np.float32),
    }


def test_full_contract_round_trip(tmp_path: Path) -> None:
    c = _cloud()
    path = write_ply(tmp_path / "c.ply", **c, comments=("units mm",))
    h = read_header(path)
    assert h.fmt == "binary_little_endian" and h.count == 1000 and h.comments == ("units mm",)
    assert h.dtype == CLOUD_DTYPE and h.dtype.itemsize == 31
    back = read_ply(path)
    for name in ("xyz", "rgb", "normals", "size"):
        assert np.array_equal(getattr(back, name), c[name]), name
    assert path.stat().st_size == h.data_offset + 31 * 1000


def test_foreign_comments_are_written_back_as_one_ascii_line(tmp_path: Path) -> None:
    """Another scanner's accented comment (read as U+FFFD) failed the header's ASCII encoding
    with a bare UnicodeEncodeError when written back (decompressing its cloud); a newline would
    have started a header line of its own. Each comment is written as one printable line."""
    src = tmp_path / "foreign.ply"
    src.write_bytes("ply\nformat ascii 1.0\ncomment scanné à Paris\nelement vertex 1\nproperty float x\n"
                    "property float y\nproperty float z\nend_header\n0 0 0\n".encode())
    h = read_header(src)
    out = write_ply(tmp_path / "out.ply", np.zeros((1, 3), np.float32), comments=(*h.comments, "units mm\nend_header"))
    assert read_header(out).comments == ("scann?? ?? Paris", "units mm?end_header")
    assert len(read_ply(out).xyz) == 1


def test_chunks_cover_the_cloud_once(tmp_path: Path) -> None:
    c = _cloud(2500)
    path = write_ply(tmp_path / "c.ply", **c)
    parts = list(iter_ply_chunks(path, chunk=1000))
    assert [len(p) for p in parts] == [1000, 1000, 500]
    assert np.array_equal(np.concatenate([p.xyz for p in parts]), c["xyz"])


def test_foreign_clouds_ascii_and_big_endian(tmp_path: Path) -> None:
    xyz = np.array([[1.5, 2.0, 3.0], [4.0, 5.0, 6.25]], np.float32)
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                         "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                         "end_header\n1.5 2 3 10 20 30\n4 5 6.25 40 50 60\n")  # fmt: skip
    a = read_ply(ascii_ply)
    assert np.array_equal(a.xyz, xyz) and a.rgb.tolist() == [[10, 20, 30], [40, 50, 60]]
    assert a.normals is None and a.size is None  # carried only when the cloud has them
    big = tmp_path / "b.ply"
    head = b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    big.write_bytes(head + xyz.astype(">f4").tobytes())
    assert np.array_equal(read_ply(big).xyz, xyz)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"PLY\n", "not a PLY file"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\n", "no end_header"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\nend_header\n", "no 'z' property"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0",
         "PLY is truncated"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty list uchar int x\nend_header\n", "list properties"),
        # Counts against the file's size before any allocation (finding 9: 10^12 vertices gave MemoryError).
        (b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\nproperty float z\n"
         b"end_header\n0 0 0\n", "PLY header claims 1000000000000 vertices, but the 6 bytes after it hold at most 1"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\n"
         b"property float z\nend_header\n" + bytes(12), "header claims 1000000000000 vertices of 12 bytes, 12 bytes follow"),
        (b"ply\nformat ascii 1.0\nelement vertex " + b"9" * 5000 + b"\nproperty float x\nend_header\n", "bad vertex count '9999"),
        (b"ply\nformat xml 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n", "unsupported PLY format"),
        # ASCII values are parsed as float64: 300 in a uchar wrapped to 44, -1 to 255, 1.5 to 1
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
         b"property uchar red\nend_header\n0 0 0 7\n1 1 1 300\n", "ASCII PLY vertex 1: red is 300, not an integer in 0..255"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
         b"property short view\nend_header\n0 0 0 1.5\n", "ASCII PLY vertex 0: view is 1.5, not an integer in -32768..32767"),
        # numpy refuses a record type with a field twice: a bare ValueError from another scanner's file
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
         b"property uchar red\nproperty uchar red\nend_header\n" + bytes(14), "PLY vertex property 'red' is declared more than once"),
    ],
)
def test_bad_files_name_the_file(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(InputError) as err:
        read_ply(path)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value), str(err.value)


def test_records_writer_refuses_a_short_stream_and_leaves_nothing(tmp_path: Path) -> None:
    rec = np.zeros(10, CLOUD_DTYPE)
    with pytest.raises(ValueError, match="5 records written, the header says 10"):
        write_ply_records(tmp_path / "c.ply", iter([rec[:5]]), 10, CLOUD_DTYPE)
    assert list(tmp_path.iterdir()) == []


def test_fifo_and_device_are_refused_without_blocking(tmp_path: Path) -> None:
    """A FIFO is opened without blocking and refused by fstat; /dev/zero is not a regular file."""
    import os

    fifo = tmp_path / "cloud.ply"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match=r"cloud\.ply: is not a regular file$"):
        read_header(fifo)
    with pytest.raises(InputError, match=r"^/dev/zero: is not a regular file$"):
        read_header("/dev/zero")
