"""How the virtual rig (:mod:`shared.sim.simulate`) forms its images: :class:`ImagingParams` and
the per-capture set-up the pattern images are rendered from.

:func:`_render_setup` casts the camera's rays into the scene (which surface each pixel sees: the
ground truth), builds the projector's shadow map, and tabulates every per-pixel term the images
share (:class:`_Shading`): a visible pixel's image is ``P * A + B``, ``P`` the pattern's value at
its projector position, blurred to its defocus level (the profile tables of :class:`_Profiles`,
:func:`_profile_table`), plus one bounce of diffuse inter-reflection between planes that ask for
it (:func:`_interreflection_setup`). :mod:`shared.sim.simulate` renders each pattern image from
the :class:`_Render` it returns; this module never imports that one.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from shared.formats.rig import Rig
from shared.sim.raycast import (
    cast_plane,
    cast_sphere,
    plane_pixels,
    raster_mesh,
    shade_points,
    undistort_grid,
)
from shared.sim.response import response_codes
from shared.sim.scenes import LABEL_NONE, MeshObject, Scene, Sphere, TexturedPlane
from shared.sim.truth import Truth

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImagingParams:
    """How the images are formed. Intensities are fractions of the sensor's full scale.

    Attributes
    ----------
    projector_power : white-pattern signal of an albedo-1 surface facing the projector at 1 m
        (on its axis, linear, before the camera's vignetting and response)
    projector_vignetting : k1 of the projector lens's vignetting ``1 + k1 r^2`` (r the undistorted
        normalised radius from its principal point, the tangent of the off-axis angle), beyond the
        natural cos^3 falloff: -1.1 loses about 20 % at the corners of :func:`make_rig`'s projector
    response : the camera's response curve from linear signal to stored value:
        ``"srgb"`` (default), ``"linear"`` or ``"gamma:G"`` (:mod:`shared.sim.response`)
    ambient : ambient signal of an albedo-1 surface (room light, lit from above)
    black_level : share of full power an "off" projector pixel still emits
    projector_blur : pattern blur (Gaussian sigma, projector pixels) at the focus distance
    projector_aperture : lens aperture in mm; sets how fast the pattern defocuses off focus
    projector_focus : focus distance along the projector axis in mm (None: the rig's working distance)
    camera_blur : optical blur of the camera (Gaussian sigma, camera pixels)
    full_well, read_noise : sensor electrons at full scale, read noise in electrons RMS
    bits : 8 or 16 bits per sample
    colour : colour camera (3-channel BGR images) instead of grey
    noise : add shot and read noise
    vignetting : camera cos^4 falloff
    interreflection : one-bounce inter-reflection between planes whose material asks for it
    rows : also capture the row patterns
    inverses : also capture each pattern's inverse (without them a decoder thresholds against white/black)
    shadow_map_scale : shadow-map resolution relative to the projector's; None picks one texel per
        ~1.25 camera pixels where the camera looks (clipped to 0.5..3), so shadow edges in ``lit``
        are right to about a camera pixel at any camera size
    """

    projector_power: float = 0.85
    projector_vignetting: float = -1.1
    response: str = "srgb"
    ambient: float = 0.03
    black_level: float = 0.03
    projector_blur: float = 0.45
    projector_aperture: float = 8.0
    projector_focus: float | None = None
    camera_blur: float = 0.55
    full_well: float = 12000.0
    read_noise: float = 6.0
    bits: int = 8
    colour: bool = False
    noise: bool = True
    vignetting: bool = True
    interreflection: bool = True
    rows: bool = True
    inverses: bool = True
    shadow_map_scale: float | None = None



# ---------------------------------------------------------------------------------------------
# Geometry: which surface each pixel sees, and how the projector lights it


def _cast(
    scene: Scene, R_dc: np.ndarray, C: np.ndarray, rx: np.ndarray, ry: np.ndarray, K: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast a device's rays into the scene.

    ``R_dc`` rotates camera-frame vectors into the device frame, ``C`` is the device centre in the
    camera frame; rays are ``(rx, ry, 1)`` in the device frame so ``t`` is device depth.

    Returns ``t`` (H, W) float64 (inf = nothing), ``surface`` (H, W) int16, ``face`` (H, W) int32.
    """
    H, W = rx.shape
    t_best = np.full((H, W), np.inf)
    surf = np.full((H, W), -1, np.int16)
    for i, s in enumerate(scene.surfaces):
        if isinstance(s, TexturedPlane):
            cast_plane(rx, ry, R_dc, C, s.t, s.R[:, 0], s.R[:, 1], s.size_mm, t_best, surf, i)
        elif isinstance(s, Sphere):
            cast_sphere(rx, ry, R_dc, C, s.center, s.radius, t_best, surf, i)
    face = np.full((H, W), -1, np.int32)
    for i, s in enumerate(scene.surfaces):
        if not isinstance(s, MeshObject):
            continue
        v_dev = (s.placed.vertices - C) @ R_dc.T
        fid = np.full((H, W), -1, np.int32)
        raster_mesh(v_dev, s.placed.faces, rx, ry, K, dist, t_best, fid)
        won = fid >= 0
        face[won] = fid[won]
        surf[won] = i
    return t_best, surf, face


@dataclass
class _ShadowMap:
    depth: np.ndarray  # (Hs, Ws) float64, 2x2-max filtered projector depth
    K: np.ndarray  # virtual pinhole (no distortion) of the map


def _shadow_map(scene: Scene, rig: Rig, scale: float) -> _ShadowMap:
    """Depth of the nearest surface along projector rays, on an undistorted grid covering its frame."""
    p = rig.projector
    prx, pry = undistort_grid(p.K, p.dist, p.width, p.height)
    border = np.concatenate([prx[0], prx[-1], prx[:, 0], prx[:, -1]]), np.concatenate([pry[0], pry[-1], pry[:, 0], pry[:, -1]])
    pad_x = 3.0 / p.fx
    pad_y = 3.0 / p.fy
    x0, x1 = float(border[0].min()) - pad_x, float(border[0].max()) + pad_x
    y0, y1 = float(border[1].min()) - pad_y, float(border[1].max()) + pad_y
    f = scale * p.fx
    Ws = int(np.ceil((x1 - x0) * f)) + 1
    Hs = int(np.ceil((y1 - y0) * f)) + 1
    Ks = np.array([[f, 0.0, -x0 * f], [0.0, f, -y0 * f], [0.0, 0.0, 1.0]])
    gx, gy = np.meshgrid((np.arange(Ws) - Ks[0, 2]) / f, (np.arange(Hs) - Ks[1, 2]) / f)
    C = -rig.R.T @ rig.T
    t, _, _ = _cast(scene, rig.R, C, gx, gy, Ks, np.zeros(5))
    # Max over each 2x2 cell: a point compares against the farthest of the four texels around it,
    # so a surface never shadows itself (no acne); shadow edges move by at most one texel.
    tt = np.where(np.isfinite(t), t, 1e30).astype(np.float32)
    tmax = cv2.dilate(tt, np.ones((2, 2), np.uint8), anchor=(0, 0))
    return _ShadowMap(depth=tmax, K=Ks)


@dataclass
class _Shading:
    """Per-visible-pixel terms; an image is ``P * A + B (+ indirect)`` with P the projected pattern value."""

    index: np.ndarray  # (N,) flat camera-pixel indices of visible surface
    A: np.ndarray  # (N, C) float32: coefficient of the pattern value (zero where not lit)
    B: np.ndarray  # (N, C) float32: constant term (ambient)
    off_u: np.ndarray  # (N,) int32 offsets into flattened column profile tables (blur level, position)
    frac_u: np.ndarray  # (N,) float32
    off_v: np.ndarray  # (N,) int32, rows likewise
    frac_v: np.ndarray
    frame_u: np.ndarray  # (N,) float32 blurred projector-frame profile along columns
    frame_v: np.ndarray  # (N,) float32 ... along rows
    sigmas: np.ndarray  # (L,) blur levels, projector pixels
    inter: _Interreflection | None = None


@dataclass
class _Interreflection:
    F: np.ndarray  # (M, M) float32 form factors receiver <- sender
    sender_G: np.ndarray  # (M, S) float32 direct irradiance factor of each patch's subsamples
    sender_off: tuple[np.ndarray, np.ndarray]  # (M*S,) int32 profile offsets along columns, rows
    sender_frac: tuple[np.ndarray, np.ndarray]  # (M*S,) float32 weights
    sender_albedo: np.ndarray  # (M, C)
    grids: list[tuple[int, int, int]]  # per plane: (offset into M, gx, gy)
    pix: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]  # per plane: rows into N, grid cell, weights x, y
    pix_coef: np.ndarray  # (N, C) vign * albedo of each pixel (zero elsewhere)


