"""A textured derivative as binary glTF 2.0 with Draco-compressed geometry.

One mesh, one primitive: POSITION (mm), NORMAL and TEXCOORD_0 in a ``KHR_draco_mesh_compression``
buffer (DracoPy, Google's encoder; positions quantised to ``position_bits`` over the bounding
cube, texture coordinates to 14 bits, normals to 10), one PBR material (base colour, normal and
occlusion textures as JPEG, metallic 0, roughness 1: a scan measures diffuse colour, not gloss).
The accessors describe the decoded geometry (DracoPy decodes the buffer to count it: the encoder
splits vertices along attribute seams). ``asset.extras`` carries ``units`` ("mm": glTF's own unit
is the metre; renderers that care scale by 0.001), the ``level`` and figures of the bake.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from shared.core.files import atomic_file

__all__ = ["encode_jpeg", "write_textured_glb"]

_DRACO = "KHR_draco_mesh_compression"
_FLOAT, _UINT32 = 5126, 5125
_ATTRIBUTE_TYPES = {0: "POSITION", 1: "NORMAL", 3: "TEXCOORD_0"}  # draco::GeometryAttribute::Type


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    """(H, W, 3) uint8 RGB -> baseline JPEG bytes (4:2:0; normal maps too: they are smooth)."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_OPTIMIZE, 1])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def _pad4(b: bytes, fill: bytes = b"\x00") -> bytes:
    return b + fill * (-len(b) % 4)


def write_textured_glb(path: str | os.PathLike[str], vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                       normals: np.ndarray, textures: dict[str, bytes], extras: dict[str, Any],
                       position_bits: int = 16) -> dict[str, Any]:
    """Write the GLB atomically; returns its figures (bytes, vertices and faces after decoding).

    vertices (V, 3) mm, faces (F, 3), uv (V, 2) glTF convention, normals (V, 3);
    textures: JPEG bytes by role (``base_colour``, ``normal``, ``occlusion``).
    """
    import DracoPy

    draco = DracoPy.encode(np.asarray(vertices, np.float64), np.asarray(faces, np.uint32),
                           quantization_bits=position_bits, compression_level=7,
                           tex_coord=np.asarray(uv, np.float64), normals=np.asarray(normals, np.float64),
                           tex_coord_quantization_bits=14, normal_quantization_bits=10)
    decoded = DracoPy.decode(draco)
    ids = {_ATTRIBUTE_TYPES[a["attribute_type"]]: int(a["unique_id"]) for a in decoded.attributes
           if a["attribute_type"] in _ATTRIBUTE_TYPES}
    pts = np.asarray(decoded.points, np.float64)
    n_points, n_faces = len(pts), len(decoded.faces)

    blobs: list[bytes] = []
    views: list[dict[str, Any]] = []

    def add_view(data: bytes) -> int:
        offset = sum(len(b) for b in blobs)
        blobs.append(_pad4(data))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data)})
        return len(views) - 1

    draco_view = add_view(draco)
    accessors = [
        {"componentType": _FLOAT, "count": n_points, "type": "VEC3",
         "min": pts.min(axis=0).tolist(), "max": pts.max(axis=0).tolist()},
        {"componentType": _FLOAT, "count": n_points, "type": "VEC3"},
        {"componentType": _FLOAT, "count": n_points, "type": "VEC2"},
        {"componentType": _UINT32, "count": 3 * n_faces, "type": "SCALAR"},
    ]
    images, tex_index = [], {}
    for role in ("base_colour", "normal", "occlusion"):
        if role in textures:
            images.append({"bufferView": add_view(textures[role]), "mimeType": "image/jpeg", "name": role})
            tex_index[role] = len(images) - 1
    material: dict[str, Any] = {"name": "scan", "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 1.0}}
    if "base_colour" in tex_index:
        material["pbrMetallicRoughness"]["baseColorTexture"] = {"index": tex_index["base_colour"]}
    if "normal" in tex_index:
        material["normalTexture"] = {"index": tex_index["normal"]}
    if "occlusion" in tex_index:
        material["occlusionTexture"] = {"index": tex_index["occlusion"]}
    binary = b"".join(blobs)
    doc = {
        "asset": {"version": "2.0", "generator": "graylight derivatives", "extras": extras},
        "extensionsUsed": [_DRACO],
        "extensionsRequired": [_DRACO],
        "scene": 0,
        "scenes": [{"nodes": [0], "extras": {"units": extras.get("units", "mm")}}],
        "nodes": [{"mesh": 0, "name": "scan"}],
        "meshes": [{"name": "scan", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3, "material": 0, "mode": 4,
            "extensions": {_DRACO: {"bufferView": draco_view, "attributes": {
                "POSITION": ids["POSITION"], "NORMAL": ids["NORMAL"], "TEXCOORD_0": ids["TEXCOORD_0"]}}}}]}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(binary)}],
        "materials": [material],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "textures": [{"source": i, "sampler": 0} for i in range(len(images))],
        "images": images,
    }
    js = _pad4(json.dumps(doc, separators=(",", ":")).encode(), b" ")
    total = 12 + 8 + len(js) + 8 + len(binary)
    out = Path(path)
    with atomic_file(out, suffix=".tmp.glb") as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<4sII", b"glTF", 2, total))
        f.write(struct.pack("<I4s", len(js), b"JSON"))
        f.write(js)
        f.write(struct.pack("<I4s", len(binary), b"BIN\x00"))
        f.write(binary)
    return {"bytes": total, "vertices": n_points, "faces": n_faces,
            "geometry_bytes": len(draco), "texture_bytes": {k: len(v) for k, v in textures.items()}}
