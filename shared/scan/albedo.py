"""Albedo from the projector's controlled light.

The projector is the only strong light of a scan and its pose and intrinsics are calibrated, so
the white frame minus the black frame at a camera pixel is, through the camera's response,

    W - B = albedo * P * g * cos(theta_p) * vignetting(u, v) / d_p^2

with ``d_p`` the distance from the projector's centre to the triangulated point, ``theta_p`` the
angle between the surface normal and the direction to the projector, ``(u, v)`` the projector
pixel lighting the point, and ``P * g`` the projector's power times the camera's gain (one
constant per rig and exposure). Dividing the linearised difference by the geometric part leaves
the albedo up to that constant; it is fixed by a reference distance: an albedo of 1 is the
linear white-minus-black value of a surface facing the projector at ``reference_distance``
(by default the median projector distance of the view's points, reported, so the views of one
object on one rig agree to within the spread of their median distances).

A sample is masked (weight 0) when its white frame is saturated in any channel (the difference
is clipped, not the light), when the signal is too dark to divide (shadow, black surface), when
the surface is grazing to the projector (cosine below ``min_cos``: noise divided by a small
number), or when the point does not project into the projector's image.

Storage in ``cloud.ply``: ``albedo_red``, ``albedo_green``, ``albedo_blue`` (uchar, the linear
albedo clipped to [0, 1] and sRGB-encoded, as textures store colour) and ``albedo_weight``
(uchar, 255 times the projector cosine; 0 where masked). The shaded colour stays in
``red, green, blue``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shared.core.errors import InputError
from shared.formats.rig import Rig

log = logging.getLogger(__name__)

__all__ = [
    "AlbedoParams",
    "CameraResponse",
    "SampleAlbedo",
    "encode_srgb",
    "estimate_albedo",
    "linear_from_srgb",
    "params_for_rig",
    "parse_response",
    "projector_geometry",
    "response_for_rig",
    "smooth_normals",
]

#: Mask reasons of :class:`SampleAlbedo` ``reason``.
REASONS = ("ok", "saturated", "dark", "grazing", "outside_projector", "back_facing")


def linear_from_srgb(v: np.ndarray) -> np.ndarray:
    """The sRGB transfer function's inverse (IEC 61966-2-1): values in [0, 1] -> linear, float32."""
    v = np.asarray(v, np.float32)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def encode_srgb(lin: np.ndarray) -> np.ndarray:
    """Linear values (clipped to [0, 1]) -> sRGB-encoded uint8 (rounded)."""
    x = np.clip(np.asarray(lin, np.float32), 0.0, 1.0)
    v = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.rint(v * 255.0), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class CameraResponse:
    """The camera's response: 8-bit code -> linear irradiance in [0, 1].

    kind : ``srgb`` (default: what most cameras write), ``linear`` (raw sensors, the simulator
        without a curve), ``gamma`` (code^gamma) or ``table`` (a measured curve, 256 values).
    """

    kind: str = "srgb"
    gamma: float = 2.2
    table: tuple[float, ...] = ()

    def rig_value(self) -> str | list[float]:
        """The response as a rig's ``radiometry.camera_response`` states it."""
        if self.kind == "gamma":
            return f"gamma:{self.gamma:g}"
        return list(self.table) if self.kind == "table" else self.kind

    def lut(self) -> np.ndarray:
        """(256,) float32: the linear value of every 8-bit code."""
        codes = np.arange(256, dtype=np.float32) / 255.0
        if self.kind == "srgb":
            return linear_from_srgb(codes)
        if self.kind == "linear":
            return codes
        if self.kind == "gamma":
            return (codes ** np.float32(self.gamma)).astype(np.float32)
        if self.kind == "table":
            return np.asarray(self.table, np.float32)
        raise ValueError(f"unknown camera response kind {self.kind!r}")


