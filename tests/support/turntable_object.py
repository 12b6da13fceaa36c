"""A textured turntable object for the preview and viewer tests: a cylinder standing on a tilted
turntable axis in a merge's frame (view 0's camera, y down), its top half (away from the table)
one colour and its bottom half another, as a derivative GLB (colour by texture alone, Draco, by
shared.derive's writer) and as a merged cloud (points with normals and sample-spacing sizes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.derive.gltf import encode_jpeg, write_textured_glb
from shared.formats.ply import write_ply

#: The turntable axis as registration.json gives it: down the image and a little away from the
#: camera, the 12-view bunny's (19 degrees of tilt).
AXIS = np.array([0.0, 0.9445, 0.3284]) / np.linalg.norm([0.0, 0.9445, 0.3284])
RADIUS, HEIGHT = 30.0, 90.0


def _frame() -> np.ndarray:
    """(3, 3) columns: two radial directions and "up" (-AXIS)."""
    up = -AXIS
    x = np.cross(up, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(up, x), up])


def write_cylinder_glb(path: Path, centre: np.ndarray, top: tuple[int, int, int], bottom: tuple[int, int, int],
                       texture_px: int = 64) -> int:
    """The cylinder as a textured derivative GLB; returns its face count."""
    import trimesh

    cyl = trimesh.creation.cylinder(radius=RADIUS, height=HEIGHT, sections=64).subdivide().subdivide()
    v = np.asarray(cyl.vertices, np.float64)
    h = v[:, 2] / HEIGHT + 0.5  # 0 at the bottom, 1 at the top
    uv = np.column_stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, 1.0 - h])
    rot = _frame()
    tex = np.zeros((texture_px, texture_px, 3), np.uint8)
    tex[: texture_px // 2] = top  # v < 0.5, the top half: glTF's v runs down the image
    tex[texture_px // 2 :] = bottom
    flat = np.full((texture_px, texture_px, 3), (128, 128, 255), np.uint8)
    write_textured_glb(path, v @ rot.T + centre, np.asarray(cyl.faces), uv, np.asarray(cyl.vertex_normals) @ rot.T,
                       {"base_colour": encode_jpeg(tex, 95), "normal": encode_jpeg(flat, 95),
                        "occlusion": encode_jpeg(np.full_like(tex, 255), 95)}, {"units": "mm"})  # fmt: skip
    return len(cyl.faces)


def write_cylinder_cloud(path: Path, centre: np.ndarray, top: tuple[int, int, int], bottom: tuple[int, int, int],
                         n: int = 120_000) -> None:
    """The cylinder's side as a merged cloud PLY (sizes: the sample spacing, as a merge writes them)."""
    rng = np.random.default_rng(3)
    ang = rng.uniform(0, 2 * np.pi, n)
    h = rng.uniform(-HEIGHT / 2, HEIGHT / 2, n)
    rot = _frame()
    radial = np.cos(ang)[:, None] * rot[:, 0] + np.sin(ang)[:, None] * rot[:, 1]
    xyz = centre + RADIUS * radial + h[:, None] * rot[:, 2]
    colour = np.where((h > 0)[:, None], [top], [bottom]).astype(np.uint8)
    write_ply(path, xyz.astype(np.float32), colour, radial.astype(np.float32), np.full(n, 0.9, np.float32))
