"""Out-of-core builder of Potree 2.0 level-of-detail tiles from a PLY point cloud.

In: a cloud PLY per :mod:`shared.ply` (``x, y, z`` required; colour, normal and the world
sample ``size`` = Z / f_camera carried when present). Out: a folder readable by Potree 2.x
viewers (``OctreeLoader.js``)::

    metadata.json   version "2.0", points, hierarchy {firstChunkSize, stepSize, depth},
                    offset, scale, spacing, cubic boundingBox, encoding "DEFAULT", attributes
    hierarchy.bin   22-byte node records (type u8, childMask u8, numPoints u32, byteOffset i64,
                    byteSize i64), breadth-first per hierarchy chunk, proxies every 4 levels
    octree.bin      every node's points once (additive LOD), 34 bytes a point:
                    position 3 x int32 (world = int * scale + offset), rgb 3 x uint16
                    (8-bit colour * 257), NormalX/NormalY/NormalZ float32, size float32
                    (world units; the scanner's Z / f_camera)

Level-of-detail scheme: positions are quantised, then Morton-coded at 21 bits an axis with
Potree's child order (bit 2 = x, bit 1 = y, bit 0 = z). A node at level L has spacing
``cube / 128 / 2**L``; an inner node keeps the first not-yet-taken point (in Morton order)
of every cell of its 128^3 grid — a grid sampler, so coverage is even — and hands the rest to
its children; a node with at most ``max_leaf`` remaining points keeps them all (a leaf).

Out of core, in three passes whose memory does not grow with the cloud:

1. :func:`plan_tiles` streams the PLY for bounds and attribute ranges (rejecting NaN or
   infinite coordinates), then again to count points per cell of a 128^3 grid, picks
   *chunks* (the largest octree nodes holding at most ``max_chunk`` points) and streams the
   points once more into one file per chunk.
2. :func:`build_chunk` builds one chunk independently (the parallel unit: a process
   in-process, a task under the job service). Because every cell a node at level L samples
   from (level L + 7) lies inside one chunk (chunks sit at level <= 7), a chunk can also
   compute its exact share of the nodes above it.
3. :func:`merge_tiles` concatenates the pieces into ``octree.bin``, writes
   ``hierarchy.bin`` and ``metadata.json`` and renames the finished folder into place.

:func:`build_tiles` runs all three. Units are those of the PLY (millimetres for Graylight).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numba
import numpy as np

from shared.errors import InputError
from shared.ply import iter_ply_chunks, read_header

log = logging.getLogger(__name__)

#: One point in ``octree.bin`` (34 bytes, packed, little-endian).
POINT_DTYPE = np.dtype(
    [("position", "<i4", (3,)), ("rgb", "<u2", (3,)), ("normal", "<f4", (3,)), ("size", "<f4")]
)
MORTON_BITS = 21  # bits an axis in a 63-bit Morton code
GRID_LEVELS = 7  # 2**7 = 128 cells a side: node spacing = node cube / 128
COUNT_LEVEL = 7  # level of the counting grid; chunks are never deeper than this
HIERARCHY_STEP = 4  # levels per hierarchy chunk (PotreeConverter's stepSize)
BYTES_PER_NODE = 22
MAX_DEPTH = MORTON_BITS - GRID_LEVELS  # deepest level whose sampling grid the codes resolve
READ_CHUNK = 1 << 20
PLAN_FILE = "plan.json"
MAX_OPEN_FILES = 256


@dataclass
class TilePlan:
    """What pass 1 found and decided; saved as ``plan.json`` in the work folder."""

    source: str
    name: str
    points: int
    offset: list[float]  # world position of integer 0 (= cube minimum)
    scale: float  # world units per integer step
    cube_size: float  # edge of the cubic bounding box, world units
    qsize: int  # edge of the cube in integer steps
    attr_min: dict[str, list[float]]
    attr_max: dict[str, list[float]]
    chunks: list[dict] = field(default_factory=list)  # {"level", "prefix", "points", "file"}
    max_leaf: int = 10_000
    has: dict[str, bool] = field(default_factory=dict)
    bounds_min: list[float] = field(default_factory=list)  # tight bounds of the points
    bounds_max: list[float] = field(default_factory=list)


# --------------------------------------------------------------------------- Morton codes


@numba.njit(cache=True, inline="always")
def _spread(v: np.int64) -> np.int64:
    v &= 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


@numba.njit(cache=True)
def morton_codes(ipos: np.ndarray, qsize: int) -> np.ndarray:
    """Morton codes of integer positions.

    Parameters
    ----------
    ipos : (N, 3) int32 positions in ``[0, qsize)``.
    qsize : edge of the cube in integer steps.

    Returns
    -------
    (N,) int64 codes, 3 x 21 bits, x the most significant bit of every triple (Potree order).
    """
    n = ipos.shape[0]
    out = np.empty(n, np.int64)
    scale = (1 << MORTON_BITS) / qsize
    top = (1 << MORTON_BITS) - 1
    for i in range(n):
        mx = min(np.int64(ipos[i, 0] * scale), top)
        my = min(np.int64(ipos[i, 1] * scale), top)
        mz = min(np.int64(ipos[i, 2] * scale), top)
        out[i] = (_spread(mx) << 2) | (_spread(my) << 1) | _spread(mz)
    return out


@numba.njit(cache=True)
def _count_unassigned(assigned: np.ndarray, lo: int, hi: int) -> int:
    c = 0
    for i in range(lo, hi):
        if assigned[i] < 0:
            c += 1
    return c


@numba.njit(cache=True)
def _sample(codes: np.ndarray, assigned: np.ndarray, lo: int, hi: int, shift: int, node: int) -> int:
    """Give ``node`` the first unassigned point of every cell (``code >> shift``) in [lo, hi)."""
    last = np.int64(-1)
    taken = 0
    for i in range(lo, hi):
        if assigned[i] < 0:
            key = codes[i] >> shift
            if key != last:
                assigned[i] = node
                last = key
                taken += 1
    return taken


@numba.njit(cache=True)
def _take_all(assigned: np.ndarray, lo: int, hi: int, node: int) -> int:
    taken = 0
    for i in range(lo, hi):
        if assigned[i] < 0:
            assigned[i] = node
            taken += 1
    return taken


@numba.njit(cache=True)
def _gather_rows(src: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``src[order]`` for a 2-D byte array (numpy's fancy indexing of records is far slower)."""
    width = src.shape[1]
    out = np.empty((order.shape[0], width), src.dtype)
    for i in range(order.shape[0]):
        k = order[i]
        for j in range(width):  # an explicit byte loop: row slices cost an object each
            out[i, j] = src[k, j]
    return out


