"""Hostile inputs for the job service's tests (issue 21): a zip bomb of many small members
written without compressing each member again, deeply nested JSON, a request body streamed
over a raw socket (so a test can send more than the server wants to read), and every field of
a valid document replaced by values a careless or hostile writer sends (:func:`field_variants`)."""

from __future__ import annotations

import copy
import socket
import struct
import threading
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["HOSTILE_VALUES", "bare_failures", "deep_json", "field_variants", "many_member_bomb", "process_rss",
           "stream_body"]

#: What a careless or hostile writer puts in a field: wrong types, numbers past float's range
#: (an integer Python's json reads from a library caller; 1e400 parses to infinity), negative,
#: zero and huge counts, paths, NUL, long text, nested and ragged lists, objects.
HOSTILE_VALUES: tuple[Any, ...] = (
    None, True, False, 0, -1, 1, 3, 2**31, 2**63, 10**400, 1e308, float("nan"), float("inf"), float("-inf"), 0.5,
    "", "abc", "../../etc/passwd", "a\x00b", "é" * 5000, [], [1], [[1, 2], [3]], [None], ["a"], {}, {"a": 1},
    [[0, 0, 0], [0, 0, 0], [0, 0, 0]], [[1e308] * 3] * 3, list(range(100)),
)


def _paths(doc: Any, prefix: tuple = ()) -> Iterator[tuple]:
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:3]):
            yield from _paths(v, prefix + (i,))


def field_variants(doc: Any) -> Iterator[tuple[str, Any]]:
    """(field path, document) for every field of ``doc`` (lists: their first three items) and
    the document itself, each replaced in turn by every :data:`HOSTILE_VALUES` value, and each
    field left out."""
    for path in list(_paths(doc)):
        name = ".".join(map(str, path)) or "(document)"
        for value in HOSTILE_VALUES:
            out = copy.deepcopy(doc)
            if not path:
                yield name, value
                continue
            cur = out
            for k in path[:-1]:
                cur = cur[k]
            cur[path[-1]] = value
            yield name, out
        if path:
            out = copy.deepcopy(doc)
            cur = out
            for k in path[:-1]:
                cur = cur[k]
            if isinstance(cur, dict):
                del cur[path[-1]]
                yield name + " (left out)", out


def bare_failures(doc: Any, read: Callable[[Any], object], expected: type[BaseException]) -> list[str]:
    """The variants of ``doc`` (:func:`field_variants`) on which ``read`` raised anything but
    ``expected``: "field: ExceptionName: text" each (empty when every variant was read or
    refused as it should be)."""
    out = []
    for name, variant in field_variants(doc):
        try:
            read(variant)
        except expected:
            pass
        except Exception as exc:  # noqa: BLE001 - what the test reports
            out.append(f"{name}: {type(exc).__name__}: {str(exc)[:100]}")
    return out


def deep_json(levels: int = 10_000) -> str:
    """A JSON document nested ``levels`` brackets deep: ``[[[...]]]``."""
    return "[" * levels + "]" * levels


def many_member_bomb(path: Path, members: int = 4095, member_bytes: int = 1 << 20,
                     declared: int | None = None, extra: dict[str, bytes] | None = None) -> Path:  # fmt: skip
    """A zip of ``members`` members of ``member_bytes`` zero bytes each (deflated once and
    repeated: a 4 GiB bomb is written in a fraction of a second), plus ``extra`` small members
    (a ``capture.json``). ``declared``: the unpacked size each header claims (a lying header)."""
    zeros = bytes(member_bytes)
    comp = zlib.compressobj(9, zlib.DEFLATED, -15)
    packed = comp.compress(zeros) + comp.flush()
    crc = zlib.crc32(zeros)
    size = member_bytes if declared is None else declared
    entries: list[tuple[bytes, bytes, int, int, int]] = []  # name, data, crc, usize, method
    for name, data in (extra or {}).items():
        entries.append((name.encode(), data, zlib.crc32(data), len(data), 0))
    central = bytearray()
    with open(path, "wb") as f:
        def put(name: bytes, data: bytes, crc_: int, usize: int, method: int) -> None:
            offset = f.tell()
            f.write(struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0x21, crc_, len(data), usize, len(name), 0))
            f.write(name)
            f.write(data)
            central.extend(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, method, 0, 0x21, crc_, len(data),
                                       usize, len(name), 0, 0, 0, 0, 0, offset))  # fmt: skip
            central.extend(name)

        for e in entries:
            put(*e)
        for i in range(members):
            put(f"zeros/{i:05d}.bin".encode(), packed, crc, size, 8)
        start = f.tell()
        f.write(central)
        n = len(entries) + members
        f.write(struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, len(central), start, 0))
    return path


def process_rss(pid: int) -> int:
    """Resident memory of process ``pid`` in bytes (Linux ``/proc``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmRSS for process {pid}")


def stream_body(url: str, path: str, headers: dict[str, str], total: int, chunk: int = 1 << 20,
                timeout: float = 60) -> tuple[int, bytes, int]:  # fmt: skip
    """POST ``total`` bytes (``{"a": "xxxx...``) to ``url + path`` with chunked transfer encoding
    from a sender thread that stops when the server stops reading; returns (status, body, bytes
    sent). The server may answer before the body ends: that is what a bounded server does."""
    host, port = url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=timeout)
    head = [f"POST {path} HTTP/1.1", f"Host: {host}", "Content-Type: application/json", "Transfer-Encoding: chunked",
            "Connection: close", *(f"{k}: {v}" for k, v in headers.items())]  # fmt: skip
    sent = 0

    def send() -> None:
        nonlocal sent
        try:
            sock.sendall(("\r\n".join(head) + "\r\n\r\n").encode())
            block = b'{"a": "' + b"x" * (chunk - 7)
            while sent < total:
                sock.sendall(f"{len(block):x}\r\n".encode() + block + b"\r\n")
                sent += len(block)
                block = b"x" * chunk
            sock.sendall(b"0\r\n\r\n")
        except OSError:
            pass  # the server answered and closed: it read no more

    t = threading.Thread(target=send, daemon=True)
    t.start()
    data = b""
    try:
        while True:
            part = sock.recv(65536)
            if not part:
                break
            data += part
    except OSError:
        pass
    finally:
        t.join(timeout)
        sock.close()
    status_line, _, rest = data.partition(b"\r\n")
    status = int(status_line.split()[1]) if status_line else 0
    return status, rest.partition(b"\r\n\r\n")[2], sent
