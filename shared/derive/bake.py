"""Unwrapping and texture baking of one derivative level.

- :func:`unwrap`: a UV atlas with ``xatlas`` (charts packed at the level's texture size with a
  few texels of padding); the mesh's vertices split along the seams.
- :func:`bake_maps`: every covered texel gets the surface point and normal it shows (its face and
  barycentric coordinates, :mod:`shared.derive._raster`), then

  * **base colour** from the fused cloud: a Gaussian-weighted mean of the nearest samples (in
    linear light, with the samples' own size as the kernel's width, and only samples whose normal
    agrees with the texel's: the two sides of a thin part do not bleed into each other). The
    colour is the albedo (:mod:`shared.scan.albedo`) where the cloud has it and ``colour="albedo"``,
    else the shaded white-frame colour. A texel whose nearest sample is farther than
    ``bridge_factor`` sample sizes shows a surface the mesh bridged without data: it is marked
    in the **bridged mask** (255) and coloured from the nearest samples all the same;
  * a **tangent-space normal map** from the master mesh's normals (nearest master vertices,
    inverse-distance weighted), in the level's tangent frame (tangent along +u, bitangent along
    the image's up, glTF's convention; clients compute MikkTSpace tangents, which agree with these
    per face for the atlases xatlas makes);
  * **ambient occlusion**: per vertex of the level, the share of ``ao_rays`` cosine-weighted rays
    that leave without hitting the level mesh within ``ao_reach`` of the object's size (Open3D's
    ray casting), interpolated over the faces.

  Texels outside every chart take the value of the nearest covered texel (so mip-mapping and
  bilinear filtering never pull in black from the gutters).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.core.threads import cpu_budget
from shared.derive._raster import rasterise_uv
from shared.derive.photo import PhotoSource
from shared.scan.albedo import encode_srgb, linear_from_srgb

log = logging.getLogger(__name__)

_LUMA = np.array([0.2126, 0.7152, 0.0722])

__all__ = ["BakeParams", "ColourSource", "Maps", "UVMesh", "bake_maps", "unwrap", "vertex_normals"]


@dataclass
class UVMesh:
    """A level's mesh with its atlas: vertices (V, 3) float64 mm, faces (F, 3) int32, uv (V, 2)
    float32 in [0, 1] (glTF: v down the image), normals (V, 3) float32 unit."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    normals: np.ndarray


@dataclass
class ColourSource:
    """The samples colours are baked from: xyz (N, 3) float mm, rgb (N, 3) uint8 sRGB-encoded,
    normals (N, 3) float32, size (N,) float32 mm, and ``kind`` (albedo, shaded or mixed)."""

    xyz: np.ndarray
    rgb: np.ndarray
    normals: np.ndarray
    size: np.ndarray
    kind: str


@dataclass(frozen=True)
class BakeParams:
    """neighbours : samples averaged per texel. bridge_factor : sample sizes beyond which a texel
    counts as bridged. ao_rays : rays per vertex for the occlusion. ao_reach : ray length as a
    share of the object's bounding-box diagonal. padding_px : texels between charts."""

    neighbours: int = 8
    bridge_factor: float = 4.0
    ao_rays: int = 48
    ao_reach: float = 0.15
    padding_px: int = 4


@dataclass
class Maps:
    """The baked maps of one level, each (S, S, 3) uint8 except ``bridged`` (S, S) uint8 (255:
    the surface there was bridged without data); ``covered`` (S, S) bool texels inside a chart;
    ``stats`` JSON-ready figures; ``view`` (S, S) int8, with the photographs, the view that weighs
    most in each texel's colour (-1: none, or outside the charts), ``view_set`` (S, S) uint32 the
    views blended there (bit k: view k)."""

    base_colour: np.ndarray
    normal: np.ndarray
    occlusion: np.ndarray
    bridged: np.ndarray
    covered: np.ndarray
    stats: dict
    view: np.ndarray | None = None
    view_set: np.ndarray | None = None


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 area-weighted unit vertex normals."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 0, n / np.maximum(length, 1e-30), np.array([0.0, 0.0, 1.0]))
    return n.astype(np.float32)


