"""Pass 1 of the Potree 2.0 tile build (:mod:`shared.render.octree`): the plan.

:func:`plan_tiles` streams the cloud PLY for bounds and attribute ranges, counts points per
cell of a 128^3 grid, chooses the chunks (the largest octree nodes holding at most
``max_chunk`` points) and distributes the points into one file per chunk (or into memory for
the in-process build); :class:`TilePlan` is what it found and decided, saved as ``plan.json``
(:data:`PLAN_FILE`) and read back by :func:`load_plan`. Also here: the point record of the
build (:data:`POINT_DTYPE`), the node encodings (:data:`NODE_CODECS`), :func:`quantise` and
the helpers that run a pass over ranges of the cloud in a pool.

The chunk pass (:mod:`shared.render._tilechunk`) and the merge (:mod:`shared.render.octree`)
import from here, never the other way.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from shared.compress import tilenode
from shared.core.errors import InputError
from shared.formats.ply import iter_ply_chunks, read_header
from shared.render._octree_kernels import (
    MORTON_BITS,
    _count_kernel,
    _distribute_kernel,
    _quantise_kernel,
    _scan_kernel,
)

log = logging.getLogger(__name__)

#: One point in ``octree.bin`` (34 bytes, packed, little-endian).
POINT_DTYPE = np.dtype(
    [("position", "<i4", (3,)), ("rgb", "<u2", (3,)), ("normal", "<f4", (3,)), ("size", "<f4")]
)
COUNT_LEVEL = 7  # level of the counting grid; chunks are never deeper than this
READ_CHUNK = 1 << 20  # points a slice of the passes over the cloud
MIN_PART_POINTS = 1 << 20  # smallest range of the cloud a pass hands to a worker
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
