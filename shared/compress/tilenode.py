"""Octree coding of one Potree tile node ("GRAYLIGHT_OCTREE" node encoding), lossless.

A node of Potree 2.0 tiles (:mod:`shared.render.octree`) stores ``numPoints`` records of
``position`` 3 x int32 (the tiles' integer grid: world = int * scale + offset), ``rgb`` 3 x uint16,
``NormalX/Y/Z`` float32 and ``size`` float32 (those the tiles carry). This codec stores the same
records, every bit of them, in the order of an octree over the node's integer positions (a
permutation of the plain node: a Potree node is drawn whole, its point order means nothing):

* positions: an occupancy octree over the cube of edge ``2**(D + k)`` integer steps at the
  points' minimum corner, one byte a non-empty cell breadth first (bit ``j`` set when child ``j``
  is occupied; child bits 4 = x, 2 = y, 1 = z, Potree's order), ``D`` levels down to cells of
  ``2**k`` steps; then each cell's point count (duplicates counted) and each point's offset in
  its cell, ``k`` bits an axis (byte planes). ``D`` is chosen per node where descending further
  would cost more occupancy bytes than it saves offset bits (a G-PCC-like direct mode for
  isolated points).
* attributes in that order, predicted from the previous point and split into byte planes:
  colour as green and the red and blue differences from green (8-bit when every value is a
  multiple of 257, as Graylight's 8-bit colour scaled to Potree's 16 bits is), floats as the
  zig-zagged difference of their bit patterns.
* one zlib (RFC 1950, "deflate") stream the browser inflates natively
  (``DecompressionStream("deflate")``) in the viewer's decoder worker; the byte planes of offsets
  and floats that are noise (order-0 entropy >= :data:`RAW_ENTROPY` bits a byte) follow it raw,
  since deflate cannot shrink them and inflating them would only cost the browser time.

Node bytes (little-endian)::

    head     "GTN1", u32 numPoints, u32 payload bytes (inflated), u32 zlib stream bytes,
             u32 CRC-32 of the raw planes
    zlib     payload: i32 origin[3], u8 D, u8 k, u8 flags (1 rgb, 2 rgb 8-bit, 4 normal, 8 size),
             u8 0, u32 occupancy bytes, u32 cells, u32 count bytes, u32 raw-plane mask,
             occupancy bytes, counts (LEB128 of count - 1 a cell),
             offset planes (ceil(k / 8) planes of N bytes an axis, x y z, low byte first),
             colour planes (N bytes a plane: G, R-G, B-G deltas mod 256; or the low then high
             byte of each 16-bit delta), normal planes (4 an axis, low byte first), size planes (4)
             -- leaving out the planes the mask marks raw
    raw      the planes the mask marks (bit i: the i-th offset, normal or size plane), in order

The viewer's decoder (``services/viewer/src/tilenode.ts``) reads exactly this. A node whose bytes
do not parse is an :class:`InputError`, never wrong points.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from shared.core.errors import InputError
from shared.core.jit import empty, kernel, zeros
from shared.core.morton import spread21

#: The metadata.json ``encoding`` of tiles whose nodes this module codes.
ENCODING = "GRAYLIGHT_OCTREE"
MAGIC = b"GTN1"
_HEAD = struct.Struct("<4sIIII")
_PAYLOAD_HEAD = struct.Struct("<3iBBBBIIII")
#: A byte plane whose order-0 entropy is at least this (bits a byte) is stored raw, outside the
#: zlib stream: deflate cannot shrink it, and the browser then inflates fewer bytes.
RAW_ENTROPY = 7.0
_MAX_LEVELS = 21  # occupancy levels an uint64 Morton key holds (3 x 21 bits)
_FLAG_RGB, _FLAG_RGB8, _FLAG_NORMAL, _FLAG_SIZE = 1, 2, 4, 8
#: zlib level: 6 codes about as small as 9 here, twice as fast.
ZLIB_LEVEL = 6

_FIELDS = ("position", "rgb", "normal", "size")


def node_dtype(rgb: bool, normal: bool, size: bool) -> np.dtype:
    """The tiles' record (34 bytes with everything) holding the attributes asked for."""
    fields = [("position", "<i4", (3,))]
    if rgb:
        fields.append(("rgb", "<u2", (3,)))
    if normal:
        fields.append(("normal", "<f4", (3,)))
    if size:
        fields.append(("size", "<f4"))
    return np.dtype(fields)


