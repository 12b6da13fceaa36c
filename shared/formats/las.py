"""LAS 1.4 / LAZ and COPC point clouds: what GIS and survey software (QGIS, PDAL, CloudCompare,
Potree) read.

Both writers produce LAS 1.4 with point data record format 7 (XYZ, RGB) or 6 when the cloud
has no colour, compressed with LASzip through ``lazrs``. The cloud's other per-point
properties go to LAS 1.4 extra bytes (described in the Extra Bytes VLR, so readers show them
by name): the unit normal as ``NormalX``, ``NormalY``, ``NormalZ`` (PDAL's dimension names),
the world sample ``size`` and any other scalar property the PLY carries (``confidence``,
``view``), each with its own type. 8-bit colour is scaled to LAS's 16-bit range (times 257).
Return number and number of returns are 1 (one return a sample, as LAS 1.4 requires).

Coordinates stay in the rig's frame and units (millimetres for Graylight: LAS has no unit
field, the VLR ``graylight``/1 says it in text). They are stored as integers
``X = floor((x - offset) * (1 / scale) + 0.5)`` (the tiles builder's own quantisation) with
``offset`` the cloud's minimum corner and ``scale`` from :func:`coordinate_scale`: the
largest power of ten not above the float32 step at the cloud's largest coordinate magnitude.
The PLY holds float32 positions, so no coordinate moves by more than half the float32 step
at the cloud's largest coordinate, the PLY's own coarsest rounding (for an object within
600 mm of the camera the scale is 1e-5 mm = 10 nm, three to four orders of magnitude below
the scanner's depth noise), while the integers span at most 20 * 2**24 steps, well inside
int32.

COPC (cloud-optimised LAZ, https://copc.io): the same points, reordered into an octree whose
every node is one LAZ chunk, with the ``copc``/1 info VLR first and the ``copc``/1000
hierarchy (one page: ``VoxelKey`` level, x, y, z; offset; byte size; point count) as an
extended VLR after the points. :func:`write_copc` takes the octree from Potree 2.0 tiles
(:mod:`shared.formats.potree`, built with the same scale and offset), whose nodes are cubes of
the same root cube and which hold every point once (additive level of detail, as COPC). The
integer positions are copied, so every point lies inside its node's bounds exactly. Dimensions
the tiles do not carry come from a ``lookup`` of the source (:func:`shared.render.export`
finds each tile point's source point by position), so COPC holds what LAZ holds.

Both writers stream: chunks of the PLY (memory-mapped) or one node group at a time.
"""

from __future__ import annotations

import io
import logging
import math
import os
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import laspy
import lazrs
import numpy as np
from laspy.vlrs.known import LasZipVlr

from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.formats.ply import CHUNK, iter_ply_records, read_header

log = logging.getLogger(__name__)

#: PLY properties with a place of their own in a LAS record (the rest become extra bytes).
POSITION = ("x", "y", "z")
COLOUR = ("red", "green", "blue")
#: PLY property -> LAS extra-bytes dimension name (PDAL's names for normals).
EXTRA_NAMES = {"nx": "NormalX", "ny": "NormalY", "nz": "NormalZ"}
EXTRA_DESCRIPTIONS = {
    "NormalX": "unit normal x",
    "NormalY": "unit normal y",
    "NormalZ": "unit normal z",
    "size": "world sample size Z/f_camera",
    "confidence": "decode confidence 0..1",
    "view": "index of the view",
}
#: Extra-bytes types LAS 1.4 defines (data_type 1..10).
_LAS_EXTRA_TYPES = {"u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8", "f4", "f8"}
#: Points a COPC compression batch holds (nodes are grouped until they reach it).
COPC_BATCH = 1 << 20
COPC_INFO_SIZE = 160
COPC_ENTRY = struct.Struct("<iiiiQii")  # VoxelKey level, x, y, z; offset; byte size; point count