def parse_response(spec: str | Path) -> CameraResponse:
    """``srgb``, ``linear``, ``gamma:G`` or a JSON file ``{"response": [256 increasing values]}``
    (a measured curve, e.g. from OpenCV's CalibrateDebevec, normalised here to end at 1).
    Raises :class:`InputError` naming the spec or file."""
    s = str(spec)
    if s in ("srgb", "linear"):
        return CameraResponse(kind=s)
    if s.startswith("gamma:"):
        try:
            g = float(s[6:])
        except ValueError:
            g = float("nan")
        if not (0.2 <= g <= 5.0):
            raise InputError("response", f"gamma must be a number in [0.2, 5], got {s[6:]!r}")
        return CameraResponse(kind="gamma", gamma=g)
    path = Path(s)
    if not path.is_file():
        raise InputError("response", f"{s!r} is not srgb, linear, gamma:G or a response file")
    if path.stat().st_size > 1 << 20:
        raise InputError(path, "response file larger than 1 MiB")
    try:
        doc = json.loads(path.read_text())
        curve = np.asarray(doc["response"], np.float64)
    except (ValueError, KeyError, TypeError):
        raise InputError(path, 'expected {"response": [256 numbers]}') from None
    if curve.shape != (256,) or not np.isfinite(curve).all() or np.any(np.diff(curve) < 0) or curve[-1] <= 0:
        raise InputError(path, "response must be 256 finite, non-decreasing numbers ending above 0")
    curve = (curve - curve[0]) / (curve[-1] - curve[0]) if curve[-1] > curve[0] else curve / curve[-1]
    return CameraResponse(kind="table", table=tuple(float(c) for c in curve))


@dataclass(frozen=True)
class AlbedoParams:
    """response : the camera's response. vignetting : the projector's radial falloff
    ``1 + k1 r^2 + k2 r^4 + ...`` with r the normalised projector radius ``|(u - c) / f|`` (empty:
    none measured). projector_cos_power, camera_cos_power : natural falloff of either lens as a
    power of the cosine of the off-axis angle (``cos = 1 / sqrt(1 + x^2 + y^2)``, x, y normalised
    device coordinates; 4 is the textbook law; the simulator renders the projector's with 3 and the
    camera's with 4; 0: none). reference_distance : projector distance (rig units) at which a facing white
    surface has albedo 1 (None: the median distance of the view's points). saturation : 8-bit
    code at or above which a white-frame channel counts as saturated. min_signal : smallest linear
    white-minus-black luminance divided (below: dark). min_cos : smallest cosine to the projector
    (about 75 degrees). min_valid_share : below this share of valid samples the view's albedo is
    not trusted (the scan falls back to the shaded colour and says so). normal_radius : half-width
    in pixels of the window whose plane gives each sample's normal (:func:`smooth_normals`;
    measured on the virtual rig's spheres at 400x300: the 8-neighbour normals are 17 degrees off
    the truth at the median and give 0.08 mean absolute albedo error, radius 4 gives 2.4 degrees
    and 0.016; larger windows round off curved surfaces)."""

    response: CameraResponse = field(default_factory=CameraResponse)
    vignetting: tuple[float, ...] = ()
    projector_cos_power: float = 0.0
    camera_cos_power: float = 0.0
    reference_distance: float | None = None
    saturation: int = 250
    min_signal: float = 0.004
    min_cos: float = 0.26
    min_valid_share: float = 0.05
    normal_radius: int = 4


def response_for_rig(rig: Rig | None) -> CameraResponse:
    """The camera response a rig's ``radiometry.camera_response`` states (validated by
    :mod:`shared.formats.rig`); sRGB when the rig states none or there is no rig."""
    resp = ((rig.radiometry or {}) if rig is not None else {}).get("camera_response", "srgb")
    if isinstance(resp, str):
        return CameraResponse("gamma", gamma=float(resp[6:])) if resp.startswith("gamma:") else CameraResponse(resp)
    curve = np.asarray(resp, np.float64)
    curve = (curve - curve[0]) / (curve[-1] - curve[0])
    return CameraResponse("table", table=tuple(float(c) for c in curve))


def params_for_rig(rig: Rig, **overrides) -> AlbedoParams:
    """The albedo parameters a rig's ``radiometry`` (:mod:`shared.formats.rig`) implies; without
    it the defaults (an sRGB camera, no falloff). ``overrides`` replace fields."""
    r = rig.radiometry or {}
    kw = {"response": response_for_rig(rig), "vignetting": tuple(r.get("projector_vignetting", ())),
          "projector_cos_power": float(r.get("projector_falloff_cos_power", 0.0)),
          "camera_cos_power": float(r.get("camera_falloff_cos_power", 0.0))}
    kw.update(overrides)
    return AlbedoParams(**kw)


