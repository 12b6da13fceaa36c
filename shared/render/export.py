"""Export a cloud PLY to the formats other tools read: LAZ, COPC, E57 or PLY.

In: a cloud PLY (:mod:`shared.formats.ply`; any scalar vertex properties). Out: one file,
written under a temporary name and renamed when complete:

- ``laz``: LAS 1.4 compressed with LASzip, every property kept (:func:`shared.formats.las.write_las`);
- ``las``: the same, uncompressed;
- ``copc``: cloud-optimised LAZ with the same dimensions as ``laz``. The octree is the Potree
  tiles builder's (:func:`shared.render.octree.build_tiles`, out of core and in parallel),
  built at the LAS scale of :func:`shared.formats.las.coordinate_scale`, then written node by
  node (:func:`shared.formats.las.write_copc`); properties the tiles do not carry
  (``confidence``, ``view``...) are looked up in the source by position;
- ``e57``: one scan with colour and normals (:func:`shared.formats.e57.write_e57`);
- ``ply``: binary little-endian PLY with every property and comment of the source.

Coordinates stay in the rig's frame and units (the PLY's ``comment units`` line, mm by default).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from shared.core.errors import InputError
from shared.formats.e57 import write_e57
from shared.formats.las import cloud_bounds, coordinate_scale, las_layout, ply_units, write_copc, write_las
from shared.formats.ply import iter_ply_records, read_header, write_ply_records
from shared.formats.potree import open_tiles
from shared.render._match import match_points
from shared.render.octree import build_tiles, quantise

FORMATS = ("laz", "las", "copc", "e57", "ply")
#: PLY properties the tiles carry; the COPC export looks the others up in the source.
TILE_PROPERTIES = frozenset({"x", "y", "z", "red", "green", "blue", "nx", "ny", "nz", "size"})


def _source_lookup(cloud_ply: Path, tiles, extras: tuple[tuple[str, str, str], ...]):
    """A function from a tile node's (N, 3) int32 positions to the source cloud's ``extras``
    properties of those points (by LAS name).

    The source points are quantised exactly as the tiles builder does and sorted by position
    (memory: 20 bytes a point); each tile point then finds its own source point by binary
    search, coincident points each taking a different one."""
    header = read_header(cloud_ply)
    offset = np.asarray(tiles.offset, np.float64)
    scale = float(np.asarray(tiles.scale, np.float64)[0])
    qsize = int(round(float(tiles.box_max[0] - tiles.box_min[0]) / scale))
    q = np.empty((header.count, 3), np.int32)
    pos = 0
    for rec in iter_ply_records(cloud_ply):
        xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
        q[pos : pos + len(rec)] = quantise(xyz, offset, scale, qsize)
        pos += len(rec)
    order = np.lexsort((q[:, 2], q[:, 1], q[:, 0]))
    sorted_q = np.ascontiguousarray(q[order])
    del q
    used = np.zeros(header.count, bool)
    source = next(iter_ply_records(cloud_ply, max(header.count, 1)))  # a memory map, not a copy

    def lookup(ixyz: np.ndarray) -> dict[str, np.ndarray]:
        idx = np.empty(ixyz.shape[0], np.int64)
        # Contiguous and writable always: a one-point node's positions come contiguous and
        # read-only from the tiles, and the kernel would compile a signature for them alone.
        missing = match_points(sorted_q, order, np.require(ixyz, np.int32, ("C", "W")), used, idx)
        if missing:
            raise RuntimeError(f"{missing} tile points have no source point in {cloud_ply}")
        return {las: np.asarray(source[src][idx]) for las, src, _t in extras}

    return lookup


def export_cloud(
    cloud_ply: Path, out: Path, fmt: str, *, workers: int | None = None, max_leaf: int = 10_000
) -> dict:
    """Write ``cloud_ply`` to ``out`` in ``fmt`` (one of :data:`FORMATS`).

    ``workers`` processes build the COPC octree (default: the CPU count); an octree node keeps
    at most ``max_leaf`` points where it stops splitting (one LAZ chunk a node). Returns a report:
    format, output, points, bytes, seconds, plus the writer's own figures (scale, bounds...).
    Raises :class:`InputError` for an unknown format or a bad cloud.
    """
    t0 = time.perf_counter()
    cloud_ply, out = Path(cloud_ply), Path(out)
    if fmt not in FORMATS:
        raise InputError("format", f"must be one of {', '.join(FORMATS)}, got {fmt!r}")
    header = read_header(cloud_ply)
    if out.resolve() == cloud_ply.resolve():
        raise InputError(out, "the export would overwrite its source cloud")
    units = ply_units(cloud_ply)
    if fmt in ("laz", "las"):
        report = write_las(cloud_ply, out, compressed=fmt == "laz")
    elif fmt == "copc":
        _n, lo, hi = cloud_bounds(cloud_ply)
        scale = coordinate_scale(lo, hi)
        out.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tiles", dir=out.parent))
        try:
            build_tiles(cloud_ply, work / "tiles", workers=workers, scale=scale, max_leaf=max_leaf)
            tiles = open_tiles(work / "tiles")
            extras = tuple(e for e in las_layout(header.dtype, cloud_ply).extra if e[1] not in TILE_PROPERTIES)
            lookup = _source_lookup(cloud_ply, tiles, extras) if extras else None
            report = write_copc(tiles, out, units=units, extras=extras, lookup=lookup)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    elif fmt == "e57":
        report = write_e57(cloud_ply, out, units=units)
    else:
        write_ply_records(out, iter_ply_records(cloud_ply), header.count, header.dtype, header.comments)
        report = {"points": header.count, "properties": list(header.dtype.names or ())}
    report.update(format=fmt, output=str(out), bytes=out.stat().st_size, seconds=time.perf_counter() - t0)
    return report
