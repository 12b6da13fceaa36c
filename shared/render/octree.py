"""Out-of-core builder of Potree 2.0 level-of-detail tiles from a PLY point cloud.

In: a cloud PLY per :mod:`shared.formats.ply` (``x, y, z`` required; colour, normal and the world
sample ``size`` = Z / f_camera carried when present). A cloud from elsewhere keeps only what it
has: no colour, no normals (unless asked to estimate them) — the attributes list and the
records say so — and a ``size`` derived from its local point spacing when it has none, so
splats still close its surfaces. Out: a folder readable by Potree 2.x viewers
(``OctreeLoader.js``)::

    metadata.json   version "2.0", points, hierarchy {firstChunkSize, stepSize, depth},
                    offset, scale, spacing, cubic boundingBox, encoding "DEFAULT", attributes
    hierarchy.bin   22-byte node records (type u8, childMask u8, numPoints u32, byteOffset i64,
                    byteSize i64), breadth-first per hierarchy chunk, proxies every 4 levels
    octree.bin      every node's points once (additive LOD), 34 bytes a point for a full cloud:
                    position 3 x int32 (world = int * scale + offset), rgb 3 x uint16
                    (8-bit colour * 257), NormalX/NormalY/NormalZ float32, size float32
                    (world units; the scanner's Z / f_camera); a cloud lacking colour or
                    normals has records without those fields

With ``node_codec="octree"`` (opt-in: ``graylight tiles --node-codec octree``, the tiles job's
``params.tiles.node_codec``) every node of ``octree.bin`` is octree-coded instead
(:mod:`shared.compress.tilenode`: the same records, lossless, about a quarter of the bytes) and
metadata.json names the encoding "GRAYLIGHT_OCTREE"; the rest is the plain build's, and the
plain build's bytes do not change.

Level-of-detail scheme: positions are quantised, then Morton-coded at 21 bits an axis with
Potree's child order (bit 2 = x, bit 1 = y, bit 0 = z). A node at level L has spacing
``cube / 128 / 2**L``; an inner node keeps the first not-yet-taken point (in Morton order)
of every cell of its 128^3 grid — a grid sampler, so coverage is even — and hands the rest to
its children; a node with at most ``max_leaf`` remaining points keeps them all (a leaf).

Out of core, in three passes whose memory does not grow with the cloud:

1. :func:`plan_tiles` streams the PLY for bounds and attribute ranges (rejecting NaN or
   infinite coordinates), then again to count points per cell of a 128^3 grid, picks
   *chunks* (the largest octree nodes holding at most ``max_chunk`` points) and streams the
   points once more into one file per chunk. Given a pool (threads or processes), each of
   these passes splits the cloud into contiguous ranges, one a worker; the chunk files come
   out the same.
2. :func:`build_chunk` builds one chunk independently (the parallel unit: a thread
   in-process, a task under the job service). Because every cell a node at level L samples
   from (level L + 7) lies inside one chunk (chunks sit at level <= 7), a chunk can also
   compute its exact share of the nodes above it.
3. :func:`merge_tiles` concatenates the pieces into ``octree.bin``, writes
   ``hierarchy.bin`` and ``metadata.json`` and renames the finished folder into place.

:func:`build_tiles` runs all three with one pool of threads (the kernels release the GIL),
and fuses 2 and 3: a thread samples each chunk, and once every chunk's node sizes are known,
writes that chunk's pieces straight to their places in ``octree.bin`` (same bytes as the
merge, less I/O, no serial copy). A cloud of at most :data:`KEEP_POINTS` points keeps the
sampled chunks in memory meanwhile (a larger one keeps their order in files). Units are
those of the PLY (millimetres for Graylight).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.compress import tilenode
from shared.core.errors import InputError
from shared.core.numba_start import blas_check_without_scipy_linalg
from shared.core.threads import cpu_budget
from shared.formats.ply import CLOUD_DTYPE, iter_ply_chunks, read_header
from shared.formats.potree import HIERARCHY_DTYPE, HIERARCHY_STEP
from shared.render._octree_kernels import (
    GRID_LEVELS,
    MORTON_BITS,
    _build_nodes,
    _count_kernel,
    _counting_order,
    _distribute_kernel,
    _pack_keys,
    _quantise_kernel,
    _scan_kernel,
    _unpack_keys,
    morton_codes,
)

log = logging.getLogger(__name__)

#: One point in ``octree.bin`` (34 bytes, packed, little-endian).
POINT_DTYPE = np.dtype(
    [("position", "<i4", (3,)), ("rgb", "<u2", (3,)), ("normal", "<f4", (3,)), ("size", "<f4")]
)
COUNT_LEVEL = 7  # level of the counting grid; chunks are never deeper than this
BYTES_PER_NODE = HIERARCHY_DTYPE.itemsize  # 22
MAX_DEPTH = MORTON_BITS - GRID_LEVELS  # deepest level whose sampling grid the codes resolve
READ_CHUNK = 1 << 20  # points a slice of the passes over the cloud
MIN_PART_POINTS = 1 << 20  # smallest range of the cloud a pass hands to a worker
KEEP_POINTS = 1 << 23  # clouds up to this many points keep pass 2's chunks in memory (~40 bytes a point)
PLAN_FILE = "plan.json"
MAX_OPEN_FILES = 256
#: Node encodings of ``octree.bin``: option value -> metadata.json "encoding".
NODE_CODECS = {"plain": "DEFAULT", "octree": tilenode.ENCODING}


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
    #: Attributes the cloud lacks that the chunks compute ("size" from the point spacing,
    #: "normal" when asked): see :mod:`shared.render._neighbours`.
    derived: dict[str, bool] = field(default_factory=dict)
    #: How ``octree.bin`` stores a node: "plain" (Potree's DEFAULT records) or "octree"
    #: (:mod:`shared.compress.tilenode`, metadata encoding "GRAYLIGHT_OCTREE").
    node_codec: str = "plain"

    def point_dtype(self) -> np.dtype:
        """Records of ``octree.bin``: :data:`POINT_DTYPE` less what the cloud neither has
        nor derives (a full Graylight cloud: all of it)."""
        return tiles_dtype({k: self.has.get(k, False) or self.derived.get(k, False) for k in ("rgb", "normal", "size")})


def tiles_dtype(present: dict[str, bool]) -> np.dtype:
    """:data:`POINT_DTYPE`'s fields, in its order, for the attributes ``present`` says exist
    (keys rgb, normal, size; the position always)."""
    return np.dtype([(name, POINT_DTYPE[name]) for name in POINT_DTYPE.names if name == "position" or present.get(name)])


# --------------------------------------------------------------------------- Morton codes


def _permute(rec: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``rec[order]``, the records moved as opaque fixed-size blobs (numpy copies each with one
    memcpy; fancy indexing of a structured dtype goes field by field and is far slower)."""
    blobs = rec.view(f"V{rec.dtype.itemsize}")
    return np.take(blobs, order).view(rec.dtype)


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

    def kernel_args(self) -> tuple:
        """``(x, y, z, r, g, b, nx, ny, nz, size, flags)`` for the fused kernels; a missing
        attribute is a one-element dummy and its flag (colour, normal, size) is False."""
        dummy_u8 = np.zeros(1, np.uint8)
        dummy_f4 = np.zeros(1, np.float32)
        r, g, b = self.rgb if self.rgb is not None else (dummy_u8,) * 3
        nx, ny, nz = self.normal if self.normal is not None else (dummy_f4,) * 3
        sz = self.size if self.size is not None else dummy_f4
        flags = np.array([self.rgb is not None, self.normal is not None, self.size is not None])
        return self.x, self.y, self.z, r, g, b, nx, ny, nz, sz, flags