def unwrap(vertices: np.ndarray, faces: np.ndarray, texture_px: int, padding_px: int = 4,
           max_charts_area_share: float = 1 / 500) -> UVMesh:
    """A UV atlas of a mesh with xatlas, packed for a ``texture_px`` square texture.

    A chart may cover at most ``max_charts_area_share`` of the surface, and the chart growing runs
    one iteration: xatlas's defaults grow charts without bound, and its time grows faster than the
    faces (measured here on the bunny's Poisson surface decimated to 150 k faces: 77 s of CPU with
    the defaults, 6-9 s with 1/1000-1/300 of the area a chart and one iteration; 40 k faces 6.5 s and
    1.1 s), at the same packing utilisation within a few points (0.84 -> 0.65-0.68: more, smaller
    charts; the texture budget loses a fifth of its texels).

    Raises :class:`InputError` when the mesh is too small to unwrap (fewer than 4 faces) or the
    atlas comes back empty."""
    import xatlas

    if len(faces) < 4:
        raise InputError("mesh", f"{len(faces)} faces are too few to unwrap (need 4)")
    v32 = np.ascontiguousarray(vertices, np.float32)
    f32 = np.ascontiguousarray(faces, np.uint32)
    area = 0.5 * float(np.linalg.norm(np.cross(v32[f32[:, 1]] - v32[f32[:, 0]], v32[f32[:, 2]] - v32[f32[:, 0]]),
                                      axis=1).sum())
    atlas = xatlas.Atlas()
    atlas.add_mesh(v32, f32)
    charts = xatlas.ChartOptions()
    charts.max_iterations = 1
    if area > 0:
        charts.max_chart_area = area * max_charts_area_share
    pack = xatlas.PackOptions()
    pack.resolution = int(texture_px)
    pack.padding = int(padding_px)
    pack.bilinear = True
    pack.rotate_charts = True
    pack.blockAlign = True
    atlas.generate(charts, pack)
    vmap, idx, uv = atlas[0]
    if len(idx) == 0:
        raise InputError("mesh", "the UV atlas is empty (degenerate mesh)")
    v = np.asarray(vertices, np.float64)[vmap]
    f = np.asarray(idx, np.int32)
    return UVMesh(vertices=v, faces=f, uv=np.asarray(uv, np.float32), normals=vertex_normals(v, f))


def _fill_gutters(img: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Texels outside the charts take the nearest covered texel's value."""
    if covered.all() or not covered.any():
        return img
    _, labels = cv2.distanceTransformWithLabels((~covered).astype(np.uint8), cv2.DIST_L2, 3,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    # Labels number the zero pixels (the covered texels) in row-major order from 1.
    src = np.flatnonzero(covered.ravel())
    flat = img.reshape(covered.size, -1)
    out = flat[src[labels.ravel() - 1]]
    return out.reshape(img.shape)


def _tangent_frames(m: UVMesh) -> tuple[np.ndarray, np.ndarray]:
    """Per face (F, 3) unit tangent (direction of +u) and bitangent (direction of the image's up,
    i.e. -v), from the faces' UV derivatives."""
    v = m.vertices[m.faces]
    t = m.uv[m.faces].astype(np.float64)
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    r = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    r = np.where(np.abs(r) < 1e-20, 1e-20, r)
    T = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / r[:, None]
    B = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) / r[:, None]
    T /= np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-30)
    B /= np.maximum(np.linalg.norm(B, axis=1, keepdims=True), 1e-30)
    return T, -B


def _occlusion(m: UVMesh, rays: int, reach: float) -> np.ndarray:
    """(V,) float32 share of cosine-weighted hemisphere rays from each vertex that escape."""
    import open3d as o3d

    if rays <= 0:
        return np.ones(len(m.vertices), np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.ascontiguousarray(m.vertices, np.float32), np.ascontiguousarray(m.faces, np.uint32))
    diag = float(np.linalg.norm(np.ptp(m.vertices, axis=0)))
    rng = np.random.default_rng(0)
    n = m.normals.astype(np.float64)
    # A frame per vertex, then the same stratified cosine-weighted directions for all.
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    u1 = (np.arange(rays) + rng.random(rays)) / rays
    u2 = rng.random(rays)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], axis=1)
    escaped = np.zeros(len(n))
    origin = m.vertices + n * diag * 1e-4
    for k in range(rays):
        d = local[k, 0] * t1 + local[k, 1] * t2 + local[k, 2] * n
        hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, d], axis=1).astype(np.float32)))
        escaped += hit["t_hit"].numpy() > reach * diag
    return (escaped / rays).astype(np.float32)


def _sheet_normal(hi: np.ndarray, N: np.ndarray) -> np.ndarray:
    """The master's normal hi (n, 3), or the level's N where they are more than ~80 degrees apart
    (the master's comes from another sheet of the surface there)."""
    return np.where((np.einsum("ij,ij->i", hi, N) < 0.17)[:, None], N, hi)