@dataclass
class _Profiles:
    """Fine-grid geometry of the tabulated 1-D pattern profiles."""

    u0: float
    v0: float
    nu: int
    nv: int
    per_px: int = 8
    margin: int = 8


def _profiles_geometry(rig: Rig) -> _Profiles:
    m = 8
    return _Profiles(u0=-0.5 - m, v0=-0.5 - m, nu=(rig.projector.width + 2 * m) * 8,
                     nv=(rig.projector.height + 2 * m) * 8)


def _profile_table(values: np.ndarray, sigmas: np.ndarray, pg: _Profiles, n_fine: int) -> np.ndarray:
    """Blurred 1-D projector profile per blur level: (L, n_fine) float32.

    ``values`` (n,) are the projector pixels' intensities along one axis; outside the frame the
    projector emits nothing. Fine samples sit at cell centres ``u0 + (j + 0.5) / per_px`` so
    no sample falls on a pixel edge.
    """
    S = pg.per_px
    fine = np.zeros(n_fine, np.float32)
    fine[pg.margin * S : pg.margin * S + values.size * S] = np.repeat(values.astype(np.float32), S)
    return np.stack([gaussian_filter1d(fine, s * S, mode="constant", truncate=5.0) for s in sigmas])


def _sigma_levels(sig: np.ndarray, step: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Blur levels about ``step`` apart covering ``sig`` and each value's nearest level (int32).

    Blur beyond 64 projector pixels washes every pattern out anyway, so it is capped there, and
    at most 200 levels are tabulated (wider spacing for scenes of extreme depth range).
    """
    if sig.size == 0:
        return np.array([0.5]), np.zeros(0, np.int32)
    sig = np.minimum(sig, 64.0)
    lo, hi = float(sig.min()), float(sig.max())
    step = max(step, (hi - lo) / 199)
    n = int(np.ceil((hi - lo) / step)) + 1
    levels = lo + step * np.arange(n)
    return levels, np.clip(np.rint((sig - lo) / step), 0, n - 1).astype(np.int32)


def _lookup(level: np.ndarray, pos: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat offsets and interpolation weights into an (L, n) profile table for fine positions ``pos``."""
    # NaN (points behind the projector, never lit) must still give an index inside the table.
    pos = np.clip(np.nan_to_num(pos, nan=0.0), 0.0, n - 1.001)
    i0 = np.floor(pos)
    return (level.astype(np.int64) * n + i0.astype(np.int64)).astype(np.int32), (pos - i0).astype(np.float32)


@dataclass
class _Render:
    truth: Truth
    shading: _Shading | None
    rig: Rig
    imaging: ImagingParams
    profiles: _Profiles
    response_codes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16))  # empty: linear camera


