"""The virtual rig: physically plausible synthetic Gray-code captures with per-pixel ground truth.

In: a :class:`~shared.sim.scenes.Scene` (surfaces in the camera frame, mm), a :class:`~shared.formats.rig.Rig`
(:func:`make_rig` builds a realistic one) and :class:`ImagingParams`. Out: a ``graycode-v1``
capture folder (``capture.json``, ``rig.json``, ``white.png``, ``black.png``, ``col_NN[_inv].png``,
``row_NN[_inv].png``) plus ``truth.npz`` with, per camera pixel (H, W):

- ``depth`` float32: camera Z in mm, NaN where no surface;
- ``points`` (H, W, 3) float32: camera-frame point in mm (NaN where no surface);
- ``normals`` (H, W, 3) float32: unit surface normal facing the camera;
- ``proj_col``, ``proj_row`` float32: continuous projector pixel coordinates of the point,
  through the projector's distortion (OpenCV: projector column ``c`` spans ``[c - 0.5, c + 0.5)``);
- ``lit`` bool: surface seen by the camera AND lit by the projector (inside its frame, facing it,
  not in its shadow);
- ``surface`` int16: index of the scene surface seen (-1 none);
- ``labels`` int8: what the pixel sees, the surface's label (:mod:`shared.sim.scenes`): -1 none,
  0 object, 1 turntable plate, 2 support (table top or floor), 3 turntable base, 4 backdrop;
- ``albedo`` (H, W, 3) float32: the linear RGB diffuse albedo (0..1) the image was rendered with
  (area-filtered over the pixel on planes; NaN where no surface);
- ``irradiance`` float32: the linear white-minus-black signal per unit albedo, in fractions of full
  scale: ``(1 - black_level) * cam_vignetting * frame * G`` with ``G = projector_power * cos(theta)
  * (1000 mm / d)^2 * cos^3(off-axis angle) * (1 + projector_vignetting * r^2)`` (``d`` the distance
  from the projector's centre, ``r`` the undistorted normalised radius in the projector's frame,
  ``frame`` the blurred edge of the projector's image, ``cam_vignetting`` cos^4 of the camera
  ray's angle); 0 where not lit, NaN where no surface. :func:`sim_radiometry` states the same for
  a rig's ``radiometry``;
- ``response`` (0-d str): the camera response the images went through (:mod:`shared.sim.response`).

So ``linearise(white) - linearise(black) = albedo * irradiance`` (grey cameras: the albedo's luma
0.299 R + 0.587 G + 0.114 B) up to sensor noise, camera blur, the specular lobe of glossy
materials and inter-reflection: dividing out the projector's irradiance recovers the albedo.

Image formation (per pattern, linear, in fractions of the sensor's full scale): projector irradiance
with cos(theta), inverse-square falloff, cos^3 and lens vignetting, projector black level, defocus blur of the pattern that grows
with distance from the projector's focus (Gaussian in projector pixels, tabulated per blur level),
shadows by a projector shadow map, ambient light, textured and coloured albedo with pixel-area
filtering, a Phong specular lobe that can saturate, subsurface scattering (extra pattern blur on
translucent materials), one bounce of diffuse inter-reflection between
planes that ask for it, camera vignetting (cos^4), optical blur, shot and read noise, full-well
clipping, the camera's response curve (sRGB by default) and 8- or 16-bit quantisation; grey or
colour (BGR PNG) images. Both devices have lens
distortion: camera pixels are traced along their exact (undistorted) rays, and projector
coordinates go through the projector's distortion model.

Public API::

    rig = make_rig(camera_size=(2048, 1536), projector_size=(1024, 768), seed=0)
    scene = build_scene("bunny")          # SCENES: plane, spheres, corner, bunny, teapot, spot, fandisk
    board = TexturedPlane.chessboard(R, t, inner_corners=(9, 7), square_size=30.0)
    scene = Scene("board", [board])       # board.to_camera(board.chessboard_corners()): true corners
    capture = simulate_capture(scene, rig, out_dir, seed=0, imaging=ImagingParams(inverses=True))
    truth = compute_truth(scene, rig)     # the truth arrays only, no images
    images, truth = render_pattern_images(scene, rig, seed=0)   # in memory, for small sizes
    capture = simulate_named("bunny", out_dir, size=(2048, 1536), seed=0)   # ``graylight simulate``
    truth = load_truth(capture.root)

``seed`` of :func:`simulate_capture` drives only the sensor noise; scenes and rigs take their own
seeds. The same arguments always give byte-identical files.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from collections.abc import Collection
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from shared.core.errors import InputError
from shared.formats.capture import Capture, load_capture, write_capture
from shared.formats.rig import Rig, save_rig
from shared.scan.graycode import capture_for_names, pattern_sequence, stripe_bits
from shared.sim.raycast import (
    cast_plane,
    cast_sphere,
    compose_image,
    plane_pixels,
    raster_mesh,
    sensor_readout,
    shade_points,
    undistort_grid,
)
from shared.sim.response import check_response, response_codes
from shared.sim.rigs import make_rig
from shared.sim.scenes import (
    LABEL_NONE,
    SCENES,
    Material,
    MeshObject,
    Scene,
    Sphere,
    TexturedPlane,
    build_scene,
)
from shared.sim.truth import TRUTH_FILE, Truth, load_truth

__all__ = [
    "SCENES",
    "TRUTH_FILE",
    "ImagingParams",
    "Material",
    "MeshObject",
    "Scene",
    "Sphere",
    "TexturedPlane",
    "Truth",
    "build_scene",
    "compute_truth",
    "load_truth",
    "make_rig",
    "render_pattern_images",
    "simulate_capture",
    "sim_radiometry",
    "simulate_named",
]

log = logging.getLogger(__name__)

RIG_FILE = "rig.json"


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


# ---------------------------------------------------------------------------------------------
# Images


def _pattern_table(rig: Rig, imaging: ImagingParams, pg: _Profiles, sigmas: np.ndarray,
                   axis: str, bit: int, inverse: bool) -> tuple[str, np.ndarray]:
    """The varying axis (``"u"`` or ``"v"``) of one projector image and its blurred profile table (L, n).

    A projector image is separable: stripes along one axis times the projector frame along the other.
    """
    w, h = rig.projector.width, rig.projector.height
    b = imaging.black_level
    if axis == "columns":
        s = stripe_bits(w, bit)
        return "u", _profile_table(b + (1 - b) * (~s if inverse else s), sigmas, pg, pg.nu)
    if axis == "rows":
        s = stripe_bits(h, bit)
        return "v", _profile_table(b + (1 - b) * (~s if inverse else s), sigmas, pg, pg.nv)
    if axis == "white":
        return "u", _profile_table(np.ones(w), sigmas, pg, pg.nu)
    if axis == "black":
        return "u", _profile_table(np.full(w, b), sigmas, pg, pg.nu)
    raise ValueError(f"unknown pattern axis {axis!r}")


def _render_image(r: _Render, axis: str, bit: int, inverse: bool, noise_seed: int) -> np.ndarray:
    """One camera image (H, W) or (H, W, 3) BGR, uint8/uint16, of the projector showing one pattern."""
    sh = r.shading
    assert sh is not None
    im = r.imaging
    cam = r.rig.camera
    nc = sh.A.shape[1]
    which, table = _pattern_table(r.rig, im, r.profiles, sh.sigmas, axis, bit, inverse)
    img = np.zeros((cam.height * cam.width, nc), np.float32)
    if which == "u":
        compose_image(sh.index, sh.A, sh.B, sh.off_u, sh.frac_u, table, sh.frame_v, img)
    else:
        compose_image(sh.index, sh.A, sh.B, sh.off_v, sh.frac_v, table, sh.frame_u, img)
    if sh.inter is not None:
        ir = sh.inter
        # Senders: the same pattern at each patch's subsamples (frame edges ignored: patches lie inside).
        k = 0 if which == "u" else 1
        t = table.ravel()
        o, f = ir.sender_off[k], ir.sender_frac[k]
        Ps = (t[o] + f * (t[o + 1] - t[o])).reshape(ir.sender_G.shape)
        E = (ir.sender_G * Ps).mean(axis=1)
        Eind = ir.F @ (ir.sender_albedo * E[:, None])  # (M, C) indirect irradiance at patch centres
        for (off, gx, _), (rows, i00, wx, wy) in zip(ir.grids, ir.pix, strict=True):
            g = Eind[off:]
            e = ((1 - wy)[:, None] * ((1 - wx)[:, None] * g[i00] + wx[:, None] * g[i00 + 1])
                 + wy[:, None] * ((1 - wx)[:, None] * g[i00 + gx] + wx[:, None] * g[i00 + gx + 1]))
            img[sh.index[rows]] += ir.pix_coef[rows] * e
    img = img.reshape(cam.height, cam.width, nc)
    if im.camera_blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), im.camera_blur)
        if img.ndim == 2:
            img = img[:, :, None]
    out = sensor_readout(img, im.full_well, im.read_noise, im.bits, noise_seed, response_codes=r.response_codes,
                         noise=im.noise)
    if nc == 3:
        return np.ascontiguousarray(out[:, :, ::-1])  # RGB -> BGR for cv2.imwrite
    return out[:, :, 0]


def _write_png(path: Path, img: np.ndarray) -> None:
    # Fast zlib level with Huffman-only coding: several times faster than the default for noisy images.
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    if not cv2.imwrite(str(path), img, params):
        raise OSError(f"could not write {path}")


def _noise_seed(seed: int, k: int) -> int:
    return int(np.random.SeedSequence([seed, k]).generate_state(1)[0] & 0x7FFFFFFF)


def render_pattern_images(
    scene: Scene,
    rig: Rig,
    *,
    seed: int = 0,
    imaging: ImagingParams | None = None,
    names: Collection[str] | None = None,
) -> tuple[dict[str, np.ndarray], Truth]:
    """Capture images in memory (name -> image, names as :func:`shared.scan.graycode.pattern_sequence`) and the truth.

    ``names`` picks some of the images (e.g. ``{"white.png", "col_09.png"}``); each image is the
    same as in the full capture with the same seed. Meant for small sizes and tests;
    :func:`simulate_capture` renders one image at a time to disk instead.
    """
    imaging = imaging or ImagingParams()
    r = _render_setup(scene, rig, imaging)
    images = {}
    for k, (name, axis, bit, inv, _) in enumerate(
        pattern_sequence(rig.projector.width, rig.projector.height, rows=imaging.rows)
    ):
        if (inv and not imaging.inverses) or (names is not None and name not in names):
            continue
        images[name] = _render_image(r, axis, bit, inv, _noise_seed(seed, k))
    return images, r.truth


def compute_truth(scene: Scene, rig: Rig, imaging: ImagingParams | None = None) -> Truth:
    """Ground truth only (no images): depth, points, normals, projector coordinates, lit mask."""
    return _render_setup(scene, rig, imaging or ImagingParams(), with_shading=False).truth


def sim_radiometry(imaging: ImagingParams | None = None) -> dict[str, object]:
    """How this simulator forms images, as a rig's ``radiometry`` block (issue 23's rig contract):
    the camera's response, the projector's cos^3 falloff, the camera's cos^4 vignetting when it is
    on, and the projector lens's vignetting ``[k1]`` of ``1 + k1 r^2`` (r the undistorted
    normalised projector radius). A scan divides them out to recover the albedo."""
    imaging = imaging or ImagingParams()
    return {"camera_response": imaging.response, "projector_falloff_cos_power": 3.0,
            "camera_falloff_cos_power": 4.0 if imaging.vignetting else 0.0,
            "projector_vignetting": [float(imaging.projector_vignetting)]}


def _check_size(camera_size: tuple[int, int]) -> None:
    w, h = camera_size
    if not (16 <= w <= 20000 and 16 <= h <= 20000):
        raise InputError("--size", f"camera size {w}x{h} is outside 16..20000 pixels per side")


def simulate_capture(
    scene: Scene,
    rig: Rig,
    out_dir: str | os.PathLike[str],
    *,
    seed: int = 0,
    imaging: ImagingParams | None = None,
    overwrite: bool = False,
    write_truth: bool = True,
) -> Capture:
    """Render a full ``graycode-v1`` capture of ``scene`` into ``out_dir`` (with ``rig.json`` and ``truth.npz``).

    The folder is assembled under a temporary name beside ``out_dir`` and renamed when complete,
    so a failure leaves nothing half-written. An existing non-empty ``out_dir`` is an
    :class:`InputError` unless ``overwrite`` and it holds a capture (then it is replaced). Images are
    rendered and written one at a time (PNG, low compression), so memory stays a few times the size
    of one image's float buffers even at 15 MP (about 1.9 GB peak there). ``seed`` drives the sensor noise; the same inputs give identical files.

    Returns the written capture (as :func:`shared.formats.capture.load_capture` would read it).
    """
    imaging = imaging or ImagingParams()
    if imaging.bits not in (8, 16):
        raise InputError("bits", f"must be 8 or 16, got {imaging.bits}")
    check_response(imaging.response)
    _check_size((rig.camera.width, rig.camera.height))
    out = Path(out_dir).absolute()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not overwrite:
            raise InputError(out, "output folder exists and is not empty")
        if not (out / "capture.json").is_file():
            # Replacing is for re-running a simulation, never for wiping an unrelated folder.
            raise InputError(out, "output folder exists and does not hold a capture; refusing to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o777 & ~umask)  # mkdtemp makes it private; the capture is an ordinary folder
    try:
        t0 = time.perf_counter()
        r = _render_setup(scene, rig, imaging)
        t1 = time.perf_counter()
        seq = pattern_sequence(rig.projector.width, rig.projector.height, rows=imaging.rows)
        # PNG encoding (OpenCV releases the GIL) overlaps with rendering the next image; at most
        # two images wait, so memory stays bounded at 15 MP.
        with ThreadPoolExecutor(max_workers=1) as pool:
            pending: list[Future[None]] = []
            for k, (name, axis, bit, inv, _) in enumerate(seq):
                if inv and not imaging.inverses:
                    continue
                img = _render_image(r, axis, bit, inv, _noise_seed(seed, k))
                pending.append(pool.submit(_write_png, tmp / name, img))
                while len(pending) > 1:
                    pending.pop(0).result()
            for f in pending:
                f.result()
        t2 = time.perf_counter()
        save_rig(rig, tmp / RIG_FILE)
        if write_truth:
            r.truth.save(tmp / TRUTH_FILE)
        capture = capture_for_names(tmp, rig.projector.width, rig.projector.height, rows=imaging.rows,
                                    rig=tmp / RIG_FILE)
        extra = {"simulated": {"scene": scene.name, "description": scene.description, "seed": seed,
                               "truth": TRUTH_FILE if write_truth else None,
                               "imaging": {k: v for k, v in imaging.__dict__.items()}}}
        capture = replace(capture, extra=extra)
        if not imaging.inverses:
            capture = replace(capture, columns=tuple(replace(e, inverse=None) for e in capture.columns),
                              rows=tuple(replace(e, inverse=None) for e in capture.rows))
        write_capture(capture)
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        os.replace(tmp, out)
        log.info("virtual rig: %s %dx%d: setup %.2fs, %d images %.2fs", scene.name, rig.camera.width,
                 rig.camera.height, t1 - t0, len(seq), t2 - t1)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return load_capture(out)


def simulate_named(
    scene: str,
    out_dir: str | os.PathLike[str],
    *,
    size: tuple[int, int] = (2048, 1536),
    projector: tuple[int, int] = (1024, 768),
    seed: int = 0,
    imaging: ImagingParams | None = None,
    overwrite: bool = False,
) -> Capture:
    """``graylight simulate``: a named scene (:data:`SCENES`) with :func:`make_rig` of the given sizes."""
    _check_size(size)
    sc = build_scene(scene, seed=seed)
    rig = make_rig(camera_size=size, projector_size=projector, seed=seed)
    return simulate_capture(sc, rig, out_dir, seed=seed, imaging=imaging, overwrite=overwrite)