@dataclass(frozen=True)
class LasLayout:
    """How a cloud's properties map to a LAS record: ``point_format`` 6 or 7, ``extra`` a list of
    (LAS dimension name, source property name, numpy dtype string)."""

    point_format: int
    extra: tuple[tuple[str, str, str], ...]

    @property
    def has_colour(self) -> bool:
        return self.point_format in (7, 8)


def las_layout(properties: np.dtype, where: str | Path = "cloud") -> LasLayout:
    """The LAS layout of a cloud whose vertex records have the structured dtype ``properties``.

    Raises :class:`InputError` naming ``where`` for a property LAS extra bytes cannot hold.
    """
    names = list(properties.names or ())
    colour = set(COLOUR) <= set(names)
    extra = []
    for name in names:
        if name in POSITION or (colour and name in COLOUR):
            continue
        t = properties[name].str[1:]
        if t not in _LAS_EXTRA_TYPES:
            raise InputError(
                where, f"property {name!r} of type {properties[name]} has no LAS extra-bytes type"
            )
        extra.append((EXTRA_NAMES.get(name, name), name, t))
    return LasLayout(point_format=7 if colour else 6, extra=tuple(extra))


def coordinate_scale(lo: np.ndarray, hi: np.ndarray) -> float:
    """Power-of-ten LAS scale keeping float32 precision (see the module docstring).

    ``lo``/``hi`` (3,) are the cloud's bounds; returns the largest power of ten not above the
    float32 step at the largest coordinate magnitude (at least 1e-9, for a cloud at the origin).
    """
    m = float(np.max(np.abs(np.concatenate([np.asarray(lo, np.float64), np.asarray(hi, np.float64)]))))
    step = max(m * 2.0**-23, 1e-9)  # float32 spacing at magnitude m lies within [m 2**-24, m 2**-23]
    scale = 10.0 ** math.floor(math.log10(step * 0.5))
    return max(scale, 1e-9)


def las_header(layout: LasLayout, scale: float, offset: np.ndarray, units: str = "mm") -> laspy.LasHeader:
    """A LAS 1.4 header for ``layout`` with the extra-bytes VLR and a text VLR naming the units."""
    header = laspy.LasHeader(version="1.4", point_format=layout.point_format)
    header.scales = np.full(3, float(scale))
    header.offsets = np.asarray(offset, np.float64)
    header.generating_software = "graylight"
    if layout.extra:
        header.add_extra_dims(
            [laspy.ExtraBytesParams(las, np.dtype(t), description=EXTRA_DESCRIPTIONS.get(las, src)[:32])
             for las, src, t in layout.extra]
        )  # fmt: skip
    header.vlrs.append(laspy.VLR("graylight", 1, "units", f"units {units}".encode("ascii")))
    return header


def _record(n: int, header: laspy.LasHeader) -> laspy.ScaleAwarePointRecord:
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    # One return a sample: return number 1 of 1 (bits 0-3 and 4-7 of the first flag byte).
    rec.array["bit_fields"] = 0x11
    return rec


def ply_to_las(rec: np.ndarray, header: laspy.LasHeader, layout: LasLayout) -> laspy.ScaleAwarePointRecord:
    """PLY vertex records (structured, any byte order) -> LAS points of ``header``'s format."""
    out = _record(len(rec), header)
    inv = 1.0 / header.scales
    for k, (axis, field) in enumerate(zip(POSITION, ("X", "Y", "Z"), strict=True)):
        out.array[field] = np.floor((rec[axis].astype(np.float64) - header.offsets[k]) * inv[k] + 0.5)
    if layout.has_colour:
        for c in COLOUR:
            v = rec[c]
            out.array[c] = v.astype(np.uint16) * 257 if v.dtype.itemsize == 1 else v
    for las, src, _t in layout.extra:
        out.array[las] = rec[src]
    return out


