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


def seam_figures(m, S: int, maps_list: list, scene: str = "bunny", views: int = 8) -> list[dict]:
    """Seams of photograph bakes of one level against the simulated scene's truth.

    ``maps_list``: :class:`shared.derive.bake.Maps` of the same level ``m`` at ``S`` px (the first
    one's ``view`` map names each texel's main view, and with it the borders every bake is measured
    on). Per bake: ``mae`` the mean absolute error of linear albedo per texel on the object (up to
    the one scale no scan knows); over pairs of neighbouring texels of one chart on the object whose
    main views differ (a border between patches of different views), ``jump`` the mean absolute
    colour difference across it (linear, per channel), ``jump_truth`` the truth's own, and
    ``jump_error`` the mean absolute difference of the two texels' errors (the step a seam adds);
    ``jump_error_inside`` the same over neighbouring pairs with one main view,
    ``jump_error_view_set`` over pairs where a view enters or leaves the blend; the pair counts."""
    from shared.scan.albedo import linear_from_srgb

    cov, P, on, truth = texel_truth(m, S, scene, views)
    luma = np.array([0.2126, 0.7152, 0.0722])
    where = np.full((S, S), -1, np.int64)
    obj = np.zeros((S, S), bool)
    ys, xs = np.nonzero(cov)
    obj[ys[on], xs[on]] = True
    where[ys[on], xs[on]] = np.arange(int(on.sum()))
    pts = P[on]
    view, used = maps_list[0].view, maps_list[0].view_set
    pairs = []
    for dy, dx in ((0, 1), (1, 0)):
        a = obj[: S - dy, : S - dx] & obj[dy:, dx:]
        ia, ib = where[: S - dy, : S - dx][a], where[dy:, dx:][a]
        pairs.append((ia, ib, view[: S - dy, : S - dx][a], view[dy:, dx:][a], used[: S - dy, : S - dx][a],
                      used[dy:, dx:][a]))
    ia, ib, va, vb, ua, ub = (np.concatenate(c) for c in zip(*pairs, strict=True))
    step = np.linalg.norm(pts[ia] - pts[ib], axis=1)
    same_chart = step < 3.0 * np.median(step)  # neighbours in the atlas and on the surface
    border = same_chart & (va >= 0) & (vb >= 0) & (va != vb)
    inside = same_chart & (va >= 0) & (va == vb)
    enter = same_chart & (va >= 0) & (vb >= 0) & (ua != ub)
    out = []
    for maps in maps_list:
        est = linear_from_srgb(maps.base_colour[cov] / 255.0).astype(np.float64)[on]
        est *= np.median(truth @ luma) / np.median(est @ luma)
        err = est - truth
        out.append({
            "mae": float(np.abs(err).mean()),
            "jump": float(np.abs(est[ia[border]] - est[ib[border]]).mean()),
            "jump_truth": float(np.abs(truth[ia[border]] - truth[ib[border]]).mean()),
            "jump_error": float(np.abs(err[ia[border]] - err[ib[border]]).mean()),
            "jump_error_inside": float(np.abs(err[ia[inside]] - err[ib[inside]]).mean()),
            "jump_error_view_set": float(np.abs(err[ia[enter]] - err[ib[enter]]).mean()),
            "border_pairs": int(border.sum()),
            "view_set_pairs": int(enter.sum()),
        })
    return out
