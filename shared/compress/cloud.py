"""Point clouds (any PLY of the cloud contract) coded by an octree to a geometry precision.

Geometry is quantised to a grid of step ``precision`` (in the cloud's units) anchored at the
origin: every decoded coordinate is the centre of its input point's voxel, within
``precision / 2`` of the input on each axis. Attributes, as stated:

- ``red, green, blue``: exact;
- ``nx, ny, nz``: octahedral 12+12-bit, re-normalised (within :data:`NORMAL_MAX_DEG` degrees);
- ``size``: to ``precision / 128`` (absolute);
- ``confidence``: to 2**-13 (absolute);
- any integer field (``view``...): exact; any other float field: exact (stored raw, zlib).

Points come back in Morton order within each chunk (the order an octree yields), chunk after
chunk in file order. The cloud is cut into equal chunks of at most :data:`CHUNK_POINTS` points in file
order (:func:`chunk_points`), each its own octree on the shared grid, coded on a thread pool (:mod:`shared.compress._octree`),
so a 100 M-point cloud streams through bounded memory on both cores. Each chunk carries a
CRC-32 of what it decodes to, bound to its place and to the header (:func:`_chunk_check`), so
that damage the container's CRC-32 does not see (a buggy tool rewrote it) is refused too.
"""

from __future__ import annotations

import io
import logging
import math
import os
import shutil
import struct
import zlib
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from shared.compress import _octree as ot
from shared.core.errors import InputError
from shared.core.threads import cpu_budget
from shared.formats.container import header_crc, header_int, open_container, write_container, write_stream
from shared.formats.ply import iter_ply_records, read_header, write_ply_records

log = logging.getLogger(__name__)

CODEC = "octree-rans-5"
#: Most points per chunk: about 200 MB of working memory per chunk in flight while encoding
#: (the adaptive models learn more from larger chunks: 2 M points cost 0.7 % fewer bits than 1 M
#: on a scan). A cloud of more than :data:`SPLIT_POINTS` points is cut into an even number of
#: equal chunks (both cores decode a scan-sized cloud of 2-3 M points together and finish together).
CHUNK_POINTS = 1 << 21
SPLIT_POINTS = 1 << 18
#: Largest chunk a reader accepts (the writer's CHUNK_POINTS may change between versions).
MAX_CHUNK_POINTS = 1 << 24
#: Most points in a cloud (268 M; a 150 MP camera's view is 151 M), refused by the writer and by
#: the reader before it allocates: an entropy coder codes a run of equal points in almost no
#: bits, so a few kilobytes of chunks can claim and really decode gigabytes of records.
MAX_POINTS = 1 << 28
NORMAL_BITS = 12
#: Largest angle between a normal and its decoded value, degrees (measured bound of 12-bit octahedral).
NORMAL_MAX_DEG = 0.05
CONFIDENCE_STEP = 2.0**-12
SIZE_STEP_OF_PRECISION = 1.0 / 64
_CHUNK_HEAD = struct.Struct("<qqqqqqI")  # points, voxels, depth, offset xyz, raw-bytes length
_CHECK = struct.Struct("<I")  # after the head: the chunk's check (_chunk_check)


def _chunk_check(header: int, first: int, head: bytes, raw: bytes, codes: np.ndarray, chan: np.ndarray) -> int:
    """The check of what a chunk decodes to: CRC-32 of the container header's CRC-32
    ``header`` (:func:`shared.formats.container.header_crc`: the precision and the fields), the
    index of the chunk's ``first`` point, its ``head`` (:data:`_CHUNK_HEAD`), its ``raw``
    fields and what the octree stream gives, the points' Morton codes ``codes`` (N,) int64
    (sorted, repeated per duplicate) and attribute differences ``chan`` (N, C) int64, from which
    every record is rebuilt. The container's CRC-32 covers the bytes; this covers a chunk
    rewritten with a fresh CRC (a buggy tool), which ``octree-rans-4`` decoded to another cloud
    in 12 of 114 random one-byte and table damages (a changed offset in the head shifts every
    point; the rANS stream's end state catches most of the rest), a chunk in another chunk's
    place, and a header rewritten with its CRC (another precision scaled every point)."""
    c = zlib.crc32(struct.pack("<IQ", header, first) + head)
    c = zlib.crc32(raw, c)
    c = zlib.crc32(np.ascontiguousarray(codes, "<i8"), c)
    return zlib.crc32(np.ascontiguousarray(chan, "<i8"), c)


def _threads() -> int:
    """Chunks coded at once: one a CPU of the budget (each holds about 200 MB while it encodes)."""
    return cpu_budget()