def _colour_normals(P: np.ndarray, N: np.ndarray, mtree: cKDTree, master_normals: np.ndarray,
                    workers: int) -> np.ndarray:
    """(n, 3) the normals the photographs are read with at level points P (n, 3) with level
    normals N: the master's (its four nearest vertices, inverse-distance weighted), see _sheet_normal."""
    d, nb = mtree.query(P, k=4, workers=workers)
    w = 1.0 / np.maximum(d, 1e-9)
    hi = np.einsum("nk,nkj->nj", w, master_normals[nb].astype(np.float64))
    hi /= np.maximum(np.linalg.norm(hi, axis=1, keepdims=True), 1e-30)
    return _sheet_normal(hi, N)


def _surface_samples(m: UVMesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n points (n, 3) mm uniformly over the level's area and their interpolated unit normals (n, 3)."""
    rng = np.random.default_rng(seed)
    v = m.vertices[m.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    fid = rng.choice(len(m.faces), size=n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    b = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
    P = np.einsum("nk,nkj->nj", b, v[fid])
    N = np.einsum("nk,nkj->nj", b, m.normals[m.faces[fid]].astype(np.float64))
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)
    return P, N


def bake_maps(m: UVMesh, texture_px: int, colours: ColourSource, master_vertices: np.ndarray,
              master_normals: np.ndarray, params: BakeParams | None = None, chunk: int = 1 << 20,
              photo: PhotoSource | None = None, master_bridged: np.ndarray | None = None) -> Maps:
    """Bake base colour, normal, occlusion and bridged maps of a level (see the module docstring).

    m : the level with its atlas; colours : the samples; master_vertices (M, 3), master_normals
    (M, 3): the master mesh the normal map carries the detail of. Texels are baked ``chunk`` at a
    time, so the memory beyond the maps themselves stays bounded at any texture size. ``photo``:
    base colour from the views' photographs (:mod:`shared.derive.photo`) wherever a view sees the
    texel, the cloud's colour elsewhere. ``master_bridged`` (M,) bool: the master's own bridged
    flag (``mesh.ply``'s ``bridged`` property); a texel whose nearest master vertex carries it is
    marked bridged too.
    """
    params = params or BakeParams()
    t0 = time.perf_counter()
    S = int(texture_px)
    face_id = np.full((S, S), -1, np.int32)
    bary = np.zeros((S, S, 3), np.float32)
    rasterise_uv(np.ascontiguousarray(m.uv, np.float32), np.ascontiguousarray(m.faces, np.int32), S, face_id, bary)
    covered = face_id >= 0
    idx = np.flatnonzero(covered.ravel())
    if len(idx) == 0:
        raise InputError("mesh", "the atlas covers no texel")
    t1 = time.perf_counter()
    workers = cpu_budget()
    tree = cKDTree(colours.xyz)
    mtree = cKDTree(master_vertices)
    T_f, B_f = _tangent_frames(m)
    ao_v = _occlusion(m, params.ao_rays, params.ao_reach)
    scene = None
    photo_seen = 0
    if photo is not None:
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(np.ascontiguousarray(m.vertices, np.float32), np.ascontiguousarray(m.faces, np.uint32))
        P, N = _surface_samples(m, photo.params.gain_samples)
        photo.solve_gains(P, _colour_normals(P, N, mtree, master_normals, workers), scene,
                          surface=(m.vertices, m.faces))
    t2 = time.perf_counter()
    lut = linear_from_srgb(np.arange(256, dtype=np.float32) / 255.0)
    colour = np.empty((len(idx), 3), np.uint8)
    nmap = np.empty((len(idx), 3), np.uint8)
    ao8 = np.empty(len(idx), np.uint8)
    bridged = np.zeros(len(idx), bool)
    view = np.full(len(idx) if photo is not None else 0, -1, np.int8)
    view_set = np.zeros(len(idx) if photo is not None else 0, np.uint32)
    occlusion_sum = 0.0
    k = max(1, params.neighbours)
    for s in range(0, len(idx), chunk):
        sl = slice(s, min(len(idx), s + chunk))
        fid = face_id.ravel()[idx[sl]]
        b = bary.reshape(-1, 3)[idx[sl]].astype(np.float64)
        corners = m.faces[fid]
        P = np.einsum("nk,nkj->nj", b, m.vertices[corners])
        N = np.einsum("nk,nkj->nj", b, m.normals[corners].astype(np.float64))
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)
        # Base colour: Gaussian-weighted mean of the nearest samples facing the same way, in linear light.
        d, nb = tree.query(P, k=k, workers=workers)
        d = d.reshape(len(d), k)
        nb = nb.reshape(len(nb), k)
        sigma = np.maximum(colours.size[nb[:, 0]].astype(np.float64), 1e-6)
        facing = np.einsum("nkj,nj->nk", colours.normals[nb].astype(np.float64), N) > 0.2
        w = np.exp(-0.5 * (d / sigma[:, None]) ** 2) * facing
        w[:, 0] += 1e-6  # never all zero: the nearest sample stands in
        lin = np.einsum("nk,nkc->nc", w, lut[colours.rgb[nb]]) / w.sum(axis=1, keepdims=True)
        bridged[sl] = d[:, 0] > params.bridge_factor * sigma
        # Normal map: the master's normals in the level's tangent frame.
        d, nb = mtree.query(P, k=4, workers=workers)
        if master_bridged is not None:
            bridged[sl] |= master_bridged[nb[:, 0]]
        w = 1.0 / np.maximum(d, 1e-9)
        hi = np.einsum("nk,nkj->nj", w, master_normals[nb].astype(np.float64))
        hi /= np.maximum(np.linalg.norm(hi, axis=1, keepdims=True), 1e-30)
        # Photographs: the master's normal divides the projector's cosine (the level's is too coarse).
        if photo is not None:
            lin_p, seen, top, used = photo.colour(P, _sheet_normal(hi, N), scene, return_view=True)
            view[sl] = top
            view_set[sl] = used
            if seen.any() and (~seen).any():
                # Texels no view sees keep the cloud's colour, brought to the photographs' scale.
                lc, lp = lin[seen] @ _LUMA, lin_p[seen] @ _LUMA
                lin[~seen] *= float(np.median(lp) / max(float(np.median(lc)), 1e-6))
            lin[seen] = lin_p[seen]
            photo_seen += int(seen.sum())
        colour[sl] = encode_srgb(lin)
        T = T_f[fid] - N * np.einsum("ij,ij->i", T_f[fid], N)[:, None]
        T /= np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-30)
        sign = np.sign(np.einsum("ij,ij->i", np.cross(N, T), B_f[fid]))
        B = np.cross(N, T) * np.where(sign == 0, 1.0, sign)[:, None]
        ts = np.stack([np.einsum("ij,ij->i", hi, T), np.einsum("ij,ij->i", hi, B), np.einsum("ij,ij->i", hi, N)], 1)
        # A master normal more than about 80 degrees off the level's comes from another sheet of
        # the surface (a thin ear, the far side of a fold the decimation closed): flat there,
        # rather than a texel that lights as if seen edge-on.
        ts[ts[:, 2] < 0.17] = (0.0, 0.0, 1.0)
        ts /= np.maximum(np.linalg.norm(ts, axis=1, keepdims=True), 1e-30)
        nmap[sl] = np.clip(np.rint((ts * 0.5 + 0.5) * 255), 0, 255).astype(np.uint8)
        ao = np.einsum("nk,nk->n", b, ao_v[corners])
        occlusion_sum += float(ao.sum())
        ao8[sl] = np.clip(np.rint(ao * 255), 0, 255).astype(np.uint8)
    del bary
    t3 = time.perf_counter()

    def image(values: np.ndarray, fill: int) -> np.ndarray:
        img = np.full((S * S, values.shape[1] if values.ndim == 2 else 1), fill, np.uint8)
        img[idx] = values.reshape(len(idx), -1)
        return _fill_gutters(img.reshape(S, S, -1), covered)

    base = image(colour, 0)
    normal = image(nmap, 128)
    occl = np.repeat(image(ao8, 255), 3, axis=2)
    bmask = image(bridged.astype(np.uint8) * 255, 0)[:, :, 0]
    stats = {
        "texture_px": S,
        "texels_covered_share": round(len(idx) / (S * S), 4),
        "bridged_share": round(float(bridged.mean()), 4),
        "mean_occlusion": round(1 - occlusion_sum / len(idx), 4),
        "colour": colours.kind if photo is None else "photo",
        "seconds": {"raster": round(t1 - t0, 3), "occlusion": round(t2 - t1, 3), "texels": round(t3 - t2, 3),
                    "fill": round(time.perf_counter() - t3, 3)},
    }
    if photo is not None:
        risk = photo.stats.get("highlight_risk_points", 0) / max(photo.stats.get("points_coloured", 0), 1)
        stats["photo"] = {"texels_seen_share": round(photo_seen / len(idx), 4),
                          "highlight_risk_share": round(risk, 5), **photo.stats}
    view_map = view_sets = None
    if photo is not None:
        view_map = np.full(S * S, -1, np.int8)
        view_map[idx] = view
        view_map = view_map.reshape(S, S)
        view_sets = np.zeros(S * S, np.uint32)
        view_sets[idx] = view_set
        view_sets = view_sets.reshape(S, S)
    return Maps(base_colour=base, normal=normal, occlusion=occl, bridged=bmask, covered=covered, stats=stats,
                view=view_map, view_set=view_sets)