def cloud_bounds(cloud_ply: Path, chunk: int = CHUNK) -> tuple[int, np.ndarray, np.ndarray]:
    """One streaming pass over a PLY cloud: its point count and (3,) float64 min and max.
    Raises :class:`InputError` for an empty cloud or NaN / infinite coordinates."""
    n = 0
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for rec in iter_ply_records(cloud_ply, chunk):
        xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
        if not np.isfinite(xyz).all():
            raise InputError(cloud_ply, "the cloud holds NaN or infinite coordinates")
        if len(xyz):
            lo = np.minimum(lo, xyz.min(axis=0))
            hi = np.maximum(hi, xyz.max(axis=0))
        n += len(rec)
    if n == 0:
        raise InputError(cloud_ply, "the point cloud is empty (0 points)")
    return n, lo, hi


def ply_units(cloud_ply: Path) -> str:
    """The units a Graylight PLY names in its ``comment units ...`` line (default mm)."""
    for c in read_header(cloud_ply).comments:
        parts = c.split()
        if len(parts) == 2 and parts[0] == "units":
            return parts[1]
    return "mm"


def write_las(
    cloud_ply: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    compressed: bool = True,
    scale: float | None = None,
    chunk: int = CHUNK,
) -> dict:
    """Write a PLY cloud as LAS 1.4 (LAZ when ``compressed``), streaming ``chunk`` points at a time.

    Every vertex property is kept (layout in the module docstring). ``scale`` overrides
    :func:`coordinate_scale`. Written atomically. Returns points, scale, offset, bounds
    (min, max) and the extra dimensions.
    """
    cloud_ply, out = Path(cloud_ply), Path(out)
    layout = las_layout(read_header(cloud_ply).dtype, cloud_ply)
    n, lo, hi = cloud_bounds(cloud_ply, chunk)
    scale = float(scale) if scale is not None else coordinate_scale(lo, hi)
    if not (scale > 0 and math.isfinite(scale)) or (hi - lo).max() / scale >= 2**31 - 2:
        raise InputError("scale", f"{scale!r} cannot hold the cloud's extent {(hi - lo).max():.6g} in int32")
    header = las_header(layout, scale, lo, ply_units(cloud_ply))
    backend = laspy.LazBackend.LazrsParallel if compressed else None
    with atomic_file(out, suffix=out.suffix or ".las") as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=compressed, laz_backend=backend) as w:
            for rec in iter_ply_records(cloud_ply, chunk):
                w.write_points(ply_to_las(rec, header, layout))
    return {
        "points": n, "scale": scale, "offset": lo.tolist(), "min": lo.tolist(), "max": hi.tolist(),
        "extra": [e[0] for e in layout.extra], "point_format": layout.point_format,
    }  # fmt: skip


# --------------------------------------------------------------------------- COPC


@dataclass(frozen=True)
class CopcNode:
    """One octree node for :func:`write_copc_nodes`: its key (level, x, y, z: cube index along
    each axis at that level, x the first) and its points' integer coordinates ``ixyz`` (N, 3)
    int32 (same scale/offset as the header), ``rgb`` (N, 3) uint16 or None, and the extra
    dimensions by LAS name."""

    key: tuple[int, int, int, int]
    ixyz: np.ndarray
    rgb: np.ndarray | None
    extra: dict[str, np.ndarray]


def potree_key(name: str) -> tuple[int, int, int, int]:
    """COPC VoxelKey of a Potree node name ("r" then one child digit a level, bit 2 = x)."""
    x = y = z = 0
    for ch in name[1:]:
        d = int(ch)
        x, y, z = 2 * x + ((d >> 2) & 1), 2 * y + ((d >> 1) & 1), 2 * z + (d & 1)
    return len(name) - 1, x, y, z


def _copc_info(
    center: np.ndarray, halfsize: float, spacing: float, root_offset: int, root_size: int
) -> bytes:
    data = struct.pack("<3dddQQdd", *center, halfsize, spacing, root_offset, root_size, 0.0, 0.0)
    return data + bytes(COPC_INFO_SIZE - len(data))


def _evlr_header(user_id: str, record_id: int, length: int, description: str) -> bytes:
    return struct.pack(
        "<H16sHQ32s", 0, user_id.encode("ascii"), record_id, length, description.encode("ascii")
    )


