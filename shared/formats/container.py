"""The Graylight compressed container: one format for range images (``.glr``) and point clouds (``.glo``).

Layout (all integers little-endian)::

    magic    8 bytes  b"\\x89GLC\\r\\n\\x1a\\n"   (PNG-style: catches text-mode and 7-bit mangling)
    version  u16      CONTAINER_VERSION (1)
    kind     u8       1 = range image, 2 = point cloud
    flags    u8       0
    length   u32      bytes of the header document
    crc      u32      CRC-32 of the header document
    header   JSON     UTF-8; always holds "chunks" (their count) and what the kind needs
                      (sizes, units, quantum or error bound, codec parameters)
    chunk    x chunks u32 payload length, u32 CRC-32 of the payload, payload
    trailer  8 bytes  b"GLC-END\\n"

Chunks are independent (a band of image rows, a slice of the cloud), so they are encoded and
decoded in parallel and in bounded memory, and a damaged chunk is found by its checksum
before it is decoded. Anything else -- a wrong magic or version, a bad checksum, a short
file, bytes after the trailer -- raises :class:`~shared.core.errors.InputError` naming the
file. Writing goes through :func:`~shared.core.files.atomic_file`: nothing half-written.
"""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.core.jsonsafe import json_integer

MAGIC = b"\x89GLC\r\n\x1a\n"
TRAILER = b"GLC-END\n"
CONTAINER_VERSION = 1
KINDS = {"range": 1, "cloud": 2}
_KIND_NAMES = {v: k for k, v in KINDS.items()}
_FIXED = struct.Struct("<HBBII")
_CHUNK = struct.Struct("<II")
#: Largest header document accepted (a corrupt length must not make us allocate gigabytes).
MAX_HEADER = 1 << 20
MAX_CHUNK = (1 << 32) - 1


@dataclass(frozen=True)
class ContainerHeader:
    """What a container's header says: ``kind`` ("range" or "cloud"), ``version``, the
    header document ``meta`` (``meta["chunks"]`` is the number of chunks) and its CRC-32
    ``crc`` (:func:`header_crc`: the codecs bind each chunk's check to it)."""

    kind: str
    version: int
    meta: dict[str, Any]
    crc: int = 0

    @property
    def chunks(self) -> int:
        return int(self.meta["chunks"])


def _document(meta: dict[str, Any]) -> bytes:
    return json.dumps(meta, separators=(",", ":")).encode("utf-8")


def header_crc(meta: dict[str, Any]) -> int:
    """The CRC-32 :func:`write_stream` stores for the header document ``meta``: a codec binds
    each chunk's own check to it (and the reader's :attr:`ContainerHeader.crc`), so that a
    header rewritten with a fresh CRC (another quantum, another size) fails every chunk."""
    return zlib.crc32(_document(meta))


def write_stream(f: BinaryIO, kind: str, meta: dict[str, Any], chunks: Iterable[bytes]) -> int:
    """Write a container to the binary file ``f``; ``meta["chunks"]`` must equal the number of
    ``chunks`` yielded (checked). Returns the bytes written."""
    if kind not in KINDS:
        raise ValueError(f"unknown container kind {kind!r}")
    doc = _document(meta)
    f.write(MAGIC + _FIXED.pack(CONTAINER_VERSION, KINDS[kind], 0, len(doc), zlib.crc32(doc)) + doc)
    total = len(MAGIC) + _FIXED.size + len(doc)
    n = 0
    for payload in chunks:
        if len(payload) > MAX_CHUNK:
            raise ValueError(f"chunk {n} is {len(payload)} bytes, more than a container chunk holds")
        f.write(_CHUNK.pack(len(payload), zlib.crc32(payload)))
        f.write(payload)
        total += _CHUNK.size + len(payload)
        n += 1
    if n != int(meta["chunks"]):
        raise ValueError(f"header announces {meta['chunks']} chunks, {n} were written")
    f.write(TRAILER)
    return total + len(TRAILER)


def write_container(path: str | os.PathLike[str], kind: str, meta: dict[str, Any], chunks: Iterable[bytes]) -> int:
    """:func:`write_stream` to ``path`` atomically (a temporary name renamed on success)."""
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        return write_stream(f, kind, meta, chunks)