def _codec_dtype(dtype: np.dtype, where: str = "records") -> np.dtype:
    """The codec's view of a tiles record ``dtype`` (normals as one (3,) field): the packed record
    :mod:`shared.render.octree` writes, normals as ``normal`` (3,) or as Potree's NormalX/Y/Z
    (metadata.json's list). Raises :class:`InputError` for any other layout."""
    names = list(dtype.names or ())
    canon, types, i = [], [], 0
    while i < len(names):
        if names[i : i + 3] == ["NormalX", "NormalY", "NormalZ"]:
            canon.append("normal")
            types.append(("<f4", (3,)) if all(dtype.fields[f][0] == np.dtype("<f4") for f in names[i : i + 3]) else None)
            i += 3
        else:
            canon.append(names[i])
            sub = dtype.fields[names[i]][0]
            types.append((sub.base.str, sub.shape))
            i += 1
    want = node_dtype("rgb" in canon, "normal" in canon, "size" in canon)
    expect = [(want.fields[f][0].base.str, want.fields[f][0].shape) for f in want.names]
    if canon != list(want.names) or types != expect or dtype.itemsize != want.itemsize:
        raise InputError(where, f"records {dtype} cannot be octree-coded (position int32 x 3, then any of "
                         "rgb uint16 x 3, normal float32 x 3, size float32, packed)")  # fmt: skip
    return want


# --------------------------------------------------------------------------- kernels


@kernel
def _keys(pos: np.ndarray, origin: np.ndarray, drop: int) -> np.ndarray:
    """(N,) uint64 Morton keys (x the high bit of a triple) of ``(pos - origin) >> drop``."""
    n = pos.shape[0]
    out = empty(n, np.uint64)
    for i in range(n):
        x = (np.int64(pos[i, 0]) - origin[0]) >> drop
        y = (np.int64(pos[i, 1]) - origin[1]) >> drop
        z = (np.int64(pos[i, 2]) - origin[2]) >> drop
        out[i] = np.uint64((spread21(x) << 2) | (spread21(y) << 1) | spread21(z))
    return out