def _albedo(scene: Scene, surf_ids: np.ndarray, P: np.ndarray, rays: tuple[np.ndarray, np.ndarray],
            index: np.ndarray, width: int, footprint_px: float = 0.29) -> np.ndarray:
    """Albedo (N, 3) float32 of visible points; planes are area-filtered over the pixel footprint."""
    rx, ry = rays
    out = np.empty((P.shape[0], 3), np.float32)
    for i, s in enumerate(scene.surfaces):
        sel = np.flatnonzero(surf_ids == i)
        if sel.size == 0:
            continue
        if isinstance(s, TexturedPlane):
            xy, foot = plane_pixels(rx, ry, index[sel], s.t, s.R[:, 0], s.R[:, 1])
            out[sel] = s.albedo_at_coords(xy, footprint_px * foot)
        else:
            out[sel] = s.albedo_at(P[sel])
    return np.clip(out, 0.0, 1.0)


def _focus_distance(rig: Rig) -> float:
    """Projector distance (along its axis) of the point where its axis passes closest to the camera's."""
    C = -rig.R.T @ rig.T
    d = rig.R[2]  # projector axis in the camera frame
    e = np.array([0.0, 0.0, 1.0])
    # Closest points of the lines C + s d and t e.
    b = float(d @ e)
    w = C
    den = 1 - b * b
    if den < 1e-9:
        return float(np.linalg.norm(C)) + 1000.0
    s = (b * float(e @ w) - float(d @ w)) / den
    return max(float(s), 100.0)