def write_copc_nodes(
    out: str | os.PathLike[str],
    nodes: Iterable[CopcNode],
    *,
    layout: LasLayout,
    scale: float,
    offset: np.ndarray,
    cube_min: np.ndarray,
    cube_size: float,
    spacing: float,
    points: int,
    units: str = "mm",
) -> dict:
    """Write a COPC file from octree nodes given parent before child (breadth-first order).

    ``cube_min`` (3,) and ``cube_size`` are the root cube (world units); ``spacing`` the root
    node's point spacing; ``points`` the total the nodes hold (checked). Nodes with no points
    are left out of the hierarchy unless they have children (then they appear with 0 points).
    Written atomically; returns points, nodes, bytes and the bounds (min, max).
    """
    out = Path(out)
    header = las_header(layout, scale, offset, units)
    center = np.asarray(cube_min, np.float64) + cube_size / 2
    header.vlrs.insert(0, laspy.VLR("copc", 1, "copc info", _copc_info(center, cube_size / 2, spacing, 0, 0)))
    vlr = lazrs.LazVlr.new_for_compression(header.point_format.id, header.point_format.num_extra_bytes, True)
    header.vlrs.append(LasZipVlr(vlr.record_data()))
    header.are_points_compressed = True
    header.point_count = points
    entries: list[tuple[tuple[int, int, int, int], int]] = []  # key, points (chunk order)
    lo_i = np.full(3, np.iinfo(np.int64).max)
    hi_i = np.full(3, np.iinfo(np.int64).min)
    with atomic_file(out, suffix=".laz") as tmp, open(tmp, "w+b") as f:
        header.write_to(f)
        start = f.tell()
        comp = lazrs.ParLasZipCompressor(f, vlr)
        batch: list[bytes] = []
        held = 0
        total = 0
        for node in nodes:
            n = int(node.ixyz.shape[0])
            if n == 0:
                entries.append((node.key, 0))
                continue
            rec = _record(n, header)
            rec.array["X"], rec.array["Y"], rec.array["Z"] = node.ixyz[:, 0], node.ixyz[:, 1], node.ixyz[:, 2]
            if layout.has_colour and node.rgb is not None:
                rec.array["red"], rec.array["green"], rec.array["blue"] = (
                    node.rgb[:, 0],
                    node.rgb[:, 1],
                    node.rgb[:, 2],
                )
            for name, values in node.extra.items():
                rec.array[name] = values
            lo_i = np.minimum(lo_i, node.ixyz.min(axis=0))
            hi_i = np.maximum(hi_i, node.ixyz.max(axis=0))
            batch.append(rec.array.tobytes())
            entries.append((node.key, n))
            held += n
            total += n
            if held >= COPC_BATCH:
                comp.compress_chunks(batch)
                batch, held = [], 0
        if batch:
            comp.compress_chunks(batch)
        comp.done()
        if total != points:
            raise RuntimeError(f"the octree nodes hold {total} points, expected {points}")
        end = f.seek(0, io.SEEK_END)
        f.seek(start)
        table = lazrs.read_chunk_table(f, vlr)
        if len(table) != sum(1 for _k, n in entries if n) or any(
            c != n for (c, _b), n in zip(table, (n for _k, n in entries if n), strict=False)
        ):
            raise RuntimeError("the LAZ chunk table does not match the octree nodes")
        # Hierarchy page: one entry a node, chunks follow each other from start + 8.
        pos = start + 8
        page = bytearray()
        sizes = iter(table)
        parents = {(lv - 1, x >> 1, y >> 1, z >> 1) for (lv, x, y, z), _n in entries if lv > 0}
        for key, n in entries:
            if n:
                _c, nbytes = next(sizes)
                page += COPC_ENTRY.pack(*key, pos, nbytes, n)
                pos += nbytes
            elif key in parents:  # an empty node on the way to its children
                page += COPC_ENTRY.pack(*key, pos, 0, 0)
        f.seek(end)
        evlr_start = end
        f.write(_evlr_header("copc", 1000, len(page), "EPT hierarchy"))
        root_offset = f.tell()
        f.write(page)
        nbytes = f.tell()
        # Final header: bounds of the stored integers, the EVLR and the hierarchy's place.
        header.mins = lo_i * header.scales + header.offsets
        header.maxs = hi_i * header.scales + header.offsets
        header.start_of_first_evlr = evlr_start
        header.number_of_evlrs = 1
        header.vlrs[0] = laspy.VLR(
            "copc", 1, "copc info", _copc_info(center, cube_size / 2, spacing, root_offset, len(page))
        )
        f.seek(0)
        header.write_to(f, ensure_same_size=True)
    return {
        "points": points, "nodes": len(page) // COPC_ENTRY.size, "bytes": nbytes,
        "min": header.mins.tolist(), "max": header.maxs.tolist(), "scale": scale,
    }  # fmt: skip