@kernel
def _cells_per_level(keys: np.ndarray, levels: int) -> np.ndarray:
    """(levels + 1,) int64: occupied cells at every level 0..levels of sorted ``keys``."""
    cells = zeros(levels + 1, np.int64)
    n = keys.shape[0]
    if n == 0:
        return cells
    split = zeros(levels + 1, np.int64)  # pairs of neighbours first apart at that level
    for i in range(1, n):
        d = keys[i] ^ keys[i - 1]
        if d == 0:
            continue
        h = 0
        while d >> np.uint64(h + 1):
            h += 1
        split[levels - h // 3] += 1
    c = 1
    for lv in range(levels + 1):
        c += split[lv]
        cells[lv] = c
    return cells


@kernel
def _geometry(pos: np.ndarray, origin: np.ndarray, keys: np.ndarray, order: np.ndarray, levels: int,
              depth: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:  # fmt: skip
    """Occupancy bytes (breadth first, ``depth`` levels), LEB128 counts of the cells at ``depth``,
    the offsets in cells (k bits an axis as ceil(k / 8) byte planes an axis, low byte first),
    and the number of cells. ``keys`` are the sorted
    Morton keys at ``levels`` levels, ``order`` the sorting permutation of ``pos``."""
    n = keys.shape[0]
    total = 0
    occ = zeros(max(1, n * depth + 1), np.uint8)
    for lv in range(depth):
        s_node = np.uint64(3 * (levels - lv))
        s_child = np.uint64(3 * (levels - lv - 1))
        i = 0
        while i < n:
            cell = keys[i] >> s_node
            b = 0
            while i < n and (keys[i] >> s_node) == cell:
                b |= 1 << int((keys[i] >> s_child) & np.uint64(7))
                i += 1
            occ[total] = b
            total += 1
    counts = zeros(max(1, 5 * n), np.uint8)
    nc = 0
    cells = 0
    s_leaf = np.uint64(3 * (levels - depth))
    i = 0
    while i < n:
        cell = keys[i] >> s_leaf
        j = i
        while j < n and (keys[j] >> s_leaf) == cell:
            j += 1
        v = j - i - 1
        while v >= 0x80:
            counts[nc] = np.uint8((v & 0x7F) | 0x80)
            nc += 1
            v >>= 7
        counts[nc] = np.uint8(v)
        nc += 1
        cells += 1
        i = j
    nb = (k + 7) // 8
    offsets = empty(3 * nb * n, np.uint8)
    mask = np.int64((1 << k) - 1)
    for a in range(3):
        for i in range(n):
            r = (np.int64(pos[order[i], a]) - origin[a]) & mask
            for j in range(nb):
                offsets[(a * nb + j) * n + i] = (r >> (8 * j)) & 0xFF
    return occ[:total].copy(), counts[:nc].copy(), offsets, cells


@kernel
def _colour_planes(rgb: np.ndarray, order: np.ndarray, eight: bool) -> np.ndarray:
    """Colour in point ``order``: G, R-G, B-G, each the difference from the previous point
    (mod 256 for 8-bit colour = value / 257, else mod 65536 as a low and a high byte plane)."""
    n = order.shape[0]
    planes = 3 if eight else 6
    out = empty(planes * n, np.uint8)
    pg = pr = pb = 0
    for i in range(n):
        p = order[i]
        if eight:
            r, g, b = rgb[p, 0] // 257, rgb[p, 1] // 257, rgb[p, 2] // 257
            m = 0xFF
        else:
            r, g, b = rgb[p, 0], rgb[p, 1], rgb[p, 2]
            m = 0xFFFF
        cg = np.int64(g)
        cr = (np.int64(r) - np.int64(g)) & m
        cb = (np.int64(b) - np.int64(g)) & m
        dg, dr, db = (cg - pg) & m, (cr - pr) & m, (cb - pb) & m
        pg, pr, pb = cg, cr, cb
        if eight:
            out[i], out[n + i], out[2 * n + i] = dg, dr, db
        else:
            out[i], out[n + i] = dg & 0xFF, dg >> 8
            out[2 * n + i], out[3 * n + i] = dr & 0xFF, dr >> 8
            out[4 * n + i], out[5 * n + i] = db & 0xFF, db >> 8
    return out


@kernel
def _float_planes(bits: np.ndarray, order: np.ndarray) -> np.ndarray:
    """(N, C) uint32 float bit patterns in point ``order``: per column, the zig-zagged
    difference from the previous point's, as four byte planes (low byte first)."""
    n = order.shape[0]
    ncol = bits.shape[1]
    out = empty(4 * ncol * n, np.uint8)
    for c in range(ncol):
        prev = np.int64(0)
        base = 4 * c * n
        for i in range(n):
            v = np.int64(bits[order[i], c])
            d = (v - prev) & 0xFFFFFFFF
            prev = v
            zz = ((d << 1) ^ (0xFFFFFFFF if d & 0x80000000 else 0)) & 0xFFFFFFFF
            out[base + i] = zz & 0xFF
            out[base + n + i] = (zz >> 8) & 0xFF
            out[base + 2 * n + i] = (zz >> 16) & 0xFF
            out[base + 3 * n + i] = zz >> 24
    return out


@kernel
def _decode_geometry(occ: np.ndarray, counts: np.ndarray, offsets: np.ndarray, origin: np.ndarray,
                     depth: int, k: int, ncells: int, n: int) -> np.ndarray:  # fmt: skip
    """(n, 3) int32 positions from the geometry streams; raises ValueError when they disagree."""
    cx = zeros(1, np.int64)
    cy = zeros(1, np.int64)
    cz = zeros(1, np.int64)
    at = 0
    for _lv in range(depth):
        m = cx.shape[0]
        if at + m > occ.shape[0]:
            raise ValueError("occupancy stream is short")
        nxt = 0
        for i in range(m):
            b = occ[at + i]
            if b == 0:
                raise ValueError("an occupied cell has no children")
            for j in range(8):
                if b & (1 << j):
                    nxt += 1
        nx = empty(nxt, np.int64)
        ny = empty(nxt, np.int64)
        nz = empty(nxt, np.int64)
        w = 0
        for i in range(m):
            b = occ[at + i]
            for j in range(8):
                if b & (1 << j):
                    nx[w] = 2 * cx[i] + ((j >> 2) & 1)
                    ny[w] = 2 * cy[i] + ((j >> 1) & 1)
                    nz[w] = 2 * cz[i] + (j & 1)
                    w += 1
        at += m
        cx, cy, cz = nx, ny, nz
    if at != occ.shape[0] or cx.shape[0] != ncells:
        raise ValueError("occupancy stream does not match the cell count")
    out = empty((n, 3), np.int32)
    p = 0
    c_at = 0
    nb = (k + 7) // 8
    for c in range(ncells):
        v = 0
        shift = 0
        while True:
            if c_at >= counts.shape[0] or shift > 28:
                raise ValueError("count stream is short or malformed")
            byte = np.int64(counts[c_at])
            c_at += 1
            v |= (byte & 0x7F) << shift
            shift += 7
            if byte < 0x80:
                break
        m = v + 1
        if p + m > n:
            raise ValueError("cells hold more points than the node")
        for _ in range(m):
            for a in range(3):
                r = np.int64(0)
                for j in range(nb):
                    r |= np.int64(offsets[(a * nb + j) * n + p]) << (8 * j)
                if r >> k:
                    raise ValueError("a point's offset lies outside its cell")
                base = cx[c] if a == 0 else (cy[c] if a == 1 else cz[c])
                out[p, a] = np.int32(origin[a] + (base << k) + r)
            p += 1
    if p != n or c_at != counts.shape[0]:
        raise ValueError("cells hold fewer points than the node")
    return out


@kernel
def _decode_colour(planes: np.ndarray, n: int, eight: bool) -> np.ndarray:
    out = empty((n, 3), np.uint16)
    m = 0xFF if eight else 0xFFFF
    g = r = b = 0
    for i in range(n):
        if eight:
            dg, dr, db = np.int64(planes[i]), np.int64(planes[n + i]), np.int64(planes[2 * n + i])
        else:
            dg = np.int64(planes[i]) | (np.int64(planes[n + i]) << 8)
            dr = np.int64(planes[2 * n + i]) | (np.int64(planes[3 * n + i]) << 8)
            db = np.int64(planes[4 * n + i]) | (np.int64(planes[5 * n + i]) << 8)
        g, r, b = (g + dg) & m, (r + dr) & m, (b + db) & m
        scale = 257 if eight else 1
        out[i, 0] = ((r + g) & m) * scale
        out[i, 1] = g * scale
        out[i, 2] = ((b + g) & m) * scale
    return out


@kernel
def _decode_floats(planes: np.ndarray, n: int, ncol: int) -> np.ndarray:
    out = empty((n, ncol), np.uint32)
    for c in range(ncol):
        base = 4 * c * n
        prev = np.int64(0)
        for i in range(n):
            zz = (np.int64(planes[base + i]) | (np.int64(planes[base + n + i]) << 8)
                  | (np.int64(planes[base + 2 * n + i]) << 16) | (np.int64(planes[base + 3 * n + i]) << 24))  # fmt: skip
            d = (zz >> 1) ^ (0xFFFFFFFF if zz & 1 else 0)
            prev = (prev + d) & 0xFFFFFFFF
            out[i, c] = prev
    return out


# --------------------------------------------------------------------------- choice of depth


def _choose_depth(cells: np.ndarray, n: int, levels: int, residual_bits: int) -> int:
    """Occupancy levels that minimise an estimate of the coded bits: an occupancy byte costs
    about 3.3 bits after deflate plus 2 bits a further child, a count about log2(1 + N / cells),
    and every level left to the offsets 3 bits a point."""
    best, best_bits = 0, np.inf
    occ_bits = 0.0
    for d in range(levels + 1):
        c = float(cells[d])
        bits = occ_bits + 3.0 * n * (residual_bits - d) + c * np.log2(1.0 + n / c)
        if bits < best_bits:
            best, best_bits = d, bits
        if d < levels:
            occ_bits += 3.3 * c + 2.0 * (float(cells[d + 1]) - c)
    return best


# --------------------------------------------------------------------------- public


def encode_node(records: np.ndarray, level: int = ZLIB_LEVEL) -> bytes:
    """Octree-code one node's records (lossless).

    Parameters
    ----------
    records : (N,) structured array with ``position`` (3,) int32 and any of ``rgb`` (3,) uint16,
        ``normal`` (3,) float32 (or NormalX/Y/Z), ``size`` float32, in that order (the tiles'
        record, :func:`node_dtype`).
    level : zlib level of the entropy stage.

    Returns
    -------
    The node's bytes (see the module docstring); :func:`decode_node` gives back the same records
    in octree order.
    """
    records = np.ascontiguousarray(records).view(_codec_dtype(records.dtype))
    names = records.dtype.names or ()
    n = int(records.shape[0])
    pos = np.ascontiguousarray(records["position"]).astype(np.int32, copy=False)
    flags = 0
    if n == 0:
        origin = np.zeros(3, np.int64)
    else:
        origin = pos.min(axis=0).astype(np.int64)
    extent = int((pos.max(axis=0).astype(np.int64) - origin).max()) if n else 0
    total_bits = extent.bit_length()  # levels to single integer steps
    levels = min(total_bits, _MAX_LEVELS)
    drop = total_bits - levels
    keys = _keys(pos, origin, drop)
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    cells = _cells_per_level(keys, levels)
    depth = _choose_depth(cells, n, levels, total_bits) if n else 0
    k = total_bits - depth
    occ, counts, offsets, ncells = _geometry(pos, origin, keys, order, levels, depth, k)
    if n == 0:
        ncells = 0
        counts = counts[:0]
    packed = [b"", occ.tobytes(), counts.tobytes()]
    raw: list[bytes] = []
    optional = [offsets.reshape(-1, n)] if n else []  # planes that may go raw, in stream order
    colour = b""
    if "rgb" in names:
        rgb = np.ascontiguousarray(records["rgb"])
        eight = bool(np.all(rgb % 257 == 0))
        flags |= _FLAG_RGB | (_FLAG_RGB8 if eight else 0)
        colour = _colour_planes(rgb, order, eight).tobytes()
    if "normal" in names:
        flags |= _FLAG_NORMAL
        if n:
            optional.append(_float_planes(np.ascontiguousarray(records["normal"]).view(np.uint32), order).reshape(-1, n))
    if "size" in names:
        flags |= _FLAG_SIZE
        if n:
            sz = np.ascontiguousarray(records["size"]).view(np.uint32).reshape(-1, 1)
            optional.append(_float_planes(sz, order).reshape(-1, n))
    mask = 0
    bit = 0
    for group, planes in enumerate(optional):
        for plane in planes:
            if _entropy(plane) >= RAW_ENTROPY:
                mask |= 1 << bit
                raw.append(plane.tobytes())
            else:
                packed.append(plane.tobytes())
            bit += 1
        if group == 0:
            packed.append(colour)  # colour sits between the offsets and the floats
    if not optional:
        packed.append(colour)
    packed[0] = _PAYLOAD_HEAD.pack(*(int(v) for v in origin), depth, k, flags, 0, len(occ), ncells, len(counts), mask)
    payload = b"".join(packed)
    deflated = zlib.compress(payload, level)
    rawbytes = b"".join(raw)
    return b"".join([_HEAD.pack(MAGIC, n, len(payload), len(deflated), zlib.crc32(rawbytes)), deflated, rawbytes])


def _entropy(plane: np.ndarray) -> float:
    """Order-0 entropy of a (N,) uint8 plane, bits a byte."""
    counts = np.bincount(plane, minlength=256)
    p = counts[counts > 0] / plane.shape[0]
    return float(-(p * np.log2(p)).sum())


def decode_node(data: bytes | memoryview, dtype: np.dtype, count: int | None = None, *, where: str = "node") -> np.ndarray:
    """The records of one octree-coded node.

    Parameters
    ----------
    data : the node's bytes as :func:`encode_node` wrote them.
    dtype : the tiles' record dtype (its fields say which attributes the node must carry;
        normals as ``normal`` (3,) or NormalX/Y/Z).
    count : points the hierarchy announces (checked when given).
    where : names the node in errors.

    Returns
    -------
    (N,) records of ``dtype`` in octree order (the plain node's records, permuted). Raises :class:`InputError` when the bytes are
    not a well-formed node of that layout.
    """
    data = bytes(data)
    if not data and count == 0:  # an empty node (an ancestor kept for the hierarchy): no bytes
        return np.empty(0, dtype)
    if len(data) < _HEAD.size:
        raise InputError(where, f"octree-coded node of {len(data)} bytes is truncated")
    magic, n, plen, zlen, crc = _HEAD.unpack_from(data)
    if magic != MAGIC:
        raise InputError(where, f"not an octree-coded node (magic {magic!r}, expected {MAGIC!r})")
    if count is not None and n != count:
        raise InputError(where, f"node holds {n} points, the hierarchy says {count}")
    if _HEAD.size + zlen > len(data):
        raise InputError(where, f"octree-coded node of {len(data)} bytes is truncated (its zlib stream has {zlen})")
    # Inflate at most one byte more than the head announces (a corrupt node cannot expand into
    # gigabytes), and accept the stream only if it ends there and nothing follows it, as the
    # viewer's DecompressionStream requires.
    inflater = zlib.decompressobj()
    try:
        payload = inflater.decompress(data[_HEAD.size : _HEAD.size + zlen], plen + 1)
    except zlib.error as exc:
        raise InputError(where, f"octree-coded node is corrupt ({exc})") from None
    if len(payload) != plen or plen < _PAYLOAD_HEAD.size or not inflater.eof:
        raise InputError(where, f"octree-coded node inflates to {len(payload)}+ bytes, its head says {plen}")
    if inflater.unused_data:
        raise InputError(where, f"octree-coded node has {len(inflater.unused_data)} bytes after its zlib stream")
    ox, oy, oz, depth, k, flags, _pad, nocc, ncells, ncount, mask = _PAYLOAD_HEAD.unpack_from(payload)
    given = np.dtype(dtype)
    dtype = _codec_dtype(given, where)
    names = dtype.names or ()
    want = (_FLAG_RGB if "rgb" in names else 0) | (_FLAG_NORMAL if "normal" in names else 0) | (
        _FLAG_SIZE if "size" in names else 0)  # fmt: skip
    if flags & ~_FLAG_RGB8 != want:
        raise InputError(where, f"node attributes (flags {flags}) do not match the tiles' record {names}")
    if k > 32 or depth > _MAX_LEVELS:
        raise InputError(where, f"octree-coded node's depth {depth} or cell bits {k} are out of range")
    eight = bool(flags & _FLAG_RGB8)
    nb = (k + 7) // 8
    groups = [3 * nb, 12 if flags & _FLAG_NORMAL else 0, 4 if flags & _FLAG_SIZE else 0]  # optional planes
    nplanes = sum(groups) if n else 0
    nraw = bin(mask).count("1")
    ncolour = ((3 if eight else 6) * n) if flags & _FLAG_RGB else 0
    if mask >> nplanes or _PAYLOAD_HEAD.size + nocc + ncount + ncolour + (nplanes - nraw) * n != plen:
        raise InputError(where, "octree-coded node's streams do not add up to its payload")
    if _HEAD.size + zlen + nraw * n != len(data):
        raise InputError(where, f"octree-coded node has {len(data)} bytes, its streams {_HEAD.size + zlen + nraw * n}")
    if zlib.crc32(data[_HEAD.size + zlen :]) != crc:
        raise InputError(where, "octree-coded node is corrupt (its raw planes fail their CRC-32)")
    buf = np.frombuffer(payload, np.uint8)
    rawbuf = np.frombuffer(data, np.uint8, offset=_HEAD.size + zlen)
    at = _PAYLOAD_HEAD.size
    occ = buf[at : at + nocc]
    counts = buf[at + nocc : at + nocc + ncount]
    at += nocc + ncount
    raw_at = 0
    plane = 0

    def planes(m: int) -> np.ndarray:
        """The next ``m`` optional planes, (m * n,) uint8, from the payload or the raw bytes."""
        nonlocal at, raw_at, plane
        out = np.empty(m * n, np.uint8)
        for j in range(m):
            if mask >> plane & 1:
                out[j * n : (j + 1) * n] = rawbuf[raw_at : raw_at + n]
                raw_at += n
            else:
                out[j * n : (j + 1) * n] = buf[at : at + n]
                at += n
            plane += 1
        return out

    offsets = planes(groups[0]) if n else np.empty(0, np.uint8)
    colour = buf[at : at + ncolour]
    at += ncolour
    origin = np.array([ox, oy, oz], np.int64)
    out = np.empty(n, dtype)
    if n:
        try:
            out["position"] = _decode_geometry(occ, counts, offsets, origin, depth, k, ncells, n)
        except ValueError as exc:
            raise InputError(where, f"octree-coded node is corrupt ({exc})") from None
        if flags & _FLAG_RGB:
            out["rgb"] = _decode_colour(colour, n, eight)
        if flags & _FLAG_NORMAL:
            out["normal"] = _decode_floats(planes(12), n, 3).view(np.float32)
        if flags & _FLAG_SIZE:
            out["size"] = _decode_floats(planes(4), n, 1).view(np.float32)[:, 0]
    return out.view(given)


#: Node decoders by metadata.json encoding, for :func:`shared.formats.potree.open_tiles`.
DECODERS = {ENCODING: decode_node}