def _projector_terms(rig: Rig, imaging: ImagingParams, P: np.ndarray, n: np.ndarray, sm: _ShadowMap,
                     focus: float, sid: np.ndarray | None = None, scene: Scene | None = None) -> dict[str, np.ndarray]:
    """Projector coordinates, lit mask, irradiance factor, blur and specular factor of points (N, 3).

    ``sid`` (N,) gives each point's surface in ``scene`` for its specular material; without them
    there is no specular term. See :func:`shared.sim.raycast.shade_points`.
    """
    if sid is None or scene is None:
        sid = np.zeros(len(P), np.int64)
        ks, shin, sss = np.zeros(1), np.ones(1), np.zeros(1)
    else:
        ks = np.array([s.material.specular for s in scene.surfaces] or [0.0], np.float64)
        shin = np.array([s.material.shininess for s in scene.surfaces] or [1.0], np.float64)
        sss = np.array([s.material.subsurface for s in scene.surfaces] or [0.0], np.float64)
    p = rig.projector
    return shade_points(
        P, n, rig.R, rig.T, p.K, p.dist, (p.width, p.height), sm.depth, sm.K, imaging.projector_power,
        imaging.projector_blur, imaging.projector_aperture * p.fx, imaging.projector_focus or focus,
        0.29 * p.fx / rig.camera.fx, sid, ks, shin, sss, vignetting=imaging.projector_vignetting,
    )