def _sign(a: np.ndarray) -> np.ndarray:
    return np.where(a >= 0, 1.0, -1.0)


def octa_encode(n: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) -> (N, 2) int64 in [0, 2**NORMAL_BITS) (octahedral map)."""
    n = n.astype(np.float64)
    s = np.abs(n).sum(axis=1)
    s[s == 0] = 1.0
    u, v, w = n[:, 0] / s, n[:, 1] / s, n[:, 2] / s
    neg = w < 0
    u2 = np.where(neg, (1 - np.abs(v)) * _sign(u), u)
    v2 = np.where(neg, (1 - np.abs(u)) * _sign(v), v)
    m = (1 << NORMAL_BITS) - 1
    return np.stack([np.rint((u2 + 1) * 0.5 * m), np.rint((v2 + 1) * 0.5 * m)], axis=1).astype(np.int64)


def octa_decode(q: np.ndarray) -> np.ndarray:
    """Inverse of :func:`octa_encode`: (N, 2) -> unit normals (N, 3) float32."""
    m = (1 << NORMAL_BITS) - 1
    u = q[:, 0] * (2.0 / m) - 1
    v = q[:, 1] * (2.0 / m) - 1
    w = 1 - np.abs(u) - np.abs(v)
    neg = w < 0
    u2 = np.where(neg, (1 - np.abs(v)) * _sign(u), u)
    v2 = np.where(neg, (1 - np.abs(u)) * _sign(v), v)
    out = np.stack([u2, v2, w], axis=1)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.astype(np.float32)


def _plan_fields(dtype: np.dtype, where: str) -> list[tuple[str, str]]:
    """(field, how) for every field other than x, y, z: how is rgb, normal, size, confidence, int or raw."""
    names = list(dtype.names or ())
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise InputError(where, f'the vertex element has no "{axis}" property')
    plan = []
    has_rgb = {"red", "green", "blue"} <= set(names)
    has_n = {"nx", "ny", "nz"} <= set(names)
    for name in names:
        kind = dtype[name]
        if name in ("x", "y", "z"):
            continue
        if has_rgb and name in ("red", "green", "blue") and kind == np.uint8:
            plan.append((name, "rgb"))
        elif has_n and name in ("nx", "ny", "nz"):
            plan.append((name, "normal"))
        elif name == "size" and kind.kind == "f":
            plan.append((name, "size"))
        elif name == "confidence" and kind.kind == "f":
            plan.append((name, "confidence"))
        elif kind.kind in "iu":
            plan.append((name, "int"))
        else:
            plan.append((name, "raw"))
    return plan


def _channels(rec: np.ndarray, plan: list[tuple[str, str]], precision: float) -> tuple[np.ndarray, np.ndarray, bytes]:
    """Attribute channels (N, C) int64 as differences in point order, their tables' direct
    sizes (log2), and the raw bytes of the fields stored raw."""
    cols: list[np.ndarray] = []
    log2d: list[int] = []
    raw = b""
    kinds = dict(plan)
    if "red" in kinds and kinds["red"] == "rgb":
        r, g, b = (rec[c].astype(np.int64) for c in ("red", "green", "blue"))
        dg = np.diff(g, prepend=0)
        cols += [dg, np.diff(r, prepend=0) - dg, np.diff(b, prepend=0) - dg]
        log2d += [6, 5, 5]
    if "nx" in kinds and kinds["nx"] == "normal":
        q = octa_encode(np.stack([rec["nx"], rec["ny"], rec["nz"]], axis=1))
        half = 1 << (NORMAL_BITS - 1)
        for k in range(2):
            d = np.diff(q[:, k], prepend=0)
            cols.append((d + half) % (1 << NORMAL_BITS) - half)  # wrapped: differences stay small
            log2d.append(6)
    raws = []
    for name, how in plan:
        if how == "size":
            cols.append(np.diff(np.rint(rec[name].astype(np.float64) / (precision * SIZE_STEP_OF_PRECISION)).astype(np.int64), prepend=0))
            log2d.append(4)
        elif how == "confidence":
            cols.append(np.diff(np.rint(rec[name].astype(np.float64) / CONFIDENCE_STEP).astype(np.int64), prepend=0))
            log2d.append(6)
        elif how == "int":
            cols.append(np.diff(rec[name].astype(np.int64), prepend=0))
            log2d.append(4)
        elif how == "raw":
            raws.append(np.ascontiguousarray(rec[name]).tobytes())
    if raws:
        raw = zlib.compress(b"".join(raws), 6)
    chan = np.stack(cols, axis=1) if cols else np.zeros((len(rec), 0), np.int64)
    return np.ascontiguousarray(chan), np.array(log2d, np.int64), raw


def _encode_chunk(rec: np.ndarray, plan: list[tuple[str, str]], precision: float, where: str, first: int,
                  header: int) -> bytes:
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputError(where, f"point {first + int(np.argmax(bad))} has a non-finite coordinate")
    q = np.floor(xyz / precision).astype(np.int64)
    off = q.min(axis=0) if len(q) else np.zeros(3, np.int64)
    q -= off
    span = int(q.max()) if len(q) else 0
    depth = max(1, span.bit_length())
    if depth > ot.MAX_DEPTH:
        raise InputError("--precision", f"{precision:g} is too fine for this cloud's extent (2**21 cells per axis at most)")
    codes = ot.morton(q)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    srec = rec[order]
    first_of = np.ones(len(codes), bool)
    first_of[1:] = codes[1:] != codes[:-1]
    vox = codes[first_of]
    counts = np.diff(np.append(np.flatnonzero(first_of), len(codes))).astype(np.int64)
    chan, log2d, raw = _channels(srec, plan, precision)
    tables, words = ot.encode_chunk(vox, counts, depth, chan, log2d)
    head = _CHUNK_HEAD.pack(len(rec), len(vox), depth, *(int(v) for v in off), len(raw))
    check = _CHECK.pack(_chunk_check(header, first, head, raw, codes, chan))
    return head + check + raw + struct.pack("<I", len(tables)) + tables.tobytes() + words.astype("<u2").tobytes()


def _chunk_log2d(plan: list[tuple[str, str]]) -> np.ndarray:
    # The direct sizes the encoder chose for each channel, in channel order (see _channels).
    kinds = dict(plan)
    out: list[int] = []
    if kinds.get("red") == "rgb":
        out += [6, 5, 5]
    if kinds.get("nx") == "normal":
        out += [6, 6]
    for _, how in plan:
        out += {"size": [4], "confidence": [6], "int": [4]}.get(how, [])
    return np.array(out, np.int64)


def _check_precision(precision: float) -> float:
    p = float(precision)
    if not math.isfinite(p) or p <= 0:
        raise InputError("--precision", f"must be a positive number, got {precision!r}")
    return p


def _check_count(count: int, where: str) -> None:
    if count > MAX_POINTS:
        raise InputError(where, f"a cloud of {count / 1e6:.0f} M points is more than the codec's {MAX_POINTS / 1e6:.0f} M")


def chunk_points(count: int) -> int:
    """Points per chunk for a cloud of ``count`` points: at most :data:`CHUNK_POINTS`, equal
    chunks, an even number of them above :data:`SPLIT_POINTS` points."""
    n = max(1, -(-count // CHUNK_POINTS))
    if count > SPLIT_POINTS:
        n += n % 2
    return max(1, -(-count // n))


def _meta(header_dtype: np.dtype, count: int, precision: float, units: str, comments: tuple[str, ...]) -> dict[str, Any]:
    per = chunk_points(count)
    return {
        "codec": CODEC,
        "points": count,
        "chunk_points": per,
        "chunks": -(-count // per),
        "precision": precision,
        "units": units,
        "fields": [[n, header_dtype[n].newbyteorder("<").str] for n in header_dtype.names or ()],
        "comments": list(comments),
    }


def _units_of(comments: tuple[str, ...]) -> str:
    for c in comments:
        if c.startswith("units "):
            return c.split(None, 1)[1]
    return "mm"


def _chunk_stream(chunks: Iterator[np.ndarray], plan: list[tuple[str, str]], precision: float, where: str,
                  header: int) -> Iterator[bytes]:
    with ThreadPoolExecutor(_threads()) as pool:
        pending = []
        first = 0
        for rec in chunks:
            pending.append(pool.submit(_encode_chunk, np.asarray(rec), plan, precision, where, first, header))
            first += len(rec)
            if len(pending) > _threads():
                yield pending.pop(0).result()
        for f in pending:
            yield f.result()


def write_cloud(path: str | os.PathLike[str], ply: str | os.PathLike[str], precision: float) -> int:
    """Code the PLY cloud ``ply`` into the container file ``path`` (atomically); returns its size."""
    precision = _check_precision(precision)
    header = read_header(ply)
    _check_count(header.count, str(ply))
    plan = _plan_fields(header.dtype, str(ply))
    meta = _meta(header.dtype, header.count, precision, _units_of(header.comments), header.comments)
    chunks = iter_ply_records(ply, meta["chunk_points"])
    return write_container(path, "cloud", meta, _chunk_stream(chunks, plan, precision, str(ply), header_crc(meta)))


def encode_cloud(rec: np.ndarray, precision: float, units: str = "mm", comments: tuple[str, ...] = ()) -> bytes:
    """Code structured point records (PLY vertex dtype, at least x, y, z) into container bytes."""
    precision = _check_precision(precision)
    _check_count(len(rec), "cloud")
    plan = _plan_fields(rec.dtype, "cloud")
    meta = _meta(rec.dtype, len(rec), precision, units, comments)
    per = meta["chunk_points"]
    parts = (rec[i : i + per] for i in range(0, len(rec), per))
    buf = io.BytesIO()
    write_stream(buf, "cloud", meta, _chunk_stream(parts, plan, precision, "cloud", header_crc(meta)))
    return buf.getvalue()


def _decode_chunk(payload: bytes, i: int, first: int, header: int, dtype: np.dtype, plan: list[tuple[str, str]],
                  precision: float, log2d: np.ndarray, where: str, out: np.ndarray | None = None) -> np.ndarray:
    """Chunk ``i``'s points (the cloud's from index ``first`` on) as records of ``dtype``, into
    ``out`` when given (a slice of the whole cloud: (points of the chunk,), or the chunk is
    corrupt) or a new array; ``header`` the container header's CRC-32 (:func:`_chunk_check`)."""
    if len(payload) < _CHUNK_HEAD.size + _CHECK.size + 4:
        raise InputError(where, f"corrupt chunk {i} (too short)")
    npts, nvox, depth, ox, oy, oz, nraw = _CHUNK_HEAD.unpack_from(payload)
    (check,) = _CHECK.unpack_from(payload, _CHUNK_HEAD.size)
    pos = _CHUNK_HEAD.size + _CHECK.size
    if (not (0 < nvox <= npts <= MAX_CHUNK_POINTS and 1 <= depth <= ot.MAX_DEPTH) or pos + nraw + 4 > len(payload)
            or (out is not None and len(out) != npts)):
        raise InputError(where, f"corrupt chunk {i} (bad chunk header)")
    raw = payload[pos : pos + nraw]
    pos += nraw
    (nt,) = struct.unpack_from("<I", payload, pos)
    pos += 4
    if pos + nt > len(payload) or (len(payload) - pos - nt) % 2:
        raise InputError(where, f"corrupt chunk {i} (bad table length)")
    tables = np.frombuffer(payload, np.uint8, nt, pos)
    words = np.frombuffer(payload, "<u2", (len(payload) - pos - nt) // 2, pos + nt).astype(np.uint16)
    codes = np.empty(npts, np.int64)
    chan = np.empty((npts, len(log2d)), np.int64)
    if ot.decode_chunk(tables, words, nvox, npts, depth, log2d, codes, chan) != 0:
        raise InputError(where, f"corrupt chunk {i} (the coded stream does not decode)")
    if _chunk_check(header, first, payload[: _CHUNK_HEAD.size], raw, codes, chan) != check:
        raise InputError(where, f"corrupt chunk {i} (what it decodes to fails its check)")
    if out is None:
        out = np.empty(npts, dtype)
    ot.voxel_centres(codes, ox, oy, oz, precision, out["x"], out["y"], out["z"])
    c = 0
    kinds = dict(plan)
    if kinds.get("red") == "rgb":
        g = np.cumsum(chan[:, 0])
        r = np.cumsum(chan[:, 1] + chan[:, 0])
        b = np.cumsum(chan[:, 2] + chan[:, 0])
        out["red"], out["green"], out["blue"] = r, g, b
        c = 3
    if kinds.get("nx") == "normal":
        m = 1 << NORMAL_BITS
        oq = np.stack([np.cumsum(chan[:, c]) % m, np.cumsum(chan[:, c + 1]) % m], axis=1)
        n = octa_decode(oq)
        out["nx"], out["ny"], out["nz"] = n[:, 0], n[:, 1], n[:, 2]
        c += 2
    raw_fields = [name for name, how in plan if how == "raw"]
    for name, how in plan:
        if how == "size":
            out[name] = np.cumsum(chan[:, c]) * (precision * SIZE_STEP_OF_PRECISION)
            c += 1
        elif how == "confidence":
            out[name] = np.cumsum(chan[:, c]) * CONFIDENCE_STEP
            c += 1
        elif how == "int":
            out[name] = np.cumsum(chan[:, c])
            c += 1
    if raw_fields:
        try:
            blob = zlib.decompress(raw)
        except zlib.error:
            raise InputError(where, f"corrupt chunk {i} (raw fields)") from None
        at = 0
        for name in raw_fields:
            nbytes = npts * dtype[name].itemsize
            if at + nbytes > len(blob):
                raise InputError(where, f"corrupt chunk {i} (raw fields)")
            out[name] = np.frombuffer(blob, dtype[name], npts, at)
            at += nbytes
    return out


def _open(source: str | os.PathLike[str] | bytes) -> tuple[dict[str, Any], Iterator[bytes], np.dtype, str, int]:
    where = "<bytes>" if isinstance(source, bytes | bytearray | memoryview) else str(source)
    header, chunks = open_container(source, kind="cloud")
    meta = header.meta
    codec = meta.get("codec")
    if isinstance(codec, str) and codec != CODEC and codec.startswith("octree-"):
        raise InputError(where, f"cloud codec {codec!r} is not supported (this build reads {CODEC!r}; re-encode the cloud)")
    try:
        dtype = np.dtype([(str(n), str(t)) for n, t in meta["fields"]])
        per = header_int(meta, "chunk_points")
        points = header_int(meta, "points")
        ok = (meta.get("codec") == CODEC and 0 < per <= MAX_CHUNK_POINTS and points >= 0
              and 0 < float(meta["precision"]) < math.inf and meta["chunks"] == -(-points // per))
    except (KeyError, TypeError, ValueError, OverflowError):  # OverflowError: float() of a 400-digit integer
        ok = False
    if not ok:
        raise InputError(where, "corrupt or unsupported cloud header")
    if points > MAX_POINTS:
        claim = f"{points / 1e6:.0f} M points" if points < 10**15 else "over 10^15 points"
        raise InputError(where, f"corrupt or hostile cloud header: it claims {claim}, more than the codec's "
                                f"{MAX_POINTS / 1e6:.0f} M")
    return meta, chunks, dtype, where, header.crc


def _decode_chunks(opened: tuple[dict[str, Any], Iterator[bytes], np.dtype, str, int],
                   whole: np.ndarray | None = None) -> Iterator[np.ndarray]:
    """Decode the chunks of a container (``opened``: what :func:`_open` returns) on the thread
    pool, yielding each in order; into its slice of ``whole`` (``(points,)`` of the cloud's
    dtype) when given, else into a new array."""
    meta, chunks, dtype, where, header = opened
    plan = _plan_fields(dtype, where)
    log2d = _chunk_log2d(plan)
    precision = float(meta["precision"])
    per = int(meta["chunk_points"])
    with ThreadPoolExecutor(_threads()) as pool:
        pending = []
        # The container yields meta["chunks"] chunks, ceil(points / per) (checked by _open), and
        # each must fill its slice of ``whole`` exactly (checked by _decode_chunk).
        for i, payload in enumerate(chunks):
            into = None if whole is None else whole[i * per : (i + 1) * per]
            pending.append(pool.submit(_decode_chunk, payload, i, i * per, header, dtype, plan, precision, log2d, where,
                                       into))
            if len(pending) > _threads():
                yield pending.pop(0).result()
        for f in pending:
            yield f.result()


def iter_cloud(source: str | os.PathLike[str] | bytes) -> Iterator[np.ndarray]:
    """Decode a cloud container chunk by chunk: structured records of the input's PLY dtype."""
    yield from _decode_chunks(_open(source))


def decode_cloud(source: str | os.PathLike[str] | bytes) -> np.ndarray:
    """The whole decoded cloud as one structured array (every chunk decoded into its slice)."""
    opened = _open(source)
    out = np.empty(int(opened[0]["points"]), opened[2])
    for _ in _decode_chunks(opened, out):
        pass
    return out


def read_cloud_to_ply(source: str | os.PathLike[str], out: str | os.PathLike[str]) -> Path:
    """Decode a cloud container into a binary PLY (the cloud contract), atomically."""
    meta, _, dtype, _, _ = _open(source)
    out = Path(out)
    # the records' bytes, checked before minutes of decoding end in a full disk
    need = int(meta["points"]) * dtype.itemsize
    room = out.parent
    while not room.exists() and room != room.parent:
        room = room.parent
    free = shutil.disk_usage(room).free
    if need > free:
        raise InputError(str(out), f"the decoded cloud needs {need / 1e6:,.1f} MB, and its folder has {free / 1e6:,.1f} MB free")
    comments = tuple(str(c) for c in meta.get("comments", ()))
    return write_ply_records(out, iter_cloud(source), int(meta["points"]), dtype, comments)
