"""Pass 2 of the Potree 2.0 tile build (:mod:`shared.render.octree`): one chunk.

:func:`build_chunk` samples one chunk of the plan (:mod:`shared.render._tileplan`) into its
subtree's nodes and its share of the nodes above it, independently of every other chunk (the
parallel unit: a thread in-process, a task under the job service). Because every cell a node
at level L samples from (level L + 7) lies inside one chunk (chunks sit at level <= 7), a
chunk can compute its exact share of the nodes above it. :func:`_chunk_nodes` is the sampling
both the fan-out and the in-process build use; :func:`_derive` fills the attributes a cloud
lacks (size, normals) per chunk.

Imports the plan module; the merge (:mod:`shared.render.octree`) imports this one.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from shared.render._octree_kernels import (
    GRID_LEVELS,
    MORTON_BITS,
    _build_nodes,
    _counting_order,
    _pack_keys,
    _unpack_keys,
    morton_codes,
)
from shared.render._tileplan import POINT_DTYPE, TilePlan, load_plan

MAX_DEPTH = MORTON_BITS - GRID_LEVELS  # deepest level whose sampling grid the codes resolve


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
