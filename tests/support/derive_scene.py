"""A small merged model with a known colour, for the derivative tests: a bumpy sphere's master
mesh (``mesh.ply``) and a dense fused cloud on its surface (``merged.ply``) whose albedo is a
known pattern and whose shaded colour is that pattern darkened by a fake lamp."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.formats.ply import write_ply
from shared.scan.albedo import encode_srgb, linear_from_srgb

RADIUS = 40.0


def pattern(xyz: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 sRGB albedo at surface points: bands of hue around the z axis, stripes along z."""
    ang = np.arctan2(xyz[:, 1], xyz[:, 0])
    lin = np.stack([0.45 + 0.35 * np.cos(3 * ang), 0.45 + 0.35 * np.sin(3 * ang),
                    0.3 + 0.25 * (np.sin(xyz[:, 2] / 4.0) > 0)], axis=1)
    return encode_srgb(lin)


def write_scene(folder: Path, faces_subdiv: int = 5, points: int = 300_000, albedo: bool = True) -> Path:
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    sphere = trimesh.creation.icosphere(subdivisions=faces_subdiv, radius=RADIUS)
    v = np.asarray(sphere.vertices, np.float64)
    v *= (1 + 0.04 * np.sin(v[:, :1] / 5.0) * np.sin(v[:, 1:2] / 5.0))  # bumps for the normal map
    mesh = trimesh.Trimesh(v, sphere.faces, process=False)
    mesh.visual.vertex_colors = np.column_stack([pattern(v), np.full(len(v), 255, np.uint8)])
    mesh.export(folder / "mesh.ply")
    pts, fid = trimesh.sample.sample_surface(mesh, points, seed=1)
    pts = np.asarray(pts, np.float64)
    normals = np.asarray(mesh.face_normals[fid], np.float32)
    alb = pattern(pts)
    lamp = np.clip(0.25 + 0.75 * np.clip(pts[:, 0] / RADIUS, 0, 1), 0, 1)  # lit from +x
    shaded = encode_srgb(linear_from_srgb(alb / 255.0) * lamp[:, None])
    size = np.full(len(pts), np.sqrt(4 * np.pi * RADIUS**2 / len(pts)), np.float32)
    kw = {"albedo": alb, "albedo_weight": np.full(len(pts), 200, np.uint8)} if albedo else {}
    write_ply(folder / "merged.ply", pts.astype(np.float32), rgb=shaded, normals=normals, size=size, **kw)
    return folder


def texel_truth(m, S: int, scene: str = "bunny", views: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The covered texels of a level's atlas (``m``: a :class:`shared.derive.bake.UVMesh`) at ``S``
    px against a simulated turntable scene's object: (cov (S, S) bool, P (n, 3) texel surface
    points in view 0's frame, on (n,) bool texels on the object (not the plate), truth (k, 3)
    float64 linear albedo of the texels on the object)."""
    from scipy.spatial import cKDTree

    from shared.derive._raster import rasterise_uv
    from shared.sim.scanset import turntable_scenes

    fid = np.full((S, S), -1, np.int32)
    bary = np.zeros((S, S, 3), np.float32)
    rasterise_uv(m.uv, m.faces, S, fid, bary)
    cov = fid >= 0
    P = np.einsum("nk,nkj->nj", bary[cov], m.vertices[m.faces[fid[cov]]])
    obj = turntable_scenes(scene, views)[0][0].surfaces[0]  # view 0's frame is the set's
    on = cKDTree(obj.placed.vertices).query(P)[0] < 3.0
    return cov, P, on, obj.albedo_at(P).astype(np.float64)[on]