@dataclass
class SampleAlbedo:
    """Per-sample albedo of one view, N rows aligned with the cloud.

    albedo : (N, 3) float32 linear albedo (NaN where masked).
    weight : (N,) float32 cosine to the projector, 0 where masked.
    reason : (N,) uint8 index into :data:`REASONS`.
    stats : JSON-ready counts, the reference distance and whether the view is trusted.
    """

    albedo: np.ndarray
    weight: np.ndarray
    reason: np.ndarray
    stats: dict

    @property
    def trusted(self) -> bool:
        return bool(self.stats.get("trusted", False))

    def encoded(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) uint8 sRGB-encoded albedo (0 where masked) and (N,) uint8 weight, for the PLY."""
        rgb = encode_srgb(np.nan_to_num(self.albedo, nan=0.0))
        w = np.clip(np.rint(self.weight * 255.0), 0, 255).astype(np.uint8)
        rgb[w == 0] = 0
        return rgb, w


def projector_geometry(xyz: np.ndarray, normals: np.ndarray, rig: Rig, vignetting: tuple[float, ...] = (),
                       cos_power: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The projector's geometric irradiance terms at each point.

    xyz : (N, 3) points in the camera frame (rig units); normals : (N, 3) unit normals (either side).

    Returns (d, cos, vig, inside): (N,) float64 distance from the projector's centre, the cosine
    between the normal turned towards the projector and the direction to it (negative when the
    normal faces away from it, i.e. it faces the camera but not the projector), the vignetting
    factor (the polynomial ``vignetting`` times the off-axis cosine to ``cos_power``), and whether the point projects inside the projector's image.
    """
    X = np.asarray(xyz, np.float64)
    n = np.asarray(normals, np.float64)
    R = np.asarray(rig.R, np.float64)
    T = np.asarray(rig.T, np.float64).ravel()
    centre = -R.T @ T  # the projector's centre in the camera frame
    L = centre[None, :] - X
    d = np.linalg.norm(L, axis=1)
    cos = np.einsum("ij,ij->i", n, L) / np.maximum(d, 1e-12)
    Xp = X @ R.T + T
    z = Xp[:, 2]
    K = np.asarray(rig.projector.K, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = Xp[:, 0] / z
        yn = Xp[:, 1] / z
    u = K[0, 0] * xn + K[0, 2]
    v = K[1, 1] * yn + K[1, 2]
    inside = (z > 0) & (u >= -0.5) & (v >= -0.5) & (u < rig.projector.width - 0.5) & (v < rig.projector.height - 0.5)
    vig = np.ones(len(X))
    if vignetting:
        r2 = np.nan_to_num(xn * xn + yn * yn)
        poly = np.ones(len(X))
        for i, k in enumerate(vignetting):
            poly += float(k) * r2 ** (i + 1)
        vig = np.clip(poly, 1e-3, None)
    if cos_power:
        r2 = np.nan_to_num(xn * xn + yn * yn)
        vig = vig * (1.0 + r2) ** (-0.5 * cos_power)
    return d, cos, vig, inside


def estimate_albedo(white: np.ndarray, black: np.ndarray, xyz: np.ndarray, normals: np.ndarray, rig: Rig,
                    params: AlbedoParams | None = None) -> SampleAlbedo:
    """Per-sample linear albedo of one view (see the module docstring).

    white, black : (N, 3) uint8 RGB of the white and black frames at each point's camera pixel.
    xyz : (N, 3) triangulated points, camera frame, rig units; normals : (N, 3) unit normals.
    """
    params = params or AlbedoParams()
    white = np.asarray(white)
    black = np.asarray(black)
    nrows = len(xyz)
    if white.shape != (nrows, 3) or black.shape != (nrows, 3):
        raise ValueError(f"white and black must be ({nrows}, 3), got {white.shape} and {black.shape}")
    lut = params.response.lut()
    signal = lut[white] - lut[black]  # (N, 3) linear
    lum = signal @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    d, cos, vig, inside = projector_geometry(xyz, normals, rig, params.vignetting, params.projector_cos_power)
    reason = np.zeros(nrows, np.uint8)
    # Checked in reverse order of precedence: the last assignment wins.
    reason[~inside] = REASONS.index("outside_projector")
    reason[inside & (cos <= 0)] = REASONS.index("back_facing")
    reason[(reason == 0) & (cos < params.min_cos)] = REASONS.index("grazing")
    reason[(reason == 0) & (lum < params.min_signal)] = REASONS.index("dark")
    reason[(white >= params.saturation).any(axis=1)] = REASONS.index("saturated")
    ok = reason == 0
    d_ref = params.reference_distance
    if d_ref is None:
        d_ref = float(np.median(d[ok])) if ok.any() else float(np.median(d)) if nrows else 1.0
    if params.camera_cos_power:
        X = np.asarray(xyz, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            r2 = np.nan_to_num((X[:, 0] ** 2 + X[:, 1] ** 2) / X[:, 2] ** 2)
        vig = vig * (1.0 + r2) ** (-0.5 * params.camera_cos_power)
    geo = np.where(ok, np.maximum(cos, 1e-6) * vig * (d_ref / np.maximum(d, 1e-9)) ** 2, 1.0)
    albedo = (signal / geo[:, None]).astype(np.float32)
    albedo[~ok] = np.nan
    albedo[ok] = np.maximum(albedo[ok], 0.0)
    weight = np.where(ok, np.clip(cos, 0.0, 1.0), 0.0).astype(np.float32)
    counts = {name: int(np.count_nonzero(reason == i)) for i, name in enumerate(REASONS)}
    share = counts["ok"] / max(1, nrows)
    trusted = share >= params.min_valid_share
    stats = {
        "samples": nrows,
        "valid": counts["ok"],
        "valid_share": round(share, 4),
        "masked": {k: v for k, v in counts.items() if k != "ok"},
        "reference_distance": round(d_ref, 4),
        "clipped_above_1": int(np.count_nonzero(np.nan_to_num(albedo, nan=0.0).max(axis=1) > 1.0)),
        "response": params.response.kind,
        "vignetting": list(params.vignetting),
        "projector_cos_power": params.projector_cos_power,
        "camera_cos_power": params.camera_cos_power,
        "trusted": trusted,
    }
    if not trusted:
        worst = max((k for k in counts if k != "ok"), key=lambda k: counts[k])
        stats["fallback"] = (f"only {share:.1%} of the samples give an albedo (most are {worst}): "
                             "the shaded colour stands in for it")
        log.warning("albedo: %s", stats["fallback"])
    return SampleAlbedo(albedo=albedo, weight=weight, reason=reason, stats=stats)


def smooth_normals(xyz: np.ndarray, pixel: np.ndarray, shape: tuple[int, int], radius: int = 4) -> np.ndarray:
    """Normals of a view's points from a plane fitted to the points in a (2r+1)^2 pixel window.

    The triangulation's normals come from the 8 nearest pixels, whose depth noise tilts them by
    tens of degrees at the sample spacing; dividing by the projector's cosine needs them far
    steadier. The window's moments are box-filtered over the valid pixels (normalised
    convolution) and the normal is the covariance's least eigenvector, turned towards the camera.

    xyz : (N, 3) points, camera frame; pixel : (N, 2) int camera pixel (x, y); shape : (H, W).
    Returns (N, 3) float32 unit normals (the window's few-point fits fall back to the input's
    orientation where fewer than 6 points are in the window: NaN then).
    """
    import cv2

    h, w = shape
    X = np.asarray(xyz, np.float64)
    # Centred on the view's mean so that the moments keep their precision in float64 sums.
    X = X - X.mean(axis=0) if len(X) else X
    flat = pixel[:, 1].astype(np.int64) * w + pixel[:, 0]
    k = (2 * radius + 1, 2 * radius + 1)
    valid = np.zeros(h * w, np.float64)
    valid[flat] = 1.0

    def box(values: np.ndarray) -> np.ndarray:
        img = np.zeros(h * w, np.float64)
        img[flat] = values
        return cv2.boxFilter(img.reshape(h, w), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT).ravel()[flat]

    cnt = np.maximum(box(np.ones(len(X))), 1.0)
    mean = np.stack([box(X[:, i]) for i in range(3)], axis=1) / cnt[:, None]
    cov = np.empty((len(X), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = box(X[:, i] * X[:, j]) / cnt - mean[:, i] * mean[:, j]
    _, vecs = np.linalg.eigh(cov)
    n = vecs[:, :, 0]
    n[np.einsum("ij,ij->i", n, np.asarray(xyz, np.float64)) > 0] *= -1
    n[cnt < 6] = np.nan
    return n.astype(np.float32)
