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

The passes live in private modules whose imports run one way: pass 1 and the plan record in
:mod:`shared.render._tileplan`, pass 2 in :mod:`shared.render._tilechunk` (which imports the
plan module), pass 3 and the in-process build here (which imports both); every public name
of the build is importable from this module.
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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from shared.compress import tilenode
from shared.core.numba_start import blas_check_without_scipy_linalg
from shared.core.threads import cpu_budget
from shared.formats.ply import CLOUD_DTYPE
from shared.formats.potree import HIERARCHY_DTYPE, HIERARCHY_STEP
from shared.render._octree_kernels import (
    _build_nodes,
    _count_kernel,
    _counting_order,
    _distribute_kernel,
    _scan_kernel,
    morton_codes,
)
from shared.render._tilechunk import (
    MAX_DEPTH,
    _as_output,
    _chunk_nodes,
    _derived_ranges,
    _morton_order,
    _permute,
    build_chunk,
    node_name,
)
from shared.render._tileplan import (
    NODE_CODECS,
    PLAN_FILE,
    POINT_DTYPE,
    TilePlan,
    _Fields,
    _plan,
    _pwrite_all,
    _run_parts,
    load_plan,
    plan_tiles,
    quantise,
    tiles_dtype,
)

__all__ = [
    "KEEP_POINTS",
    "NODE_CODECS",
    "PLAN_FILE",
    "POINT_DTYPE",
    "TilePlan",
    "build_chunk",
    "build_tiles",
    "load_plan",
    "merge_tiles",
    "node_name",
    "plan_tiles",
    "quantise",
    "tiles_dtype",
]

log = logging.getLogger(__name__)

BYTES_PER_NODE = HIERARCHY_DTYPE.itemsize  # 22
KEEP_POINTS = 1 << 23  # clouds up to this many points keep pass 2's chunks in memory (~40 bytes a point)


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