def _read_exact(f: BinaryIO, n: int, where: str, what: str) -> bytes:
    b = f.read(n)
    if len(b) != n:
        raise InputError(where, f"truncated: the file ends inside {what}")
    return b


def read_header(f: BinaryIO, where: str, kind: str | None = None) -> ContainerHeader:
    """Read and check a container's header from ``f`` (positioned at its start)."""
    magic = f.read(len(MAGIC))
    if magic != MAGIC:
        if len(magic) < len(MAGIC) and MAGIC.startswith(magic) and magic:
            raise InputError(where, "truncated: the file ends inside the magic number")
        raise InputError(where, "not a Graylight compressed file (wrong magic number)")
    version, kind_id, _flags, length, crc = _FIXED.unpack(_read_exact(f, _FIXED.size, where, "the header"))
    if version != CONTAINER_VERSION:
        raise InputError(where, f"container version {version} is not supported (this build reads version {CONTAINER_VERSION})")
    if kind_id not in _KIND_NAMES:
        raise InputError(where, f"unknown container kind {kind_id}")
    if length > MAX_HEADER:
        raise InputError(where, f"corrupt header: it claims {length} bytes")
    doc = _read_exact(f, length, where, "the header")
    if zlib.crc32(doc) != crc:
        raise InputError(where, "corrupt header (checksum mismatch)")
    try:
        meta = json.loads(doc)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise InputError(where, "corrupt header (not a JSON document)") from None
    if not isinstance(meta, dict) or not json_integer(meta.get("chunks")) or meta["chunks"] < 0:
        raise InputError(where, 'corrupt header (no "chunks" count)')
    name = _KIND_NAMES[kind_id]
    if kind is not None and name != kind:
        raise InputError(where, f"holds a {name}, not a {kind}")
    return ContainerHeader(name, version, meta, crc)


def header_int(meta: dict[str, Any], key: str) -> int:
    """``meta[key]`` when the header holds a JSON integer there: KeyError when it is absent,
    TypeError for anything else (a float, which ``int()`` would truncate or fail to convert when
    infinite, a string, a bool) -- what the readers' header checks catch as a corrupt header."""
    v = meta[key]
    if not json_integer(v):
        raise TypeError(f"{key!r} is not an integer")
    return v


def iter_chunks(f: BinaryIO, header: ContainerHeader, where: str) -> Iterator[bytes]:
    """The payloads of the chunks after the header, each checked against its CRC-32; then the
    trailer and the end of the file are checked."""
    for i in range(header.chunks):
        length, crc = _CHUNK.unpack(_read_exact(f, _CHUNK.size, where, f"chunk {i}"))
        payload = _read_exact(f, length, where, f"chunk {i}")
        if zlib.crc32(payload) != crc:
            raise InputError(where, f"corrupt chunk {i} (checksum mismatch)")
        yield payload
    if _read_exact(f, len(TRAILER), where, "the trailer") != TRAILER:
        raise InputError(where, "corrupt file: no end marker after the last chunk")
    if f.read(1):
        raise InputError(where, "corrupt file: bytes after the end marker")


def open_container(source: str | os.PathLike[str] | bytes, kind: str | None = None) -> tuple[ContainerHeader, Iterator[bytes]]:
    """Header (read and checked now) and chunk iterator of a container file (or of its bytes).
    The iterator opens the file when iteration starts and closes it when it ends."""
    if isinstance(source, bytes | bytearray | memoryview):
        data = bytes(source)
        f = io.BytesIO(data)
        header = read_header(f, "<bytes>", kind)
        start = f.tell()

        def from_bytes() -> Iterator[bytes]:
            g = io.BytesIO(data)
            g.seek(start)
            yield from iter_chunks(g, header, "<bytes>")

        return header, from_bytes()
    where = str(source)
    if not Path(source).is_file():
        raise InputError(where, "a folder, not a compressed file" if Path(source).is_dir() else "no such file")
    with open(source, "rb") as fh:
        header = read_header(fh, where, kind)
        start = fh.tell()

    def from_file() -> Iterator[bytes]:
        with open(source, "rb") as g:
            g.seek(start)
            yield from iter_chunks(g, header, where)

    return header, from_file()