def _render_setup(scene: Scene, rig: Rig, imaging: ImagingParams, with_shading: bool = True,
                  chunk: int = 1 << 20) -> _Render:
    """Trace the camera's rays, build the projector's shadow map, and tabulate every per-pixel term.

    Per-pixel work runs over chunks of ``chunk`` visible pixels so that temporaries stay small at 15 MP.
    """
    t0 = time.perf_counter()
    cam = rig.camera
    W, H = cam.width, cam.height
    rx, ry = undistort_grid(cam.K, cam.dist, W, H)
    t, surf, face = _cast(scene, np.eye(3), np.zeros(3), rx, ry, cam.K, cam.dist)
    index = np.flatnonzero(np.isfinite(t))
    N = len(index)
    t1 = time.perf_counter()
    scale = imaging.shadow_map_scale
    if scale is None:
        scale = float(np.clip(0.8 * rig.camera.fx / rig.projector.fx, 0.5, 3.0))
    sm = _shadow_map(scene, rig, scale)
    t2 = time.perf_counter()
    focus = _focus_distance(rig)
    nc = 3 if imaging.colour else 1
    luma = np.array([0.299, 0.587, 0.114], np.float32)
    inter_planes = imaging.interreflection and sum(
        isinstance(s, TexturedPlane) and s.material.interreflect for s in scene.surfaces) >= 2

    depth = np.full(H * W, np.nan, np.float32)
    points = np.full((H * W, 3), np.nan, np.float32)
    normals = np.full((H * W, 3), np.nan, np.float32)
    proj_col = np.full(H * W, np.nan, np.float32)
    proj_row = np.full(H * W, np.nan, np.float32)
    lit = np.zeros(H * W, np.bool_)
    albedo_map = np.full((H * W, 3), np.nan, np.float32)
    irradiance = np.full(H * W, np.nan, np.float32)
    sigma = np.empty(N, np.float32)
    if with_shading:
        A = np.empty((N, nc), np.float32)
        B = np.empty((N, nc), np.float32)
        coef = np.zeros((N, nc), np.float32) if inter_planes else None
    t_flat, surf_flat, face_flat, rxf, ryf = t.ravel(), surf.ravel(), face.ravel(), rx.ravel(), ry.ravel()
    for c0 in range(0, N, chunk):
        idx = index[c0 : c0 + chunk]
        tv = t_flat[idx]
        P = np.stack([rxf[idx] * tv, ryf[idx] * tv, tv], axis=-1)
        sv = surf_flat[idx]
        n = np.empty_like(P)
        for i, s in enumerate(scene.surfaces):
            sel = np.flatnonzero(sv == i)
            if sel.size == 0:
                continue
            n[sel] = s.face_normals[face_flat[idx[sel]]] if isinstance(s, MeshObject) else s.normals_at(P[sel])
        n[np.einsum("ij,ij->i", n, P) > 0] *= -1
        pt = _projector_terms(rig, imaging, P, n, sm, focus, sv, scene)
        depth[idx] = tv
        points[idx] = P
        normals[idx] = n
        proj_col[idx] = pt["u"]
        proj_row[idx] = pt["v"]
        lit[idx] = pt["lit"]
        albedo = _albedo(scene, sv, P, (rx, ry), idx, W)
        albedo_map[idx] = albedo
        if imaging.vignetting:
            vign = (1.0 / (1.0 + rxf[idx] ** 2 + ryf[idx] ** 2) ** 2).astype(np.float32)
        else:
            vign = np.ones(len(idx), np.float32)
        sl = slice(c0, c0 + len(idx))
        sigma[sl] = pt["sigma"]
        # White minus black per unit albedo (the projector frame's edge profile follows below).
        irradiance[idx] = vign * (1.0 - imaging.black_level) * pt["G"]
        if not with_shading:
            continue
        if nc == 1:
            albedo = (albedo @ luma)[:, None]
        # Room light from above (camera -Y is roughly up in every scene).
        amb = (imaging.ambient * (0.65 + 0.35 * np.clip(-n[:, 1], 0, None))).astype(np.float32)
        A[sl] = vign[:, None] * (pt["G"][:, None] * albedo + pt["spec"][:, None])
        B[sl] = vign[:, None] * amb[:, None] * albedo
        if coef is not None:
            coef[sl] = vign[:, None] * albedo
    del t, face, t_flat, face_flat
    label_of = np.array([s.label for s in scene.surfaces] + [LABEL_NONE], np.int8)  # index -1: no surface
    truth = Truth(
        depth=depth.reshape(H, W), points=points.reshape(H, W, 3), normals=normals.reshape(H, W, 3),
        proj_col=proj_col.reshape(H, W), proj_row=proj_row.reshape(H, W), lit=lit.reshape(H, W), surface=surf,
        labels=label_of[surf], albedo=albedo_map.reshape(H, W, 3), irradiance=irradiance.reshape(H, W),
        response=imaging.response,
    )
    pg = _profiles_geometry(rig)
    levels, lvl = _sigma_levels(sigma)
    del sigma
    S = pg.per_px
    off_u = np.empty(N, np.int32)
    frac_u = np.empty(N, np.float32)
    off_v = np.empty(N, np.int32)
    frac_v = np.empty(N, np.float32)
    fr_u = np.empty(N, np.float32)
    fr_v = np.empty(N, np.float32)
    frame_u = _profile_table(np.ones(rig.projector.width), levels, pg, pg.nu).ravel()
    frame_v = _profile_table(np.ones(rig.projector.height), levels, pg, pg.nv).ravel()
    for c0 in range(0, N, chunk):
        idx = index[c0 : c0 + chunk]
        sl = slice(c0, c0 + len(idx))
        ou, fu = _lookup(lvl[sl], (proj_col[idx].astype(np.float64) - pg.u0) * S - 0.5, pg.nu)
        ov, fv = _lookup(lvl[sl], (proj_row[idx].astype(np.float64) - pg.v0) * S - 0.5, pg.nv)
        off_u[sl], frac_u[sl], off_v[sl], frac_v[sl] = ou, fu, ov, fv
        fr_u[sl] = frame_u[ou] + fu * (frame_u[ou + 1] - frame_u[ou])
        fr_v[sl] = frame_v[ov] + fv * (frame_v[ov + 1] - frame_v[ov])
    irradiance[index] *= fr_u * fr_v
    if not with_shading:
        return _Render(truth=truth, shading=None, rig=rig, imaging=imaging, profiles=pg)
    shading = _Shading(index=index, A=A, B=B, off_u=off_u, frac_u=frac_u, off_v=off_v, frac_v=frac_v,
                       frame_u=fr_u, frame_v=fr_v, sigmas=levels)
    if coef is not None:
        shading.inter = _interreflection_setup(scene, rig, imaging, sm, shading, surf.ravel()[index], truth, coef,
                                               levels, pg)
    t3 = time.perf_counter()
    log.info("virtual rig: rays+cast %.2fs, shadow map %.2fs, shading %.2fs", t1 - t0, t2 - t1, t3 - t2)
    return _Render(truth=truth, shading=shading, rig=rig, imaging=imaging, profiles=pg,
                   response_codes=response_codes(imaging.response, imaging.bits))


