"""E57 (ASTM E2807) point clouds: what survey scanners' software (Leica Cyclone, FARO Scene,
Trimble RealWorks, CloudCompare) exchanges.

:func:`write_e57` writes one ``data3D`` scan through libE57 (the ``pye57`` build of it),
streamed in chunks: ``cartesianX/Y/Z`` as single-precision floats (the PLY's own float32
values, so nothing is rounded) in the rig's frame and units (the scan's ``description`` names
the units), ``colorRed/Green/Blue`` 0..255 when the cloud has colour, and the unit normal as
``nor:normalX/Y/Z`` of libE57's surface-normals extension
(``http://www.libe57.org/E57_NOR_surface_normals.txt``, which CloudCompare reads). The scan's
pose is the identity: coordinates are already in the file's frame. Other properties (the
sample ``size``) have no E57 field and are left out; LAS/LAZ carries them.

:func:`read_e57` reads such a file back (any E57 scan with cartesian coordinates, colour and
normals when present), for round-trip tests and imports.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np
from pye57 import E57, libe57

from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.formats.las import cloud_bounds
from shared.formats.ply import CHUNK, PointCloud, iter_ply_records, read_header

NORMALS_PREFIX = "nor"
NORMALS_URI = "http://www.libe57.org/E57_NOR_surface_normals.txt"
_NORMALS = ("nor:normalX", "nor:normalY", "nor:normalZ")
_XYZ = ("cartesianX", "cartesianY", "cartesianZ")
_RGB = ("colorRed", "colorGreen", "colorBlue")


def write_e57(
    cloud_ply: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    units: str = "mm",
    name: str | None = None,
    chunk: int = CHUNK,
) -> dict:
    """Write a PLY cloud as an E57 file with one scan (layout in the module docstring).

    Streams ``chunk`` points at a time; written atomically. Returns points, fields, min, max.
    """
    cloud_ply, out = Path(cloud_ply), Path(out)
    names = set(read_header(cloud_ply).dtype.names or ())
    has_rgb = {"red", "green", "blue"} <= names
    has_normal = {"nx", "ny", "nz"} <= names
    n, lo, hi = cloud_bounds(cloud_ply, chunk)
    fields = list(_XYZ) + (list(_RGB) if has_rgb else []) + (list(_NORMALS) if has_normal else [])
    with atomic_file(out, suffix=".e57") as tmp:
        tmp.unlink()  # libE57 creates the file itself
        e57 = E57(str(tmp), mode="w")
        try:
            imf = e57.image_file
            if has_normal:
                imf.extensionsAdd(NORMALS_PREFIX, NORMALS_URI)
            scan = libe57.StructureNode(imf)
            scan.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
            scan.set("name", libe57.StringNode(imf, name or cloud_ply.stem))
            scan.set("description", libe57.StringNode(imf, f"graylight export; units {units}; camera frame"))
            bbox = libe57.StructureNode(imf)
            for k, axis in enumerate("xyz"):
                bbox.set(f"{axis}Minimum", libe57.FloatNode(imf, float(lo[k])))
                bbox.set(f"{axis}Maximum", libe57.FloatNode(imf, float(hi[k])))
            scan.set("cartesianBounds", bbox)
            pose = libe57.StructureNode(imf)
            rot = libe57.StructureNode(imf)
            for key, v in (("w", 1.0), ("x", 0.0), ("y", 0.0), ("z", 0.0)):
                rot.set(key, libe57.FloatNode(imf, v))
            trans = libe57.StructureNode(imf)
            for key in "xyz":
                trans.set(key, libe57.FloatNode(imf, 0.0))
            pose.set("rotation", rot)
            pose.set("translation", trans)
            scan.set("pose", pose)
            proto = libe57.StructureNode(imf)
            for k, f in enumerate(_XYZ):
                proto.set(
                    f, libe57.FloatNode(imf, float(lo[k]), libe57.E57_SINGLE, float(lo[k]), float(hi[k]))
                )
            if has_rgb:
                limits = libe57.StructureNode(imf)
                for f in _RGB:
                    proto.set(f, libe57.IntegerNode(imf, 0, 0, 255))
                    limits.set(f"{f}Minimum", libe57.IntegerNode(imf, 0))
                    limits.set(f"{f}Maximum", libe57.IntegerNode(imf, 255))
                scan.set("colorLimits", limits)
            if has_normal:
                for f in _NORMALS:
                    proto.set(f, libe57.FloatNode(imf, 0.0, libe57.E57_SINGLE, -1.0, 1.0))
            points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
            scan.set("points", points)
            e57.data3d.append(scan)
            cap = min(chunk, n)
            arrays = {f: np.empty(cap, np.float32) for f in _XYZ + (_NORMALS if has_normal else ())}
            arrays.update({f: np.empty(cap, np.uint8) for f in (_RGB if has_rgb else ())})
            buffers = libe57.VectorSourceDestBuffer()
            for f in fields:
                buffers.append(libe57.SourceDestBuffer(imf, f, arrays[f], cap, True, False))
            writer = points.writer(buffers)
            src = {"cartesianX": "x", "cartesianY": "y", "cartesianZ": "z", "colorRed": "red",
                   "colorGreen": "green", "colorBlue": "blue", "nor:normalX": "nx", "nor:normalY": "ny",
                   "nor:normalZ": "nz"}  # fmt: skip
            for rec in iter_ply_records(cloud_ply, cap):
                m = len(rec)
                for f in fields:
                    v = rec[src[f]]
                    if f in _NORMALS:
                        v = np.clip(v, -1.0, 1.0)  # the prototype's declared range
                    arrays[f][:m] = v
                writer.write(m)
            writer.close()
        finally:
            e57.close()
    return {"points": n, "fields": fields, "min": lo.tolist(), "max": hi.tolist()}


def read_e57(path: str | os.PathLike[str], scan: int = 0) -> PointCloud:
    """Read scan ``scan`` of an E57 file: positions (float32, the scan's own frame), colour and
    normals when the scan has them. Raises :class:`InputError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "E57 file not found")
    try:
        e57 = E57(str(path), mode="r")
    except Exception as exc:  # libE57 raises its own exception types for any malformed file
        raise InputError(path, f"not a readable E57 file ({exc})") from None
    try:
        if scan >= e57.scan_count:
            raise InputError(path, f"has {e57.scan_count} scans, no scan {scan}")
        header = e57.get_header(scan)
        points = header.points
        have = set(header.point_fields)
        if not set(_XYZ) <= have:
            raise InputError(path, f"scan {scan} has no cartesian coordinates")
        n = points.childCount()
        fields = (
            list(_XYZ)
            + [f for f in _RGB if set(_RGB) <= have]
            + [f for f in _NORMALS if set(_NORMALS) <= have]
        )
        arrays = {f: np.empty(n, np.uint8 if f in _RGB else np.float64) for f in fields}
        buffers = libe57.VectorSourceDestBuffer()
        for f in fields:
            buffers.append(libe57.SourceDestBuffer(e57.image_file, f, arrays[f], n, True, True))
        reader = points.reader(buffers)
        got = reader.read()
        reader.close()
        if got != n:
            raise InputError(path, f"scan {scan} holds {got} points, its header says {n}")
    finally:
        e57.close()
    xyz = np.stack([arrays[f] for f in _XYZ], axis=1).astype(np.float32)
    rgb = np.stack([arrays[f] for f in _RGB], axis=1) if _RGB[0] in arrays else None
    normals = (
        np.stack([arrays[f] for f in _NORMALS], axis=1).astype(np.float32) if _NORMALS[0] in arrays else None
    )
    return PointCloud(xyz=xyz, rgb=rgb, normals=normals)