def _permute(rec: np.ndarray, order: np.ndarray) -> np.ndarray:
    raw = rec.view(np.uint8).reshape(rec.shape[0], rec.dtype.itemsize)
    return _gather_rows(raw, order).view(rec.dtype).reshape(-1)


@numba.njit(cache=True)
def _counting_order(keys: np.ndarray, nkeys: int) -> tuple[np.ndarray, np.ndarray]:
    """Stable order sorting small non-negative integer ``keys``; also the (nkeys + 1,) bucket starts."""
    starts = np.zeros(nkeys + 1, np.int64)
    for k in keys:
        starts[k + 1] += 1
    for k in range(nkeys):
        starts[k + 1] += starts[k]
    fill = starts[:-1].copy()
    order = np.empty(keys.shape[0], np.int64)
    for i in range(keys.shape[0]):
        k = keys[i]
        order[fill[k]] = i
        fill[k] += 1
    return order, starts


def node_name(level: int, prefix: int) -> str:
    """Potree node name ("r" then one child digit a level) of the node ``prefix`` at ``level``."""
    digits = [str((prefix >> (3 * (level - 1 - k))) & 7) for k in range(level)]
    return "r" + "".join(digits)


# --------------------------------------------------------------------------- pass 1: plan


@dataclass
class _Fields:
    """Field views of one slice of the cloud (memory-mapped for little-endian binary PLY)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    rgb: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    normal: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    size: np.ndarray | None

    def __len__(self) -> int:
        return int(self.x.shape[0])


def _iter_fields(path: Path, chunk: int = READ_CHUNK):
    """Yield :class:`_Fields` of at most ``chunk`` points; no copies for little-endian binary PLY."""
    header = read_header(path)
    names = set(header.dtype.names or ())
    if header.fmt == "binary_little_endian":
        need = header.data_offset + header.count * header.dtype.itemsize
        if path.stat().st_size < need:
            raise InputError(
                path, f"PLY is truncated: {path.stat().st_size} bytes, the header promises {need}"
            )
        if header.count == 0:
            return
        mm = np.memmap(path, dtype=header.dtype, mode="r", offset=header.data_offset, shape=(header.count,))
        for start in range(0, header.count, chunk):
            r = mm[start : start + chunk]
            yield _Fields(
                r["x"], r["y"], r["z"],
                (r["red"], r["green"], r["blue"]) if {"red", "green", "blue"} <= names else None,
                (r["nx"], r["ny"], r["nz"]) if {"nx", "ny", "nz"} <= names else None,
                r["size"] if "size" in names else None,
            )  # fmt: skip
        return
    for pc in iter_ply_chunks(path, chunk):
        yield _Fields(
            pc.xyz[:, 0], pc.xyz[:, 1], pc.xyz[:, 2],
            (pc.rgb[:, 0], pc.rgb[:, 1], pc.rgb[:, 2]) if pc.rgb is not None else None,
            (pc.normals[:, 0], pc.normals[:, 1], pc.normals[:, 2]) if pc.normals is not None else None,
            pc.size,
        )  # fmt: skip


@numba.njit(cache=True)
def _bounds_kernel(x, y, z, lo, hi) -> int:
    """Grow ``lo``/``hi`` (3,) by the finite points; return how many points are not finite."""
    bad = 0
    for i in range(x.shape[0]):
        a, b, c = np.float64(x[i]), np.float64(y[i]), np.float64(z[i])
        if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(c)):
            bad += 1
            continue
        lo[0] = min(lo[0], a)
        lo[1] = min(lo[1], b)
        lo[2] = min(lo[2], c)
        hi[0] = max(hi[0], a)
        hi[1] = max(hi[1], b)
        hi[2] = max(hi[2], c)
    return bad


@numba.njit(cache=True)
def _range_kernel(v, lo, hi, k: int) -> bool:
    """Grow ``lo[k]``/``hi[k]`` by ``v``; False when ``v`` holds NaN or infinity."""
    ok = True
    for i in range(v.shape[0]):
        a = np.float64(v[i])
        if not np.isfinite(a):
            ok = False
            continue
        lo[k] = min(lo[k], a)
        hi[k] = max(hi[k], a)
    return ok


@numba.njit(cache=True)
def _quantise_kernel(x, y, z, offset, scale: float, qsize: int, out) -> None:
    inv = 1.0 / scale
    top = qsize - 1
    for i in range(x.shape[0]):
        out[i, 0] = min(max(np.int64(np.floor((np.float64(x[i]) - offset[0]) * inv + 0.5)), 0), top)
        out[i, 1] = min(max(np.int64(np.floor((np.float64(y[i]) - offset[1]) * inv + 0.5)), 0), top)
        out[i, 2] = min(max(np.int64(np.floor((np.float64(z[i]) - offset[2]) * inv + 0.5)), 0), top)


def quantise(xyz: np.ndarray, offset: np.ndarray, scale: float, qsize: int) -> np.ndarray:
    """Integer positions exactly as the tiles store them: (N, 3) float -> (N, 3) int32."""
    xyz = np.asarray(xyz)
    out = np.empty((xyz.shape[0], 3), np.int32)
    _quantise_kernel(
        xyz[:, 0], xyz[:, 1], xyz[:, 2], np.asarray(offset, np.float64), float(scale), int(qsize), out
    )
    return out


def _scan_bounds(path: Path) -> tuple[int, np.ndarray, np.ndarray, dict, dict, dict]:
    header = read_header(path)
    names = set(header.dtype.names or ())
    has = {
        "rgb": {"red", "green", "blue"} <= names,
        "normal": {"nx", "ny", "nz"} <= names,
        "size": "size" in names,
    }
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    amin = {"rgb": np.full(3, np.inf), "normal": np.full(3, np.inf), "size": np.full(1, np.inf)}
    amax = {k: -v for k, v in amin.items()}
    n = 0
    bad = 0
    size_ok = True
    for f in _iter_fields(path):
        n += len(f)
        bad += _bounds_kernel(f.x, f.y, f.z, lo, hi)
        for key, arrs in (
            ("rgb", f.rgb),
            ("normal", f.normal),
            ("size", (f.size,) if f.size is not None else None),
        ):
            if arrs is not None:
                for k, v in enumerate(arrs):
                    ok = _range_kernel(v, amin[key], amax[key], k)
                    size_ok &= ok or key != "size"
    if n == 0:
        raise InputError(path, "the point cloud is empty (0 points)")
    if bad:
        raise InputError(path, f"{bad} of {n} points have NaN or infinite coordinates")
    if not size_ok:
        raise InputError(path, "the 'size' property holds NaN or infinite values")
    return n, lo, hi, amin, amax, has


@numba.njit(cache=True)
def _encode_kernel(
    x, y, z, r, g, b, nx, ny, nz, sz, flags, offset, scale, qsize, pos, rgb, nrm, size
) -> None:
    """Quantise and pack one slice; ``flags`` says which of colour, normal, size exist."""
    inv = 1.0 / scale
    top = qsize - 1
    for i in range(x.shape[0]):
        pos[i, 0] = min(max(np.int64(np.floor((np.float64(x[i]) - offset[0]) * inv + 0.5)), 0), top)
        pos[i, 1] = min(max(np.int64(np.floor((np.float64(y[i]) - offset[1]) * inv + 0.5)), 0), top)
        pos[i, 2] = min(max(np.int64(np.floor((np.float64(z[i]) - offset[2]) * inv + 0.5)), 0), top)
        if flags[0]:
            rgb[i, 0] = np.uint16(r[i]) * 257  # 8-bit colour to Potree's 16-bit range
            rgb[i, 1] = np.uint16(g[i]) * 257
            rgb[i, 2] = np.uint16(b[i]) * 257
        else:
            rgb[i, 0] = rgb[i, 1] = rgb[i, 2] = 65535
        if flags[1]:
            nrm[i, 0] = nx[i]
            nrm[i, 1] = ny[i]
            nrm[i, 2] = nz[i]
        else:
            nrm[i, 0] = nrm[i, 1] = nrm[i, 2] = 0.0
        size[i] = sz[i] if flags[2] else 0.0


def _encode(f: _Fields, offset: np.ndarray, scale: float, qsize: int) -> np.ndarray:
    rec = np.empty(len(f), POINT_DTYPE)
    dummy_u8 = np.zeros(1, np.uint8)
    dummy_f4 = np.zeros(1, np.float32)
    r, g, b = f.rgb if f.rgb is not None else (dummy_u8,) * 3
    nx, ny, nz = f.normal if f.normal is not None else (dummy_f4,) * 3
    sz = f.size if f.size is not None else dummy_f4
    flags = np.array([f.rgb is not None, f.normal is not None, f.size is not None])
    _encode_kernel(f.x, f.y, f.z, r, g, b, nx, ny, nz, sz, flags, offset, scale, qsize,
                   rec["position"], rec["rgb"], rec["normal"], rec["size"])  # fmt: skip
    return rec


def _choose_chunks(counts: np.ndarray, max_chunk: int) -> list[tuple[int, int, int]]:
    """Top-down: the largest nodes (level <= COUNT_LEVEL) holding at most ``max_chunk`` points."""
    pyramid = [counts]
    for _ in range(COUNT_LEVEL):
        pyramid.append(pyramid[-1].reshape(-1, 8).sum(axis=1))
    pyramid.reverse()  # pyramid[L] has 8**L cells in Morton order
    chunks: list[tuple[int, int, int]] = []
    stack = [(0, 0)]
    while stack:
        level, prefix = stack.pop()
        c = int(pyramid[level][prefix])
        if c == 0:
            continue
        if c <= max_chunk or level == COUNT_LEVEL:
            chunks.append((level, prefix, c))
        else:
            stack.extend((level + 1, prefix * 8 + k) for k in range(7, -1, -1))
    chunks.sort(key=lambda t: t[1] << (3 * (COUNT_LEVEL - t[0])))  # Morton order
    return chunks


def plan_tiles(
    cloud_ply: Path, work_dir: Path, *, max_chunk: int = 2_000_000, max_leaf: int = 10_000
) -> TilePlan:
    """Pass 1: bounds, counts, chunk choice and distribution of points into chunk files.

    Writes ``work_dir/chunk_*.bin`` (raw :data:`POINT_DTYPE` records) and ``work_dir/plan.json``.
    Raises :class:`InputError` for an empty cloud or NaN / infinite coordinates.
    """
    cloud_ply = Path(cloud_ply)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    for old in work_dir.glob("chunk_*"):  # a re-run starts clean: no stale chunk results
        old.unlink()
    n, lo, hi, amin, amax, has = _scan_bounds(cloud_ply)
    extent = float((hi - lo).max())
    cube = max(extent * (1 + 1e-6), 1e-6 * max(1.0, float(np.abs(np.concatenate([lo, hi])).max())))
    # A power-of-ten step that keeps cube / scale well inside int32.
    scale = 10.0 ** math.ceil(math.log10(cube / 2**30))
    qsize = int(math.ceil(cube / scale)) + 1
    cube = qsize * scale
    offset = lo.astype(np.float64)
    shift = 3 * (MORTON_BITS - COUNT_LEVEL)

    counts = np.zeros(8**COUNT_LEVEL, np.int64)
    for f in _iter_fields(cloud_ply):
        pos = np.empty((len(f), 3), np.int32)
        _quantise_kernel(f.x, f.y, f.z, offset, scale, qsize, pos)
        codes = morton_codes(pos, qsize)
        counts += np.bincount(codes >> shift, minlength=counts.size)
    chunks = _choose_chunks(counts, max(max_chunk, max_leaf))
    cell_to_chunk = np.full(counts.size, -1, np.int32)
    for i, (level, prefix, _c) in enumerate(chunks):
        span = 3 * (COUNT_LEVEL - level)
        cell_to_chunk[prefix << span : (prefix + 1) << span] = i

    paths = [work_dir / f"chunk_{i:05d}.bin" for i in range(len(chunks))]
    for p in paths:
        p.write_bytes(b"")
    # Keep the chunk files open unless there are too many for the descriptor limit.
    keep_open = len(chunks) <= MAX_OPEN_FILES
    files = [open(p, "ab") for p in paths] if keep_open else []
    try:
        for f in _iter_fields(cloud_ply):
            rec = _encode(f, offset, scale, qsize)
            cid = cell_to_chunk[morton_codes(rec["position"], qsize) >> shift]
            order, bounds = _counting_order(cid, len(chunks))
            rec = _permute(rec, order)
            for i in np.flatnonzero(np.diff(bounds)):
                data = memoryview(rec[bounds[i] : bounds[i + 1]]).cast("B")  # no copy
                if keep_open:
                    files[i].write(data)
                else:
                    with open(paths[i], "ab") as out:
                        out.write(data)
    finally:
        for fh in files:
            fh.close()

    plan = TilePlan(
        source=str(cloud_ply),
        name=cloud_ply.stem,
        points=n,
        offset=[float(v) for v in offset],
        scale=scale,
        cube_size=cube,
        qsize=qsize,
        attr_min={k: [float(x) for x in v] for k, v in amin.items()},
        attr_max={k: [float(x) for x in v] for k, v in amax.items()},
        chunks=[
            {"level": lv, "prefix": p, "points": c, "file": f"chunk_{i:05d}.bin"}
            for i, (lv, p, c) in enumerate(chunks)
        ],
        max_leaf=max_leaf,
        has=has,
        bounds_min=[float(v) for v in lo],
        bounds_max=[float(v) for v in hi],
    )
    tmp = work_dir / f"{PLAN_FILE}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(asdict(plan)))
    os.replace(tmp, work_dir / PLAN_FILE)
    log.info("planned %d points into %d chunks", n, len(chunks))
    return plan


def load_plan(work_dir: Path) -> TilePlan:
    """Read the plan :func:`plan_tiles` saved in ``work_dir``."""
    return TilePlan(**json.loads((Path(work_dir) / PLAN_FILE).read_text()))


# --------------------------------------------------------------------------- pass 2: chunks


@numba.njit(cache=True)
def _pack_keys(codes: np.ndarray, base: int, drop: int, idx_bits: int) -> np.ndarray:
    out = np.empty(codes.shape[0], np.uint64)
    for i in range(codes.shape[0]):
        out[i] = (np.uint64((codes[i] - base) >> drop) << np.uint64(idx_bits)) | np.uint64(i)
    return out


@numba.njit(cache=True)
def _unpack_index(keys: np.ndarray, idx_bits: int) -> np.ndarray:
    mask = np.uint64((1 << idx_bits) - 1)
    out = np.empty(keys.shape[0], np.int64)
    for i in range(keys.shape[0]):
        out[i] = np.int64(keys[i] & mask)
    return out


def _morton_order(codes: np.ndarray, level_c: int, prefix_c: int) -> tuple[np.ndarray, int]:
    """Order of a chunk's points by Morton code, and the deepest level it resolves.

    numpy's value sort is several times faster than its argsort, so the point index is packed
    under the code (relative to the chunk) in one uint64 key. When code and index do not fit
    in 64 bits, the code's finest levels are dropped; the chunk then stops splitting where
    those levels would be needed (leaves there keep all their points).
    """
    n = codes.shape[0]
    idx_bits = max(1, (n - 1).bit_length())
    rel_bits = 3 * (MORTON_BITS - level_c)
    drop = 3 * math.ceil(max(0, rel_bits + idx_bits - 64) / 3)
    # A node at level L samples with shift 3 * (MAX_DEPTH - L) and must see every kept bit.
    max_depth = min(MAX_DEPTH, MAX_DEPTH + 1 - drop // 3)
    base = (prefix_c << rel_bits) if level_c else 0
    key = _pack_keys(codes, base, drop, idx_bits)
    key.sort()
    return _unpack_index(key, idx_bits), max_depth


def build_chunk(work_dir: Path, index: int) -> Path:
    """Pass 2 for one chunk: sample its subtree and its share of the nodes above it.

    Reads ``chunk_{index}.bin``; writes ``chunk_{index}.nodes.bin`` (the points grouped by
    node) and ``chunk_{index}.nodes.json`` (a list of ``[name, numPoints, byteOffset, own]``,
    ``own`` false for the nodes above the chunk that other chunks share). Returns the JSON
    path. Independent of every other chunk, so chunks can run as separate processes or tasks;
    idempotent (a retried task whose outputs exist returns at once; outputs appear by rename,
    so a killed task leaves none).
    """
    work_dir = Path(work_dir)
    out_bin = work_dir / f"chunk_{index:05d}.nodes.bin"
    out_json = work_dir / f"chunk_{index:05d}.nodes.json"
    if out_json.is_file() and out_bin.is_file():
        return out_json
    plan = load_plan(work_dir)
    spec = plan.chunks[index]
    src = work_dir / spec["file"]
    rec = np.fromfile(src, dtype=POINT_DTYPE)
    codes = morton_codes(rec["position"], plan.qsize)
    n = rec.shape[0]
    level_c, prefix_c = spec["level"], spec["prefix"]
    order, max_depth = _morton_order(codes, level_c, prefix_c)
    codes = codes[order]
    assigned = np.full(n, -1, np.int32)
    names: list[str] = []
    own: list[bool] = []  # node lies inside this chunk (not an upper node shared with others)

    # Upper nodes: this chunk's share of every ancestor's grid sample.
    for level in range(level_c):
        names.append(node_name(level, prefix_c >> (3 * (level_c - level))))
        own.append(False)
        _sample(codes, assigned, 0, n, 3 * (MORTON_BITS - level - GRID_LEVELS), len(names) - 1)

    stack = [(level_c, prefix_c, 0, n)]
    while stack:
        level, prefix, lo, hi = stack.pop()
        remaining = _count_unassigned(assigned, lo, hi)
        if remaining == 0:  # a small chunk whose points all went to the nodes above it
            continue
        node = len(names)
        names.append(node_name(level, prefix))
        own.append(True)
        if remaining <= plan.max_leaf or level >= max_depth:
            _take_all(assigned, lo, hi, node)
            continue
        _sample(codes, assigned, lo, hi, 3 * (MORTON_BITS - level - GRID_LEVELS), node)
        cshift = 3 * (MORTON_BITS - level - 1)
        keys = prefix * 8 + np.arange(9, dtype=np.int64)
        edges = np.searchsorted(codes[lo:hi], keys << cshift) + lo
        edges[-1] = hi
        for k in range(7, -1, -1):
            a, b = int(edges[k]), int(edges[k + 1])
            if b > a and _count_unassigned(assigned, a, b) > 0:
                stack.append((level + 1, prefix * 8 + k, a, b))

    by_node, bounds = _counting_order(assigned, len(names))
    counts = np.diff(bounds)
    starts = bounds[:-1]
    # One gather of the records: Morton order, then grouped by node.
    tmp_bin = out_bin.with_name(out_bin.name + f".{os.getpid()}.tmp")
    _permute(rec, order[by_node]).tofile(tmp_bin)
    os.replace(tmp_bin, out_bin)
    table = [
        [names[i], int(counts[i]), int(starts[i]) * POINT_DTYPE.itemsize, own[i]]
        for i in range(len(names))
        if counts[i] > 0 or own[i]
    ]
    tmp_json = out_json.with_name(out_json.name + f".{os.getpid()}.tmp")
    tmp_json.write_text(json.dumps(table))
    os.replace(tmp_json, out_json)  # last: its presence marks the chunk done
    return out_json


# --------------------------------------------------------------------------- pass 3: merge


def _attributes(plan: TilePlan) -> list[dict]:
    lo, hi = plan.bounds_min, plan.bounds_max

    def rng(key: str, k: int, default: float, factor: float = 1.0) -> tuple[list[float], list[float]]:
        mn, mx = plan.attr_min[key], plan.attr_max[key]
        if not plan.has.get(key) or not all(math.isfinite(v) for v in mn + mx):
            return [default] * k, [default] * k
        return [v * factor for v in mn], [v * factor for v in mx]

    rgb_min, rgb_max = rng("rgb", 3, 65535.0, 257.0)
    n_min, n_max = rng("normal", 3, 0.0)
    s_min, s_max = rng("size", 1, 0.0)
    return [
        {"name": "position", "description": "", "size": 12, "numElements": 3, "elementSize": 4,
         "type": "int32", "min": lo, "max": hi},
        {"name": "rgb", "description": "", "size": 6, "numElements": 3, "elementSize": 2,
         "type": "uint16", "min": rgb_min, "max": rgb_max},
        # Normals as three scalars: Potree and potree-core both join NormalX/Y/Z into a
        # NORMAL vector (potree-core cannot decode a 3-element "normal"); same bytes.
        *({"name": f"Normal{axis}", "description": "unit normal", "size": 4, "numElements": 1,
           "elementSize": 4, "type": "float", "min": [n_min[k]], "max": [n_max[k]]}
          for k, axis in enumerate("XYZ")),
        {"name": "size", "description": "world-space sample size Z / f_camera", "size": 4,
         "numElements": 1, "elementSize": 4, "type": "float", "min": s_min, "max": s_max},
    ]  # fmt: skip


def _hierarchy(nodes: dict[str, dict]) -> tuple[bytes, int, int]:
    """hierarchy.bin bytes, firstChunkSize, depth (PotreeConverter's chunking, step 4)."""
    children: dict[str, list[str]] = {name: [] for name in nodes}
    for name in nodes:
        if name != "r":
            children[name[:-1]].append(name)

    def gather(root: str) -> list[str]:
        base = len(root) - 1
        out, stack = [], [root]
        while stack:
            nm = stack.pop()
            out.append(nm)
            if len(nm) - 1 < base + HIERARCHY_STEP:
                stack.extend(children[nm])
        out.sort(key=lambda s: (len(s), s))
        return out

    chunk_list: list[list[str]] = []
    stack = ["r"]
    while stack:
        root = stack.pop()
        members = gather(root)
        chunk_list.append(members)
        stack.extend(m for m in members if len(m) - 1 == len(root) - 1 + HIERARCHY_STEP)
    chunk_index = {members[0]: i for i, members in enumerate(chunk_list)}
    chunk_offsets = np.concatenate([[0], np.cumsum([len(m) * BYTES_PER_NODE for m in chunk_list])])
    rec_dtype = np.dtype(
        [("type", "u1"), ("mask", "u1"), ("points", "<u4"), ("offset", "<i8"), ("size", "<i8")]
    )
    parts = []
    for members in chunk_list:
        root_level = len(members[0]) - 1
        arr = np.zeros(len(members), rec_dtype)
        for j, nm in enumerate(members):
            info = nodes[nm]
            mask = 0
            for c in children[nm]:
                mask |= 1 << int(c[-1])
            arr[j]["mask"] = mask
            arr[j]["points"] = info["points"]
            if len(nm) - 1 == root_level + HIERARCHY_STEP:
                ci = chunk_index[nm]
                arr[j]["type"] = 2
                arr[j]["offset"] = chunk_offsets[ci]
                arr[j]["size"] = len(chunk_list[ci]) * BYTES_PER_NODE
            else:
                arr[j]["type"] = 1 if mask == 0 else 0
                arr[j]["offset"] = info["offset"]
                arr[j]["size"] = info["size"]
        parts.append(arr.tobytes())
    depth = max(len(nm) - 1 for nm in nodes)
    return b"".join(parts), len(chunk_list[0]) * BYTES_PER_NODE, depth


def _copy_range(src, dst, src_off: int, dst_off: int, nbytes: int) -> None:
    """Copy bytes between files in the kernel where it can (no trip through Python buffers)."""
    done = 0
    try:
        while done < nbytes:
            n = os.copy_file_range(src.fileno(), dst.fileno(), nbytes - done, src_off + done, dst_off + done)
            if n <= 0:
                break
            done += n
    except (OSError, AttributeError):  # no copy_file_range here (not Linux, or across devices)
        pass
    if done < nbytes:
        src.seek(src_off + done)
        dst.seek(dst_off + done)
        dst.write(src.read(nbytes - done))
        dst.flush()


def merge_tiles(work_dir: Path, out_dir: Path) -> dict:
    """Pass 3: gather every chunk's node pieces into ``octree.bin``, write the hierarchy and
    metadata, and rename the finished folder to ``out_dir`` (replacing an older one).
    ``work_dir`` is left in place for the caller to remove.

    Returns a report: points, nodes, depth, bytes.
    """
    work_dir = Path(work_dir)
    out_dir = Path(out_dir)
    plan = load_plan(work_dir)
    pieces: dict[str, list[tuple[int, int, int]]] = {}  # name -> [(chunk, byte offset, points)]
    for i in range(len(plan.chunks)):
        table = json.loads((work_dir / f"chunk_{i:05d}.nodes.json").read_text())
        for name, npts, off, _own in table:
            pieces.setdefault(name, []).append((i, off, npts))
    for name in list(pieces):  # every node needs its ancestors, even one left empty
        for k in range(1, len(name)):
            pieces.setdefault(name[:k], [])
    names = sorted(pieces, key=lambda s: (len(s), s))
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    try:
        nodes: dict[str, dict] = {}
        sources = [
            open(work_dir / f"chunk_{i:05d}.nodes.bin", "rb", buffering=0) for i in range(len(plan.chunks))
        ]
        total = 0
        try:
            with open(stage / "octree.bin", "wb", buffering=0) as out:
                pos = 0
                for nm in names:
                    npts = 0
                    for ci, off, cnt in pieces[nm]:
                        if cnt == 0:
                            continue
                        _copy_range(
                            sources[ci],
                            out,
                            off,
                            pos + npts * POINT_DTYPE.itemsize,
                            cnt * POINT_DTYPE.itemsize,
                        )
                        npts += cnt
                    size = npts * POINT_DTYPE.itemsize
                    nodes[nm] = {"points": npts, "offset": pos, "size": size}
                    pos += size
                    total += npts
        finally:
            for f in sources:
                f.close()
        if total != plan.points:
            raise RuntimeError(f"tiles hold {total} points, the cloud has {plan.points}")
        hierarchy, first_chunk, depth = _hierarchy(nodes)
        (stage / "hierarchy.bin").write_bytes(hierarchy)
        lo = plan.offset
        metadata = {
            "version": "2.0",
            "name": plan.name,
            "description": "",
            "points": plan.points,
            "projection": "",
            "hierarchy": {"firstChunkSize": first_chunk, "stepSize": HIERARCHY_STEP, "depth": depth},
            "offset": lo,
            "scale": [plan.scale] * 3,
            "spacing": plan.cube_size / 128.0,
            "boundingBox": {"min": lo, "max": [v + plan.cube_size for v in lo]},
            "encoding": "DEFAULT",
            "attributes": _attributes(plan),
        }
        (stage / "metadata.json").write_text(json.dumps(metadata, indent=2) + "\n")
        os.chmod(stage, 0o755)
        if out_dir.exists():
            old = out_dir.with_name(f".{out_dir.name}.old.{os.getpid()}")
            os.replace(out_dir, old)
            os.replace(stage, out_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(stage, out_dir)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return {"points": plan.points, "nodes": len(nodes), "depth": depth, "bytes": int(pos)}


def _warm_kernels() -> None:
    """Load every kernel once (from numba's cache) so forked chunk workers inherit them."""
    pos = np.zeros((2, 3), np.int32)
    codes = morton_codes(pos, 8)
    assigned = np.full(2, -1, np.int32)
    _count_unassigned(assigned, 0, 2)
    _sample(codes, assigned, 0, 2, 3, 0)
    _take_all(assigned, 0, 2, 1)
    _counting_order(assigned, 2)
    _permute(np.zeros(2, POINT_DTYPE), np.arange(2))
    _morton_order(codes, 0, 0)


def _build_chunk_job(args: tuple[str, int]) -> str:
    return str(build_chunk(Path(args[0]), args[1]))


def build_tiles(
    cloud_ply: Path,
    out_dir: Path,
    *,
    workers: int | None = None,
    max_chunk: int = 2_000_000,
    max_leaf: int = 10_000,
) -> dict:
    """Build Potree 2.0 tiles from ``cloud_ply`` into ``out_dir`` (all passes, in-process).

    ``workers`` processes build chunks in parallel (default: the CPU count; 1 runs in this
    process). Temporary chunk files live beside ``out_dir`` and are removed. Returns a report
    with points, nodes, depth, bytes, chunks, seconds and points_per_second.
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.work.", dir=out_dir.parent))
    try:
        plan = plan_tiles(Path(cloud_ply), work, max_chunk=max_chunk, max_leaf=max_leaf)
        _warm_kernels()
        nchunks = len(plan.chunks)
        workers = max(1, min(workers or os.cpu_count() or 1, nchunks))
        # Largest chunks first keeps the pool busy to the end. Fork: the chunk builder starts
        # no threads, and forked workers inherit the compiled kernels (spawn would re-import).
        order = sorted(range(nchunks), key=lambda i: -plan.chunks[i]["points"])
        if workers == 1:
            for i in order:
                build_chunk(work, i)
        else:
            with ProcessPoolExecutor(workers, mp_context=get_context("fork")) as pool:
                list(pool.map(_build_chunk_job, [(str(work), i) for i in order]))
        report = merge_tiles(work, out_dir)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    dt = time.perf_counter() - t0
    report.update(chunks=nchunks, seconds=dt, points_per_second=plan.points / dt if dt > 0 else 0.0)
    return report