def iter_potree_nodes(tiles, layout: LasLayout) -> Iterator[CopcNode]:
    """COPC nodes of opened Potree tiles (:class:`shared.formats.potree.PotreeTiles`), breadth first."""
    names = tiles.point_dtype.names or ()
    for name in tiles.nodes:
        rec = tiles.records(name)
        extra = {}
        for las, src, _t in layout.extra:
            extra[las] = rec[las if las in names else src]
        yield CopcNode(
            key=potree_key(name),
            ixyz=rec["position"],
            rgb=rec["rgb"] if "rgb" in names else None,
            extra=extra,
        )


def potree_layout(tiles) -> LasLayout:
    """The LAS layout of what Potree tiles carry (colour, NormalX/Y/Z, size)."""
    names = tiles.point_dtype.names or ()
    extra = []
    for name in names:
        if name in ("position", "rgb"):
            continue
        t = tiles.point_dtype[name]
        if t.shape:
            raise InputError(
                tiles.root / "metadata.json",
                f"attribute {name!r} has {t.shape} elements; COPC export needs scalars",
            )
        extra.append((name, name, t.str[1:]))
    return LasLayout(point_format=7 if "rgb" in names else 6, extra=tuple(extra))


def write_copc(
    tiles,
    out: str | os.PathLike[str],
    *,
    units: str = "mm",
    extras: tuple[tuple[str, str, str], ...] = (),
    lookup: Callable[[np.ndarray], dict[str, np.ndarray]] | None = None,
) -> dict:
    """Write opened Potree 2.0 tiles (``shared.formats.potree.PotreeTiles``) as one COPC file.

    The LAS scale and offset are the tiles' own (build the tiles with the scale wanted, e.g.
    :func:`coordinate_scale`); the root cube is the tiles' cubic bounding box. ``extras``
    (LAS name, source name, dtype) are dimensions the tiles do not carry; ``lookup(ixyz)``
    returns them, by LAS name, for a node's (N, 3) int32 positions.
    """
    base = potree_layout(tiles)
    layout = LasLayout(point_format=base.point_format, extra=base.extra + tuple(extras))
    scales = np.asarray(tiles.scale, np.float64)
    if not np.allclose(scales, scales[0], rtol=0, atol=0):
        raise InputError(tiles.root / "metadata.json", "COPC needs one scale for the three axes")

    def nodes() -> Iterator[CopcNode]:
        for node in iter_potree_nodes(tiles, base):
            if extras and lookup is not None and len(node.ixyz):
                node = CopcNode(node.key, node.ixyz, node.rgb, {**node.extra, **lookup(node.ixyz)})
            elif extras:
                node = CopcNode(node.key, node.ixyz, node.rgb,
                                {**node.extra, **{e[0]: np.empty(0, e[2]) for e in extras}})  # fmt: skip
            yield node

    return write_copc_nodes(
        out, nodes(), layout=layout, scale=float(scales[0]), offset=tiles.offset,
        cube_min=tiles.box_min, cube_size=float(tiles.box_max[0] - tiles.box_min[0]),
        spacing=float(tiles.metadata["spacing"]), points=tiles.points, units=units,
    )  # fmt: skip