def _iter_fields(path: Path, chunk: int | None = None, start: int = 0, stop: int | None = None):
    """Yield :class:`_Fields` of at most ``chunk`` points; no copies for little-endian binary PLY.

    ``start``/``stop`` select a range of points (little-endian binary only; other formats are
    read whole, so callers split only that format).
    """
    chunk = chunk or READ_CHUNK
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
        stop = header.count if stop is None else min(stop, header.count)
        for a in range(start, stop, chunk):
            r = mm[a : min(a + chunk, stop)]
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


def quantise(xyz: np.ndarray, offset: np.ndarray, scale: float, qsize: int) -> np.ndarray:
    """Integer positions exactly as the tiles store them: (N, 3) float -> (N, 3) int32."""
    xyz = np.asarray(xyz)
    out = np.empty((xyz.shape[0], 3), np.int32)
    _quantise_kernel(
        xyz[:, 0], xyz[:, 1], xyz[:, 2], np.asarray(offset, np.float64), float(scale), int(qsize), out
    )
    return out


def _attribute_names(path: Path) -> dict[str, bool]:
    names = set(read_header(path).dtype.names or ())
    return {
        "rgb": {"red", "green", "blue"} <= names,
        "normal": {"nx", "ny", "nz"} <= names,
        "size": "size" in names,
    }


