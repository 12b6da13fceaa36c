"""A tiny self-contained structured-light renderer for unit tests: one tilted textured plane.

Independent of the virtual rig (shared/simulate.py), so decoder and triangulation unit tests
have exact analytic truth: the plane is known, and each camera pixel's projector coordinate
is computed by intersecting its (distorted) ray with the plane and projecting the point into
the (distorted) projector. Patterns are box-filtered over 3x3 sub-samples per camera pixel,
then blurred, scaled by a texture albedo, offset by ambient light and given sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from shared.formats.capture import code_bits, write_capture
from shared.formats.rig import Device, Rig, save_rig
from shared.scan.graycode import capture_for_names, gray_encode


@dataclass
class PlaneTruth:
    rig: Rig
    normal: np.ndarray  # plane: normal . X = offset (camera frame, mm)
    offset: float
    depth: np.ndarray  # (H, W) true Z at pixel centres
    proj_col: np.ndarray  # (H, W) true projector column at pixel centres
    proj_row: np.ndarray
    lit: np.ndarray  # (H, W) bool

    def distance(self, xyz: np.ndarray) -> np.ndarray:
        return np.abs(xyz.astype(np.float64) @ self.normal - self.offset)


def make_rig(cam: tuple[int, int], proj: tuple[int, int], distortion: bool = True) -> Rig:
    cw, ch = cam
    pw, ph = proj
    Kc = np.array([[1.5 * cw, 0, cw / 2 - 0.5], [0, 1.5 * cw, ch / 2 - 0.5], [0, 0, 1]], float)
    Kp = np.array([[1.6 * pw, 0, pw / 2], [0, 1.6 * pw, ph * 0.6], [0, 0, 1]], float)
    dc = np.array([-0.12, 0.08, 0.0005, -0.0004, 0.0]) if distortion else np.zeros(5)
    dp = np.array([0.06, -0.03, 0.0003, 0.0002, 0.0]) if distortion else np.zeros(5)
    # Projector 220 mm to the right, slightly above, turned toward the scene centre at 1 m.
    angle = np.deg2rad(12.0)
    Ry = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    tilt = np.deg2rad(3.0)
    Rx = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    R = Rx @ Ry
    C = np.array([220.0, -30.0, 0.0])  # projector centre in the camera frame
    T = -R @ C
    return Rig(camera=Device(cw, ch, Kc, dc), projector=Device(pw, ph, Kp, dp), R=R, T=T)


def _project(rig: Rig, X: np.ndarray) -> np.ndarray:
    """Projector pixel coordinates of camera-frame points (N, 3), through its distortion."""
    Xp = X @ rig.R.T + rig.T
    x, y = Xp[:, 0] / Xp[:, 2], Xp[:, 1] / Xp[:, 2]
    k1, k2, p1, p2, k3 = rig.projector.dist[:5]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    K = rig.projector.K
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


def render_plane_capture(
    out: Path,
    cam: tuple[int, int] = (640, 480),
    proj: tuple[int, int] = (256, 192),
    *,
    seed: int = 0,
    blur: float = 0.6,
    noise: float = 1.2,
    ambient: float = 12.0,
    gain: float = 200.0,
    dark_albedo: float = 0.15,
    rows: bool = True,
    inverse: bool = True,
    drop_bits: int = 0,
    distortion: bool = True,
    shadow: bool = True,
) -> PlaneTruth:
    """Render a capture of a tilted plane into ``out`` (PNG files, capture.json, rig.json)."""
    rng = np.random.default_rng(seed)
    rig = make_rig(cam, proj, distortion)
    cw, ch = cam
    normal = np.array([0.25, -0.15, 1.0])
    normal /= np.linalg.norm(normal)
    offset = 1000.0 * normal[2]
    ss = 3
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    xs = (np.arange(cw)[None, :, None, None] + sub[None, None, None, :]) * np.ones((ch, 1, ss, 1))
    ys = (np.arange(ch)[:, None, None, None] + sub[None, None, :, None]) * np.ones((1, cw, 1, ss))
    pix = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pix, rig.camera.K, rig.camera.dist).reshape(-1, 2)
    rays = np.concatenate([und, np.ones((len(und), 1))], axis=1)
    lam = offset / (rays @ normal)
    X = rays * lam[:, None]
    pq = _project(rig, X)
    p = pq[:, 0].reshape(ch, cw, ss, ss)
    q = pq[:, 1].reshape(ch, cw, ss, ss)
    inside = (p > -0.5) & (p < proj[0] - 0.5) & (q > -0.5) & (q < proj[1] - 0.5)
    if shadow:
        # An occluder between projector and plane: a disc in projector coordinates casts a shadow.
        inside &= (p - proj[0] * 0.3) ** 2 + (q - proj[1] * 0.6) ** 2 > (proj[1] * 0.08) ** 2
    pi = np.clip(np.floor(p + 0.5).astype(np.int64), 0, proj[0] - 1)
    qi = np.clip(np.floor(q + 0.5).astype(np.int64), 0, proj[1] - 1)
    gp, gq = gray_encode(pi), gray_encode(qi)

    # Albedo: smooth texture with dark patches, in (dark_albedo, 1).
    tex = cv2.GaussianBlur(rng.random((ch // 8 + 1, cw // 8 + 1)), (0, 0), 1.5)
    tex = (tex - tex.min()) / (np.ptp(tex) + 1e-9)
    albedo = dark_albedo + (1 - dark_albedo) * cv2.resize(tex, (cw, ch), interpolation=cv2.INTER_LINEAR)
    colour_tint = np.array([1.0, 0.8, 0.6])

    def shoot(lit_sub: np.ndarray) -> np.ndarray:
        img = (lit_sub & inside).mean(axis=(2, 3))
        if blur > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur)
        val = ambient + gain * albedo * img + ambient * 0.3 * albedo
        val = val + rng.normal(0, noise, val.shape)
        return np.clip(np.round(val), 0, 255).astype(np.uint8)

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    capture = capture_for_names(out, proj[0], proj[1], rows=rows, rig=out / "rig.json")
    full = np.ones_like(inside)
    white = shoot(full)
    cv2.imwrite(str(out / "white.png"), np.clip(white[..., None] * colour_tint[::-1], 0, 255).astype(np.uint8))
    cv2.imwrite(str(out / "black.png"), shoot(np.zeros_like(inside)))
    for g, entries in ((gp, capture.columns), (gq, capture.rows)):
        for e in entries:
            on = ((g >> e.bit) & 1).astype(bool)
            cv2.imwrite(str(e.pattern), shoot(on))
            cv2.imwrite(str(e.inverse), shoot(~on))

    cols = capture.columns[: len(capture.columns) - drop_bits]
    if not inverse:
        cols = tuple(replace(e, inverse=None) for e in cols)
        capture = replace(capture, rows=tuple(replace(e, inverse=None) for e in capture.rows))
    capture = replace(capture, columns=cols)
    write_capture(capture)
    # The images above are linear in the light (a raw sensor): the rig says so.
    save_rig(replace(rig, radiometry={"camera_response": "linear"}), out / "rig.json")

    # Truth at pixel centres.
    cpix = np.stack(np.meshgrid(np.arange(cw, dtype=float), np.arange(ch, dtype=float)), axis=-1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(cpix, rig.camera.K, rig.camera.dist).reshape(-1, 2)
    rays = np.concatenate([und, np.ones((len(und), 1))], axis=1)
    Xc = rays * (offset / (rays @ normal))[:, None]
    pqc = _project(rig, Xc)
    lit = inside.all(axis=(2, 3))
    assert code_bits(proj[0]) == len(capture.columns) + drop_bits
    return PlaneTruth(
        rig=rig,
        normal=normal,
        offset=offset,
        depth=Xc[:, 2].reshape(ch, cw),
        proj_col=pqc[:, 0].reshape(ch, cw),
        proj_row=pqc[:, 1].reshape(ch, cw),
        lit=lit,
    )
