"""GLB files as a scene lists them: faces, points, the largest texture, vertex positions; and a cloud
written as a GLB of points (a scan without a mesh).

The figures come from the GLB's own JSON chunk (glTF 2.0: a primitive's ``mode``, its indices'
``count``, ``POSITION``'s ``min``/``max``), and the texture sizes from the image headers in the
binary chunk, so a 100 MB derivative is measured without decoding its geometry.
"""

from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.core.errors import InputError
from shared.core.files import atomic_file

__all__ = ["GlbInfo", "glb_positions", "inspect_glb", "write_points_glb"]

_MAGIC = 0x46546C67  # "glTF"
_JSON, _BIN = 0x4E4F534A, 0x004E4942
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}


@dataclass(frozen=True)
class GlbInfo:
    """What a GLB holds: ``faces`` (triangles), ``points`` (point primitives), ``vertices``, the largest
    texture side in px (0 without textures), the bounding box of every position (file units)."""

    path: Path
    byte_size: int
    faces: int
    points: int
    vertices: int
    image_size: int
    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]


def _chunks(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    if len(data) < 20:
        raise InputError(path, "not a GLB (too short)")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _MAGIC or version != 2 or length != len(data):
        raise InputError(path, "not a glTF 2.0 binary (bad header)")
    doc, binary, off = None, b"", 12
    while off + 8 <= len(data):
        size, kind = struct.unpack_from("<II", data, off)
        body = data[off + 8: off + 8 + size]
        if kind == _JSON:
            try:
                doc = json.loads(body)
            except (UnicodeDecodeError, json.JSONDecodeError):
                raise InputError(path, "GLB JSON chunk is malformed") from None
        elif kind == _BIN:
            binary = body
        off += 8 + size
    if not isinstance(doc, dict):
        raise InputError(path, "GLB has no JSON chunk")
    return doc, binary


def _image_side(doc: dict, binary: bytes) -> int:
    from PIL import Image

    side = 0
    for img in doc.get("images", []):
        view = doc.get("bufferViews", [])[img["bufferView"]] if "bufferView" in img else None
        if view is None:
            continue
        start = view.get("byteOffset", 0)
        try:
            with Image.open(io.BytesIO(binary[start:start + view["byteLength"]])) as im:
                side = max(side, *im.size)
        except OSError:
            continue
    return side


def inspect_glb(path: Path) -> GlbInfo:
    """Measure a GLB (see :class:`GlbInfo`); :class:`InputError` naming it when it is not one."""
    path = Path(path)
    doc, binary = _chunks(path)
    acc = doc.get("accessors", [])
    faces = points = vertices = 0
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            pos = acc[prim["attributes"]["POSITION"]]
            n = int(pos["count"])
            vertices += n
            if "min" in pos and "max" in pos:
                lo, hi = np.minimum(lo, pos["min"]), np.maximum(hi, pos["max"])
            mode = prim.get("mode", 4)
            count = int(acc[prim["indices"]]["count"]) if "indices" in prim else n
            if mode == 4:
                faces += count // 3
            elif mode in (5, 6):  # strips and fans
                faces += max(count - 2, 0)
            elif mode == 0:
                points += count
    if not np.isfinite(lo).all():
        lo = hi = np.zeros(3)
    return GlbInfo(path, path.stat().st_size, faces, points, vertices, _image_side(doc, binary),
                   tuple(float(v) for v in lo), tuple(float(v) for v in hi))


def _draco_positions(path: Path, binary: bytes, view: dict) -> np.ndarray:
    import DracoPy

    start = view.get("byteOffset", 0)
    try:
        mesh = DracoPy.decode(binary[start:start + view["byteLength"]])
    except Exception as exc:  # DracoPy raises its own failure types for a corrupt stream
        raise InputError(path, f"its Draco geometry cannot be decoded ({type(exc).__name__})") from None
    return np.asarray(mesh.points, np.float64).reshape(-1, 3)


def glb_positions(path: Path) -> np.ndarray:
    """Every vertex position of a GLB's meshes, (N, 3) float64, in the file's units (node transforms
    are not applied: Graylight's GLBs have none); Draco-compressed primitives are decoded."""
    doc, binary = _chunks(Path(path))
    acc, views = doc.get("accessors", []), doc.get("bufferViews", [])
    out = []
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            draco = prim.get("extensions", {}).get("KHR_draco_mesh_compression")
            if draco is not None:  # the derivatives' geometry (shared.derive.gltf) is Draco-compressed
                out.append(_draco_positions(path, binary, views[draco["bufferView"]]))
                continue
            a = acc[prim["attributes"]["POSITION"]]
            v = views[a["bufferView"]]
            dtype = np.dtype(_DTYPES[a["componentType"]])
            width = _COMPONENTS[a["type"]]
            stride = v.get("byteStride") or dtype.itemsize * width
            start = v.get("byteOffset", 0) + a.get("byteOffset", 0)
            raw = np.frombuffer(binary, np.uint8, count=stride * (a["count"] - 1) + dtype.itemsize * width,
                                offset=start)
            rows = np.lib.stride_tricks.as_strided(raw, shape=(a["count"], dtype.itemsize * width),
                                                   strides=(stride, 1))
            out.append(np.ascontiguousarray(rows).view(dtype).reshape(-1, width)[:, :3].astype(np.float64))
    return np.concatenate(out) if out else np.zeros((0, 3))


def write_points_glb(path: Path, xyz: np.ndarray, rgb: np.ndarray | None) -> Path:
    """Write points as a GLB of one ``POINTS`` primitive (positions float32 in the input's units, colours
    as ``COLOR_0`` when given), atomically. ``xyz`` (N, 3); ``rgb`` (N, 3) uint8 or None."""
    import trimesh

    colors = None if rgb is None else np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)
    cloud = trimesh.PointCloud(np.asarray(xyz, np.float64), colors=colors)
    with atomic_file(path, suffix=".glb") as tmp:
        tmp.write_bytes(trimesh.Scene(cloud).export(file_type="glb"))
    return path