def _scan_part(
    path: str, start: int, stop: int | None
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Bounds pass over points [start, stop): count, lo, hi, attribute min / max (7,), bad counts."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    amin = np.full(7, np.inf)
    amax = np.full(7, -np.inf)
    n = bad = bad_size = 0
    for f in _iter_fields(Path(path), start=start, stop=stop):
        n += len(f)
        nb, ns = _scan_kernel(*f.kernel_args(), lo, hi, amin, amax)
        bad += nb
        bad_size += ns
    return n, lo, hi, amin, amax, bad, bad_size


def _count_part(
    path: str, start: int, stop: int | None, offset: np.ndarray, scale: float, qsize: int
) -> tuple[np.ndarray, np.ndarray]:
    """Counting pass over points [start, stop): the occupied cells and their counts."""
    counts = np.zeros(8**COUNT_LEVEL, np.int64)
    shift = 3 * (MORTON_BITS - COUNT_LEVEL)
    for f in _iter_fields(Path(path), start=start, stop=stop):
        _count_kernel(f.x, f.y, f.z, offset, scale, qsize, shift, counts)
    cells = np.flatnonzero(counts)  # a scan fills few of the 2M cells: send only those
    return cells, counts[cells]


def _cell_to_chunk(chunks: list[tuple[int, int, int]]) -> np.ndarray:
    table = np.full(8**COUNT_LEVEL, -1, np.int32)
    for i, (level, prefix, _c) in enumerate(chunks):
        span = 3 * (COUNT_LEVEL - level)
        table[prefix << span : (prefix + 1) << span] = i
    return table


def _pwrite_all(fd: int, data: memoryview, offset: int) -> None:
    done = 0
    while done < len(data):
        done += os.pwrite(fd, data[done:], offset + done)


def _distribute_part(
    path: str, start: int, stop: int | None, work_dir: str, chunks: list[tuple[int, int, int]],
    offset: np.ndarray, scale: float, qsize: int, file_offsets: np.ndarray, memory: np.ndarray | None = None,
) -> int:  # fmt: skip
    """Distribution pass over points [start, stop): each chunk's points, in file order, are
    written into its chunk file from ``file_offsets[chunk]`` (bytes) on; several parts of the
    cloud write into the same files at disjoint offsets. With ``memory`` (uint8, every chunk's
    records one after the other) they go there instead, ``file_offsets`` counting from its
    start. Returns the points written."""
    cell_to_chunk = _cell_to_chunk(chunks)
    shift = 3 * (MORTON_BITS - COUNT_LEVEL)
    paths = [Path(work_dir) / f"chunk_{i:05d}.bin" for i in range(len(chunks))]
    pos = np.array(file_offsets, np.int64)
    # Keep the chunk files open unless there are too many for the descriptor limit.
    keep_open = memory is None and len(chunks) <= MAX_OPEN_FILES
    fds = [os.open(p, os.O_WRONLY) for p in paths] if keep_open else []
    written = 0
    # Buffers reused slice after slice: fresh ones would cost a page fault every 4 KiB.
    buf = np.empty(READ_CHUNK, POINT_DTYPE)
    q = np.empty((READ_CHUNK, 3), np.int32)
    cid = np.empty(READ_CHUNK, np.int32)
    try:
        for f in _iter_fields(Path(path), start=start, stop=stop):
            if len(f) > buf.shape[0]:
                buf = np.empty(len(f), POINT_DTYPE)
                q = np.empty((len(f), 3), np.int32)
                cid = np.empty(len(f), np.int32)
            rec = buf[: len(f)]
            bounds = _distribute_kernel(*f.kernel_args(), offset, scale, qsize, shift, cell_to_chunk,
                                        len(chunks), rec["position"], rec["rgb"], rec["normal"],
                                        rec["size"], q, cid)  # fmt: skip
            for i in np.flatnonzero(np.diff(bounds)):
                data = memoryview(rec[bounds[i] : bounds[i + 1]]).cast("B")  # no copy
                if memory is not None:
                    memory[pos[i] : pos[i] + len(data)] = data
                elif keep_open:
                    _pwrite_all(fds[i], data, int(pos[i]))
                else:
                    fd = os.open(paths[i], os.O_WRONLY)
                    try:
                        _pwrite_all(fd, data, int(pos[i]))
                    finally:
                        os.close(fd)
                pos[i] += len(data)
            written += len(f)
    finally:
        for fd in fds:
            os.close(fd)
    return written


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


def _parts(path: Path, pool: Executor | None, workers: int) -> list[tuple[int, int | None]]:
    """Contiguous point ranges the passes split over (one unless the PLY can be memory-mapped)."""
    header = read_header(path)
    parts = min(workers, header.count // MIN_PART_POINTS)
    if pool is None or parts <= 1 or header.fmt != "binary_little_endian":
        return [(0, None)]
    step = -(-header.count // parts)
    return [(a, min(a + step, header.count)) for a in range(0, header.count, step)]


def _run_parts(pool: Executor | None, fn, calls: list[tuple], done: Callable[[int], None] | None = None) -> list:
    """``[fn(*args) for args in calls]``, in ``pool`` when there is one and more than one call;
    ``done(k)`` after the k-th call's result is in (in order), for progress."""
    if pool is None or len(calls) == 1:
        out = []
        for k, args in enumerate(calls):
            out.append(fn(*args))
            if done is not None:
                done(k)
        return out
    futures = [pool.submit(fn, *args) for args in calls]
    results = []
    for k, f in enumerate(futures):
        results.append(f.result())
        if done is not None:
            done(k)
    return results


def plan_tiles(
    cloud_ply: Path,
    work_dir: Path,
    *,
    max_chunk: int = 2_000_000,
    max_leaf: int = 10_000,
    pool: Executor | None = None,
    workers: int = 1,
    scale: float | None = None,
    estimate_normals: bool = False,
    node_codec: str = "plain",
) -> TilePlan:
    """Pass 1: bounds, counts, chunk choice and distribution of points into chunk files.

    Writes ``work_dir/chunk_*.bin`` (raw :data:`POINT_DTYPE` records) and ``work_dir/plan.json``.
    With a ``pool`` of ``workers`` threads or processes, each pass over a little-endian binary
    PLY splits into that many contiguous ranges run in the pool (same files, byte for byte).
    ``scale`` (world units per integer step) overrides the default power of ten that spreads
    the cube over about 2**30 steps (a COPC export picks its own, see
    :func:`shared.formats.las.coordinate_scale`); it must keep the cube within int32.
    A cloud without ``size`` gets one from its local point spacing, and with
    ``estimate_normals`` one without normals gets them from its neighbourhoods (both computed
    per chunk, :mod:`shared.render._neighbours`); missing colour stays missing.
    ``node_codec`` (:data:`NODE_CODECS`) is how the merge stores the nodes: "plain" (Potree's
    DEFAULT, the default) or "octree" (octree-coded, :mod:`shared.compress.tilenode`).
    Raises :class:`InputError` for an empty cloud or NaN / infinite coordinates.
    """
    return _plan(cloud_ply, work_dir, max_chunk=max_chunk, max_leaf=max_leaf, pool=pool, workers=workers,
                 scale=scale, estimate_normals=estimate_normals, node_codec=node_codec)[0]  # fmt: skip


def _plan(
    cloud_ply: Path, work_dir: Path, *, max_chunk: int, max_leaf: int, pool: Executor | None, workers: int,
    scale: float | None, estimate_normals: bool, node_codec: str, keep_points: int = 0,
) -> tuple[TilePlan, np.ndarray | None]:  # fmt: skip
    """:func:`plan_tiles`; a cloud of at most ``keep_points`` points is distributed into memory
    rather than chunk files (``pool`` then must not be a process pool): returned beside the
    plan, (N,) :data:`POINT_DTYPE`, chunk after chunk in plan order (None when in files)."""
    if node_codec not in NODE_CODECS:
        raise InputError("node_codec", f"must be one of {', '.join(NODE_CODECS)}, got {node_codec!r}")
    cloud_ply = Path(cloud_ply)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    for old in work_dir.glob("chunk_*"):  # a re-run starts clean: no stale chunk results
        old.unlink()
    has = _attribute_names(cloud_ply)
    parts = _parts(cloud_ply, pool, workers)
    src = str(cloud_ply)

    scans = _run_parts(pool, _scan_part, [(src, a, b) for a, b in parts])
    n = sum(s[0] for s in scans)
    lo = np.min([s[1] for s in scans], axis=0)
    hi = np.max([s[2] for s in scans], axis=0)
    amin7 = np.min([s[3] for s in scans], axis=0)
    amax7 = np.max([s[4] for s in scans], axis=0)
    bad = sum(s[5] for s in scans)
    if n == 0:
        raise InputError(cloud_ply, "the point cloud is empty (0 points)")
    if bad:
        raise InputError(cloud_ply, f"{bad} of {n} points have NaN or infinite coordinates")
    if sum(s[6] for s in scans):
        raise InputError(cloud_ply, "the 'size' property holds NaN or infinite values")
    amin = {"rgb": amin7[0:3], "normal": amin7[3:6], "size": amin7[6:7]}
    amax = {"rgb": amax7[0:3], "normal": amax7[3:6], "size": amax7[6:7]}

    extent = float((hi - lo).max())
    cube = max(extent * (1 + 1e-6), 1e-6 * max(1.0, float(np.abs(np.concatenate([lo, hi])).max())))
    # A power-of-ten step that keeps cube / scale well inside int32.
    if scale is None:
        scale = 10.0 ** math.ceil(math.log10(cube / 2**30))
    elif not (scale > 0 and math.isfinite(scale)) or cube / scale > 2**31 - 2:
        raise InputError("scale", f"{scale!r} cannot hold the cloud's extent {cube:.6g} in int32 steps")
    qsize = int(math.ceil(cube / scale)) + 1
    cube = qsize * scale
    offset = lo.astype(np.float64)

    if n <= max(max_chunk, max_leaf):
        # The root alone is the chunk (what the counts would choose): no counting pass.
        chunks = [(0, 0, n)]
        part_counts = np.array([[scan[0]] for scan in scans], np.int64)
    else:
        counted = _run_parts(pool, _count_part, [(src, a, b, offset, scale, qsize) for a, b in parts])
        counts = np.zeros(8**COUNT_LEVEL, np.int64)
        for cells, c in counted:
            counts[cells] += c
        chunks = _choose_chunks(counts, max(max_chunk, max_leaf))
        cell_to_chunk = _cell_to_chunk(chunks)
        # Where every part's points start in each chunk file: parts write disjoint byte ranges,
        # in part order, so a chunk file holds its points in file order whatever the split.
        part_counts = np.zeros((len(parts), len(chunks)), np.int64)
        for k, (cells, c) in enumerate(counted):
            np.add.at(part_counts[k], cell_to_chunk[cells], c)
    starts = (np.cumsum(part_counts, axis=0) - part_counts) * POINT_DTYPE.itemsize

    records = np.empty(n, POINT_DTYPE) if n <= keep_points else None
    if records is not None:
        # Chunk after chunk in one array: each chunk's byte offsets count from its start.
        sizes = np.array([c for _lv, _p, c in chunks], np.int64) * POINT_DTYPE.itemsize
        starts = starts + (np.cumsum(sizes) - sizes)
    else:
        for i, (_lv, _p, c) in enumerate(chunks):
            with open(work_dir / f"chunk_{i:05d}.bin", "wb") as fh:
                fh.truncate(c * POINT_DTYPE.itemsize)
    memory = records.view(np.uint8) if records is not None else None
    _run_parts(
        pool,
        _distribute_part,
        [
            (src, a, b, str(work_dir), chunks, offset, scale, qsize, starts[k], memory)
            for k, (a, b) in enumerate(parts)
        ],
    )

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
        derived={"size": not has["size"], "normal": bool(estimate_normals) and not has["normal"]},
        bounds_min=[float(v) for v in lo],
        bounds_max=[float(v) for v in hi],
        node_codec=node_codec,
    )
    tmp = work_dir / f"{PLAN_FILE}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(asdict(plan)))
    os.replace(tmp, work_dir / PLAN_FILE)
    log.info("planned %d points into %d chunks over %d parts%s", n, len(chunks), len(parts),
             " (in memory)" if records is not None else "")  # fmt: skip
    return plan, records


def load_plan(work_dir: Path) -> TilePlan:
    """Read the plan :func:`plan_tiles` saved in ``work_dir``."""
    return TilePlan(**json.loads((Path(work_dir) / PLAN_FILE).read_text()))


# --------------------------------------------------------------------------- pass 2: chunks


def _morton_order(codes: np.ndarray, level_c: int, prefix_c: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Order of a chunk's points by Morton code, the sorted codes, and the deepest level it resolves.

    numpy's value sort is several times faster than its argsort, so the point index is packed
    under the code (relative to the chunk) in one uint64 key. When code and index do not fit
    in 64 bits, the code's finest levels are dropped (zero in the sorted codes returned); the
    chunk then stops splitting where those levels would be needed (leaves there keep all their
    points), so no comparison ever looks at a dropped bit.
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
    order, sorted_codes = _unpack_keys(key, base, drop, idx_bits)
    return order, sorted_codes, max_depth


def _derive(plan: TilePlan, rec: np.ndarray, work_dir: Path, index: int, write_back: bool = True) -> None:
    """Fill the derived attributes of one chunk's records in place and, with ``write_back``,
    write the chunk back (the in-process build re-reads it), with their ranges in
    ``chunk_*.range.json`` for the metadata. Neighbours are looked up within the chunk: near a
    chunk's faces a point misses those across it, which only widens its size a little there."""
    # Imported here: scipy.spatial takes about a second to import, and only clouds that lack
    # a size or normals need it (``graylight tiles`` of a scan starts without it).
    from shared.render import _neighbours

    xyz = rec["position"] * plan.scale  # relative to the offset: float64 keeps every step
    tree = _neighbours.kdtree(xyz)
    ranges = {}
    if plan.derived.get("size"):
        rec["size"] = _neighbours.spacing_size(xyz, tree=tree)
        ranges["size"] = [[float(rec["size"].min())], [float(rec["size"].max())]]
    if plan.derived.get("normal"):
        viewpoint = -np.asarray(plan.offset, np.float64)  # the world origin: where the scanner is
        rec["normal"] = _neighbours.pca_normals(xyz, viewpoint, tree=tree)
        ranges["normal"] = [rec["normal"].min(axis=0).tolist(), rec["normal"].max(axis=0).tolist()]
    if write_back:
        rec.tofile(work_dir / plan.chunks[index]["file"])
    (work_dir / f"chunk_{index:05d}.range.json").write_text(json.dumps(ranges))


def _derived_ranges(plan: TilePlan, work_dir: Path) -> None:
    """Put the derived attributes' ranges (over every chunk) into ``plan.attr_min/max``."""
    for key in (k for k, v in plan.derived.items() if v):
        lows, highs = [], []
        for i in range(len(plan.chunks)):
            path = work_dir / f"chunk_{i:05d}.range.json"
            if path.is_file():
                r = json.loads(path.read_text()).get(key)
                if r:
                    lows.append(r[0])
                    highs.append(r[1])
        if lows:
            plan.attr_min[key] = np.min(lows, axis=0).tolist()
            plan.attr_max[key] = np.max(highs, axis=0).tolist()


def _as_output(rec: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Records in the tiles' own layout (only the fields ``dtype`` keeps)."""
    if dtype == rec.dtype:
        return rec
    out = np.empty(rec.shape[0], dtype)
    for name in dtype.names:
        out[name] = rec[name]
    return out


def _chunk_nodes(
    work_dir: Path, index: int, rec: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, list[list]]:
    """Sample chunk ``index``: its records as read (from its file, or ``rec`` when given: the
    chunk's (N,) :data:`POINT_DTYPE` records held in memory), the order grouping them by node,
    and the node table ``[name, numPoints, byteOffset, own]`` (offsets into the grouped records)."""
    plan = load_plan(work_dir)
    spec = plan.chunks[index]
    in_file = rec is None
    if in_file:
        rec = np.fromfile(work_dir / spec["file"], dtype=POINT_DTYPE)
    if any(plan.derived.values()):
        _derive(plan, rec, work_dir, index, write_back=in_file)
    level_c, prefix_c = spec["level"], spec["prefix"]
    order, codes, max_depth = _morton_order(morton_codes(rec["position"], plan.qsize), level_c, prefix_c)
    assigned, levels, prefixes, own = _build_nodes(codes, level_c, prefix_c, plan.max_leaf, max_depth)
    by_node, bounds = _counting_order(assigned, levels.shape[0])
    counts = np.diff(bounds)
    table = [
        [node_name(int(levels[i]), int(prefixes[i])), int(counts[i]), int(bounds[i]) * plan.point_dtype().itemsize,
         bool(own[i])]
        for i in range(levels.shape[0])
        if counts[i] > 0 or own[i]
    ]  # fmt: skip
    # Morton order, then grouped by node: one gather of the records does both.
    return rec, order[by_node], table


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
    rec, by_node, table = _chunk_nodes(work_dir, index)
    tmp_bin = out_bin.with_name(out_bin.name + f".{os.getpid()}.tmp")
    _as_output(_permute(rec, by_node), load_plan(work_dir).point_dtype()).tofile(tmp_bin)
    os.replace(tmp_bin, out_bin)
    tmp_json = out_json.with_name(out_json.name + f".{os.getpid()}.tmp")
    tmp_json.write_text(json.dumps(table))
    os.replace(tmp_json, out_json)  # last: its presence marks the chunk done
    return out_json


# --------------------------------------------------------------------------- pass 3: merge


def _attributes(plan: TilePlan) -> list[dict]:
    """The attributes list of ``metadata.json``: the position and what the cloud has or the
    chunks derived, in :data:`POINT_DTYPE` order (for a full cloud, all of them)."""
    lo, hi = plan.bounds_min, plan.bounds_max
    present = plan.point_dtype().names

    def rng(key: str, k: int, default: float, factor: float = 1.0) -> tuple[list[float], list[float]]:
        mn, mx = plan.attr_min[key], plan.attr_max[key]
        if not (plan.has.get(key) or plan.derived.get(key)) or not all(math.isfinite(v) for v in mn + mx):
            return [default] * k, [default] * k
        return [v * factor for v in mn], [v * factor for v in mx]

    rgb_min, rgb_max = rng("rgb", 3, 65535.0, 257.0)
    n_min, n_max = rng("normal", 3, 0.0)
    s_min, s_max = rng("size", 1, 0.0)
    normal_text = "unit normal (estimated from neighbours)" if plan.derived.get("normal") else "unit normal"
    size_text = ("world-space sample size from the local point spacing" if plan.derived.get("size")
                 else "world-space sample size Z / f_camera")  # fmt: skip
    out = [
        {"name": "position", "description": "", "size": 12, "numElements": 3, "elementSize": 4,
         "type": "int32", "min": lo, "max": hi},
    ]  # fmt: skip
    if "rgb" in present:
        out.append({"name": "rgb", "description": "", "size": 6, "numElements": 3, "elementSize": 2,
                    "type": "uint16", "min": rgb_min, "max": rgb_max})  # fmt: skip
    if "normal" in present:
        # Normals as three scalars: Potree and potree-core both join NormalX/Y/Z into a
        # NORMAL vector (potree-core cannot decode a 3-element "normal"); same bytes.
        out += [{"name": f"Normal{axis}", "description": normal_text, "size": 4, "numElements": 1,
                 "elementSize": 4, "type": "float", "min": [n_min[k]], "max": [n_max[k]]}
                for k, axis in enumerate("XYZ")]  # fmt: skip
    if "size" in present:
        out.append({"name": "size", "description": size_text, "size": 4,
                    "numElements": 1, "elementSize": 4, "type": "float", "min": s_min, "max": s_max})  # fmt: skip
    return out


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
    rec_dtype = HIERARCHY_DTYPE
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


def _layout(
    tables: list[list[list]], itemsize: int = POINT_DTYPE.itemsize
) -> tuple[dict[str, dict], list[list[tuple[int, int, int]]], int]:
    """Where every chunk's node pieces go in ``octree.bin``: nodes breadth first, a node's
    pieces in chunk order. Returns the nodes (name -> points, offset, size), per chunk its
    copies ``(source byte offset, octree.bin byte offset, bytes)``, and the file size."""
    pieces: dict[str, list[tuple[int, int, int]]] = {}  # name -> [(chunk, byte offset, points)]
    for i, table in enumerate(tables):
        for name, npts, off, _own in table:
            pieces.setdefault(name, []).append((i, off, npts))
    for name in list(pieces):  # every node needs its ancestors, even one left empty
        for k in range(1, len(name)):
            pieces.setdefault(name[:k], [])
    nodes: dict[str, dict] = {}
    copies: list[list[tuple[int, int, int]]] = [[] for _ in tables]
    pos = 0
    for nm in sorted(pieces, key=lambda s: (len(s), s)):
        npts = 0
        for ci, off, cnt in pieces[nm]:
            if cnt:
                copies[ci].append((off, pos + npts * itemsize, cnt * itemsize))
                npts += cnt
        size = npts * itemsize
        nodes[nm] = {"points": npts, "offset": pos, "size": size}
        pos += size
    return nodes, copies, pos


def _code_nodes(
    octree_bin: Path, nodes: dict[str, dict], dtype: np.dtype, workers: int
) -> tuple[dict[str, dict], int]:
    """Replace the plain ``octree_bin`` by the octree-coded nodes (:mod:`shared.compress.tilenode`),
    breadth first as before; returns the nodes with their new offsets and sizes, and the file
    size. The plain file is read one node at a time; ``workers`` threads code nodes at once (the
    kernels and zlib release the GIL)."""
    coded = octree_bin.with_name(octree_bin.name + ".coded")
    out: dict[str, dict] = {}
    pos = 0
    names = [nm for nm in nodes if nodes[nm]["points"]]
    with open(coded, "wb") as f, ThreadPoolExecutor(max(1, workers)) as pool:
        futures = {
            nm: pool.submit(tilenode.encode_node, np.fromfile(octree_bin, dtype=dtype, count=nodes[nm]["points"],
                                                              offset=nodes[nm]["offset"]))
            for nm in names[: 2 * max(1, workers)]
        }  # fmt: skip
        ahead = len(futures)
        for nm, info in nodes.items():
            if not info["points"]:
                out[nm] = {"points": 0, "offset": pos, "size": 0}
                continue
            data = futures.pop(nm).result()
            if ahead < len(names):  # keep a few nodes in flight, not the whole file in memory
                nxt = names[ahead]
                rec = np.fromfile(octree_bin, dtype=dtype, count=nodes[nxt]["points"], offset=nodes[nxt]["offset"])
                futures[nxt] = pool.submit(tilenode.encode_node, rec)
                ahead += 1
            f.write(data)
            out[nm] = {"points": info["points"], "offset": pos, "size": len(data)}
            pos += len(data)
    plain = octree_bin.stat().st_size
    os.replace(coded, octree_bin)
    log.info("octree-coded %d nodes: %d -> %d bytes (%.2fx)", len(names), plain, pos, plain / max(pos, 1))
    return out, pos


def _write_tiles(plan: TilePlan, nodes: dict[str, dict], nbytes: int, out_dir: Path, fill, workers: int = 1) -> dict:
    """Write the tiles folder in a staging folder and rename it to ``out_dir`` (replacing an
    older one); ``fill(octree_bin)`` writes the points into the pre-sized ``octree.bin``. With
    the plan's octree node codec, the plain nodes are then coded (``workers`` threads)."""
    total = sum(info["points"] for info in nodes.values())
    if total != plan.points:
        raise RuntimeError(f"tiles hold {total} points, the cloud has {plan.points}")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    try:
        with open(stage / "octree.bin", "wb") as f:
            f.truncate(nbytes)
        fill(stage / "octree.bin")
        if plan.node_codec != "plain":
            nodes, nbytes = _code_nodes(stage / "octree.bin", nodes, plan.point_dtype(), workers)
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
            "encoding": NODE_CODECS[plan.node_codec],
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
    return {"points": plan.points, "nodes": len(nodes), "depth": depth, "bytes": int(nbytes)}


def merge_tiles(work_dir: Path, out_dir: Path) -> dict:
    """Pass 3: gather every chunk's node pieces into ``octree.bin``, write the hierarchy and
    metadata, and rename the finished folder to ``out_dir`` (replacing an older one).
    ``work_dir`` is left in place for the caller to remove.

    Returns a report: points, nodes, depth, bytes.
    """
    work_dir = Path(work_dir)
    plan = load_plan(work_dir)
    tables = [
        json.loads((work_dir / f"chunk_{i:05d}.nodes.json").read_text()) for i in range(len(plan.chunks))
    ]
    nodes, copies, nbytes = _layout(tables, plan.point_dtype().itemsize)
    _derived_ranges(plan, work_dir)

    def fill(octree_bin: Path) -> None:
        with open(octree_bin, "r+b", buffering=0) as out:
            for i, chunk_copies in enumerate(copies):
                with open(work_dir / f"chunk_{i:05d}.nodes.bin", "rb", buffering=0) as src:
                    for src_off, dst_off, n in chunk_copies:
                        _copy_range(src, out, src_off, dst_off, n)

    return _write_tiles(plan, nodes, nbytes, Path(out_dir), fill, workers=cpu_budget())


# --------------------------------------------------------------------------- in-process build


def _chunk_table_job(work: str, index: int, kept: dict[int, Any] | None = None) -> list[list]:
    """In-process pass 2, first half: sample chunk ``index`` and return the node table.

    With ``kept`` (a cloud of at most :data:`KEEP_POINTS`, the pool's threads share it), the
    chunk's records come from ``kept[index]`` (in memory since the distribution) and wait
    there with the order grouping them by node for the second half. Otherwise they are read
    from the chunk's file and the order goes to ``chunk_*.order`` (4 bytes a point)."""
    rec, by_node, table = _chunk_nodes(Path(work), index, kept.pop(index) if kept is not None else None)
    if kept is not None:
        kept[index] = (rec, by_node)
        return table
    dtype = np.uint32 if rec.shape[0] <= np.iinfo(np.uint32).max else np.int64
    by_node.astype(dtype).tofile(Path(work) / f"chunk_{index:05d}.order.{np.dtype(dtype).str[1:]}")
    return table


def _chunk_write_job(
    work: str, index: int, octree_bin: str, copies: list[tuple[int, int, int]], kept: dict[int, Any] | None = None
) -> None:  # fmt: skip
    """In-process pass 2, second half: write chunk ``index``'s node pieces straight to their
    places in ``octree.bin`` (no intermediate pieces file, no serial concatenation); the
    records and their order from ``kept`` (then dropped) or the chunk's files (then removed)."""
    work_dir = Path(work)
    if kept is not None:
        rec, by_node = kept.pop(index)
    else:
        rec = np.fromfile(work_dir / f"chunk_{index:05d}.bin", dtype=POINT_DTYPE)
        (order_file,) = work_dir.glob(f"chunk_{index:05d}.order.*")
        by_node = np.fromfile(order_file, dtype=order_file.suffix[1:])
    data = memoryview(_as_output(_permute(rec, by_node), load_plan(work_dir).point_dtype())).cast("B")
    del rec, by_node
    fd = os.open(octree_bin, os.O_WRONLY)
    try:
        for src_off, dst_off, n in copies:
            _pwrite_all(fd, data[src_off : src_off + n], dst_off)
    finally:
        os.close(fd)
    if kept is None:
        # Done with this chunk's files: drop them now (in parallel) rather than at the end.
        (work_dir / f"chunk_{index:05d}.bin").unlink()
        order_file.unlink()


def _warm_kernels() -> None:
    """Load every kernel once (from numba's cache) before the pool's threads call them; the fields
    mimic a memory-mapped cloud PLY (read-only strided views of its records), so the kernels
    loaded are the ones the passes call. The first of them initialises numba's target; it does
    so without importing scipy.linalg (:mod:`shared.core.numba_start`, a quarter second)."""
    with blas_check_without_scipy_linalg():
        _load_kernels()


def _load_kernels() -> None:
    """Call every kernel of the passes once on two-point inputs of the passes' types."""
    cloud = np.frombuffer(bytes(2 * CLOUD_DTYPE.itemsize), CLOUD_DTYPE)
    f = _Fields(cloud["x"], cloud["y"], cloud["z"], (cloud["red"], cloud["green"], cloud["blue"]),
                (cloud["nx"], cloud["ny"], cloud["nz"]), cloud["size"])  # fmt: skip
    lo, hi, amin, amax = np.zeros(3), np.ones(3), np.zeros(7), np.ones(7)
    _scan_kernel(*f.kernel_args(), lo, hi, amin, amax)
    _count_kernel(f.x, f.y, f.z, lo, 1.0, 8, 60, np.zeros(8, np.int64))
    rec = np.empty(2, POINT_DTYPE)
    _distribute_kernel(*f.kernel_args(), lo, 1.0, 8, 60, np.zeros(8, np.int32), 1, rec["position"],
                       rec["rgb"], rec["normal"], rec["size"], np.empty((2, 3), np.int32),
                       np.empty(2, np.int32))  # fmt: skip
    rec = np.zeros(2, POINT_DTYPE)
    codes = morton_codes(rec["position"], 8)
    _, sorted_codes, _ = _morton_order(codes, 0, 0)
    assigned, levels, _, _ = _build_nodes(sorted_codes, 0, 0, 1, MAX_DEPTH)
    _counting_order(assigned, levels.shape[0])
    _permute(rec, np.arange(2))


def build_tiles(
    cloud_ply: Path,
    out_dir: Path,
    *,
    workers: int | None = None,
    max_chunk: int = 2_000_000,
    max_leaf: int = 10_000,
    scale: float | None = None,
    estimate_normals: bool = False,
    node_codec: str = "plain",
    progress: Callable[[float], None] | None = None,
) -> dict:
    """Build Potree 2.0 tiles from ``cloud_ply`` into ``out_dir`` (all passes, in-process).

    ``workers`` threads run the passes over the cloud and build chunks in parallel (default:
    :func:`~shared.core.threads.cpu_budget`; 1 runs in the calling thread). Temporary chunk
    files (none for a cloud of at most :data:`KEEP_POINTS` points) live beside ``out_dir`` and
    are removed. ``scale``, ``estimate_normals`` and ``node_codec`` as :func:`plan_tiles`.
    ``progress`` gets the fraction done: 0.2 once the cloud is distributed into chunks, then by
    points of the chunks laid out (to 0.6) and written (to 1.0).
    Returns a report with points, nodes, depth, bytes, chunks, seconds and points_per_second.
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    workers = max(1, workers or cpu_budget())
    report_progress = progress or (lambda f: None)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.work.", dir=out_dir.parent))
    try:
        _warm_kernels()
        # One pool of threads for every pass: the kernels, numpy's sort and take and the file
        # I/O release the GIL. A pool of forked processes cost a 2 M-point build 0.3 s more CPU
        # (copying the page tables of a process holding numba, copy-on-write faults, exits).
        with contextlib.ExitStack() as stack:
            pool = stack.enter_context(ThreadPoolExecutor(workers)) if workers > 1 else None
            # A cloud of at most KEEP_POINTS is distributed into memory, and every chunk's
            # records and order stay there between the halves of pass 2: no chunk files.
            plan, records = _plan(
                Path(cloud_ply), work, max_chunk=max_chunk, max_leaf=max_leaf, pool=pool, workers=workers,
                scale=scale, estimate_normals=estimate_normals, node_codec=node_codec, keep_points=KEEP_POINTS,
            )
            nchunks = len(plan.chunks)
            kept: dict[int, Any] | None = None
            if records is not None:
                ends = np.cumsum([c["points"] for c in plan.chunks])
                kept = {i: records[e - c["points"] : e] for i, (c, e) in enumerate(zip(plan.chunks, ends, strict=True))}
                del records  # the chunks' views hold it, and free it once written
            # Largest chunks first keeps the pool busy to the end.
            order = sorted(range(nchunks), key=lambda i: -plan.chunks[i]["points"])
            report_progress(0.2)
            share = np.cumsum([plan.chunks[i]["points"] for i in order]) / max(plan.points, 1)
            chunk_pool = pool if nchunks > 1 else None
            # Chunks deriving attributes are sampled one at a time: their neighbour queries and
            # normals kernel already use every core, and numba's workqueue layer (where neither
            # TBB nor OpenMP loads) refuses launches from two threads at once.
            table_pool = None if any(plan.derived.values()) else chunk_pool
            tables: list[list[list]] = [[] for _ in range(nchunks)]
            done = _run_parts(table_pool, _chunk_table_job, [(str(work), i, kept) for i in order],
                              done=lambda k: report_progress(0.2 + 0.4 * float(share[k])))
            for i, table in zip(order, done, strict=True):
                tables[i] = table
            nodes, copies, nbytes = _layout(tables, plan.point_dtype().itemsize)
            _derived_ranges(plan, work)

            def fill(octree_bin: Path) -> None:
                calls = [(str(work), i, str(octree_bin), copies[i], kept) for i in order]
                _run_parts(chunk_pool, _chunk_write_job, calls, done=lambda k: report_progress(0.6 + 0.4 * float(share[k])))

            report = _write_tiles(plan, nodes, nbytes, out_dir, fill, workers=workers)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    dt = time.perf_counter() - t0
    report.update(chunks=nchunks, seconds=dt, points_per_second=plan.points / dt if dt > 0 else 0.0)
    return report