def _interreflection_setup(scene: Scene, rig: Rig, imaging: ImagingParams, sm: _ShadowMap, sh: _Shading,
                           sv: np.ndarray, truth: Truth, coef: np.ndarray,
                           levels: np.ndarray, pg: _Profiles) -> _Interreflection | None:
    """Form factors between patches of the inter-reflecting planes, and where each camera pixel sits on them.

    ``sv`` (N,) surface of each visible pixel, ``coef`` (N, C) its vignetting times albedo.
    """
    planes = [(i, s) for i, s in enumerate(scene.surfaces)
              if isinstance(s, TexturedPlane) and s.material.interreflect]
    if len(planes) < 2:
        return None
    sub = 3
    centres, normals, areas, grids, alb, sub_pts, sub_n = [], [], [], [], [], [], []
    offset = 0
    for _, s in planes:
        w, h = s.size_mm
        gx = 32
        gy = max(2, int(round(gx * h / w)))
        cw, chh = w / gx, h / gy
        xs = (np.arange(gx) + 0.5) * cw
        ys = (np.arange(gy) + 0.5) * chh
        cxy = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        centres.append(s.to_camera(cxy))
        normals.append(np.broadcast_to(s.normal, (len(cxy), 3)))
        areas.append(np.full(len(cxy), cw * chh))
        off = (np.arange(sub) + 0.5) / sub - 0.5
        oxy = np.stack(np.meshgrid(off * cw, off * chh), axis=-1).reshape(-1, 2)
        sxy = (cxy[:, None, :] + oxy[None, :, :]).reshape(-1, 2)
        sub_pts.append(s.to_camera(sxy))
        sub_n.append(np.broadcast_to(s.normal, (len(sxy), 3)))
        a = s.albedo_at_coords(sxy, np.full((len(sxy), 2), cw / sub / 2)).reshape(len(cxy), sub * sub, 3).mean(axis=1)
        alb.append(a)
        grids.append((offset, gx, gy))
        offset += len(cxy)
    Cs = np.concatenate(centres)
    Ns = np.concatenate(normals).copy()
    As = np.concatenate(areas)
    Sp = np.concatenate(sub_pts)
    Sn = np.concatenate(sub_n).copy()
    # Orient each patch's normal towards the camera (the side that is lit and seen).
    Ns[np.einsum("ij,ij->i", Ns, Cs) > 0] *= -1
    Sn[np.einsum("ij,ij->i", Sn, Sp) > 0] *= -1
    M = len(Cs)
    D = Cs[None, :, :] - Cs[:, None, :]  # receiver i -> sender j
    r2 = np.einsum("ijk,ijk->ij", D, D)
    r2 = np.maximum(r2, As[None, :])
    r = np.sqrt(r2)
    cos_i = np.einsum("ijk,ik->ij", D, Ns) / r
    cos_j = -np.einsum("ijk,jk->ij", D, Ns) / r
    F = np.where((cos_i > 0) & (cos_j > 0), cos_i * cos_j * As[None, :] / (np.pi * r2), 0.0)
    np.fill_diagonal(F, 0.0)
    pt = _projector_terms(rig, imaging, Sp, Sn, sm, _focus_distance(rig))
    step = levels[1] - levels[0] if len(levels) > 1 else 1.0
    lvl = np.clip(np.rint((np.minimum(pt["sigma"], 64.0) - levels[0]) / step), 0, len(levels) - 1).astype(np.int32)
    S = pg.per_px
    off_u, frac_u = _lookup(lvl, (pt["u"] - pg.u0) * S - 0.5, pg.nu)
    off_v, frac_v = _lookup(lvl, (pt["v"] - pg.v0) * S - 0.5, pg.nv)
    a_s = np.concatenate(alb).astype(np.float32)
    if coef.shape[1] == 1:
        a_s = (a_s @ np.array([0.299, 0.587, 0.114], np.float32))[:, None]
    pix = []
    pts = truth.points.reshape(-1, 3)
    for (i, s), (_, gx, gy) in zip(planes, grids, strict=True):
        rows = np.flatnonzero(sv == i)
        xy = s.plane_coords(pts[sh.index[rows]].astype(np.float64))
        w, h = s.size_mm
        # Bilinear weights into the plane's patch grid, fixed for every pattern.
        fx = np.clip(xy[:, 0] / (w / gx) - 0.5, 0, gx - 1.0)
        fy = np.clip(xy[:, 1] / (h / gy) - 0.5, 0, gy - 1.0)
        ix = np.minimum(np.floor(fx).astype(np.int32), gx - 2)
        iy = np.minimum(np.floor(fy).astype(np.int32), gy - 2)
        pix.append((rows, (iy * gx + ix).astype(np.int32), (fx - ix).astype(np.float32), (fy - iy).astype(np.float32)))
    return _Interreflection(
        F=F.astype(np.float32),
        sender_G=pt["G"].reshape(M, sub * sub).astype(np.float32),
        sender_off=(off_u, off_v),
        sender_frac=(frac_u, frac_v),
        sender_albedo=a_s,
        grids=grids,
        pix=pix,
        pix_coef=coef,
    )
