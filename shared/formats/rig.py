"""The rig contract: camera and projector intrinsics and their relative pose (``rig.json``).

::

    {"units": "mm",
     "camera":    {"width": W, "height": H, "K": [[3x3]], "dist": [k1, k2, p1, p2, k3]},
     "projector": {"width": W, "height": H, "K": [[3x3]], "dist": [k1, k2, p1, p2, k3]},
     "R": [[3x3]], "T": [3]}

``X_projector = R @ X_camera + T`` (OpenCV ``stereoCalibrate`` convention); ``T`` and all
reconstructed points are in ``units``; pixel coordinates follow OpenCV (the centre of the
top-left pixel is (0, 0)). Distortion is OpenCV's five-parameter model.

Optional ``"radiometry"`` (what :mod:`shared.scan.albedo` divides out to recover the object's own
colour): ``camera_response`` (``"srgb"``, the default; ``"linear"``; ``"gamma:G"``; or 256
non-decreasing numbers, a measured curve from 8-bit code to linear light),
``camera_falloff_cos_power`` and ``projector_falloff_cos_power`` (natural falloff of each lens as
a power of the off-axis cosine, 0 to 8), ``projector_vignetting`` (up to 4 coefficients of
``1 + k1 r^2 + k2 r^4 ...`` in the projector's normalised radius).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError
from shared.core.files import read_json, write_json_atomic
from shared.core.jsonsafe import loads_bounded


@dataclass(frozen=True)
class Device:
    """A pinhole device (camera, or projector as an inverse camera) with OpenCV distortion."""

    width: int
    height: int
    K: np.ndarray  # (3, 3) float64
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # (5,) float64

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def to_json(self) -> dict[str, Any]:
        return {
            "width": int(self.width),
            "height": int(self.height),
            "K": np.asarray(self.K, dtype=float).tolist(),
            "dist": np.asarray(self.dist, dtype=float).ravel().tolist(),
        }


@dataclass(frozen=True)
class Rig:
    """A calibrated camera-projector pair. ``X_projector = R @ X_camera + T``."""

    camera: Device
    projector: Device
    R: np.ndarray  # (3, 3) float64, rotation camera -> projector
    T: np.ndarray  # (3,) float64, in ``units``
    units: str = "mm"
    radiometry: dict[str, Any] | None = None  # see the module docstring

    @property
    def baseline(self) -> float:
        """Distance between the two optical centres, in ``units``."""
        return float(np.linalg.norm(self.R.T @ self.T))

    def to_json(self) -> dict[str, Any]:
        return {
            "units": self.units,
            "camera": self.camera.to_json(),
            "projector": self.projector.to_json(),
            "R": np.asarray(self.R, dtype=float).tolist(),
            "T": np.asarray(self.T, dtype=float).ravel().tolist(),
            **({"radiometry": dict(self.radiometry)} if self.radiometry else {}),
        }


#: The keys of each object of the contract; any other is an error naming it. "radiometry" (the
#: camera response and fall-off, written by the simulator and calibration) is validated by its own
#: parser (issue 23's branch adds it).
_TOP_KEYS = ("units", "camera", "projector", "R", "T", "radiometry")
_DEVICE_KEYS = ("width", "height", "K", "dist")
#: Largest device side in pixels, and the range of focal lengths (pixels) and principal points
#: (within this many image sides of the image) a real lens gives: a focal length of 1e308 parses
#: but overflows the triangulation and fails only at export.
MAX_DEVICE_SIDE = 65536
MAX_FOCAL_PX = 1e6
MAX_PRINCIPAL_SIDES = 4.0
#: Largest magnitude of a distortion coefficient (OpenCV's rational terms reach hundreds).
MAX_DISTORTION = 1e4
#: Lengths of OpenCV's distortion vectors (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]).
DIST_LENGTHS = (4, 5, 8, 12, 14)
#: Largest camera-projector distance in the rig's units (10 km in mm).
MAX_BASELINE = 1e7
#: Largest rig file accepted.
MAX_RIG_BYTES = 1 << 20


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _no_unknown(obj: dict[str, Any], known: tuple[str, ...], where: Path | str, parent: str | None) -> None:
    for k in obj:
        if k not in known:
            at = f'in "{parent}"' if parent else "at the top level"
            raise InputError(where, f'unknown field {_short(k)} {at} (allowed: {", ".join(known)})')


def _matrix(value: Any, shape: tuple[int, ...], where: Path | str, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer past float's range
        raise InputError(where, f'field "{name}" must be numbers of shape {shape}') from None
    if arr.shape != shape:
        raise InputError(where, f'field "{name}" has shape {arr.shape}, expected {shape}')
    if not np.all(np.isfinite(arr)):
        raise InputError(where, f'field "{name}" holds NaN or infinite values')
    return arr


def _floats(values: list[Any]) -> np.ndarray | None:
    """``values`` as float64 (n,), or None when one is an integer past float's range."""
    try:
        return np.asarray(values, dtype=np.float64).ravel()
    except OverflowError:
        return None


def _device(doc: Any, where: Path | str, name: str) -> Device:
    if not isinstance(doc, dict):
        raise InputError(where, f'field "{name}" must be an object')
    _no_unknown(doc, _DEVICE_KEYS, where, name)
    for key in ("width", "height"):
        v = doc.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or not 2 <= v <= MAX_DEVICE_SIDE:
            raise InputError(where, f'field "{name}.{key}" must be an integer in 2..{MAX_DEVICE_SIDE}, got {_short(v)}')
    if "K" not in doc:
        raise InputError(where, f'missing field "{name}.K"')
    K = _matrix(doc["K"], (3, 3), where, f"{name}.K")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0:
        raise InputError(where, f'field "{name}.K" is not a camera matrix [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0')
    if max(K[0, 0], K[1, 1], abs(K[0, 1])) > MAX_FOCAL_PX:
        raise InputError(where, f'field "{name}.K": focal length and skew must be at most {MAX_FOCAL_PX:g} pixels, '
                                f"got fx {K[0, 0]:.6g}, fy {K[1, 1]:.6g}, s {K[0, 1]:.6g}")
    side = max(doc["width"], doc["height"])
    if max(abs(K[0, 2]), abs(K[1, 2])) > MAX_PRINCIPAL_SIDES * side:
        raise InputError(where, f'field "{name}.K": principal point ({K[0, 2]:.6g}, {K[1, 2]:.6g}) lies more than '
                                f"{MAX_PRINCIPAL_SIDES:g} image sides from the image")
    dist_raw = doc.get("dist", [0, 0, 0, 0, 0])
    dist = _floats(dist_raw) if isinstance(dist_raw, list) and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in dist_raw) else None
    if dist is None or dist.size not in DIST_LENGTHS or not np.all(np.isfinite(dist)):
        raise InputError(where, f'field "{name}.dist" must be OpenCV distortion coefficients [k1, k2, p1, p2, k3]')
    if np.abs(dist).max(initial=0.0) > MAX_DISTORTION:
        raise InputError(where, f'field "{name}.dist": coefficients must be at most {MAX_DISTORTION:g} in magnitude')
    if dist.size == 4:
        dist = np.append(dist, 0.0)
    return Device(width=doc["width"], height=doc["height"], K=K, dist=dist)


def _radiometry(doc: Any, where: Path | str) -> dict[str, Any]:
    if not isinstance(doc, dict):
        raise InputError(where, 'field "radiometry" must be an object')
    out: dict[str, Any] = {}
    for key, value in doc.items():
        name = f"radiometry.{key}"
        if key == "camera_response":
            if isinstance(value, str):
                ok = value in ("srgb", "linear")
                if value.startswith("gamma:"):
                    try:
                        ok = 0.2 <= float(value[6:]) <= 5.0
                    except ValueError:
                        ok = False
                if not ok:
                    raise InputError(where, f'field "{name}" must be "srgb", "linear", "gamma:G" (G in [0.2, 5]) '
                                            "or 256 numbers")
                out[key] = value
            else:
                curve = _matrix(value, (256,), where, name)
                if np.any(np.diff(curve) < 0) or curve[-1] <= curve[0]:
                    raise InputError(where, f'field "{name}" must be 256 non-decreasing numbers, the last above the first')
                out[key] = curve.tolist()
        elif key in ("camera_falloff_cos_power", "projector_falloff_cos_power"):
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value <= 8:
                raise InputError(where, f'field "{name}" must be a number in [0, 8], got {value!r}')
            out[key] = float(value)
        elif key == "projector_vignetting":
            if not isinstance(value, list) or len(value) > 4:
                raise InputError(where, f'field "{name}" must be a list of at most 4 numbers')
            out[key] = _matrix(value, (len(value),), where, name).tolist()
        else:
            raise InputError(where, f'unknown field "{name}"')
    return out


def parse_rig(doc: Any, where: Path | str = "rig.json") -> Rig:
    """Validate a rig document; raises :class:`InputError` naming ``where`` and the field."""
    if not isinstance(doc, dict):
        raise InputError(where, "must be a JSON object")
    _no_unknown(doc, _TOP_KEYS, where, None)
    units = doc.get("units", "mm")
    if not isinstance(units, str) or not units or len(units) > 16 or not (units.isascii() and units.isprintable()):
        # printable ASCII: units go into every output's PLY header comments and paradata
        raise InputError(where, f'field "units" must be a string such as "mm", got {_short(units)}')
    for key in ("camera", "projector", "R", "T"):
        if key not in doc:
            raise InputError(where, f'missing field "{key}"')
    R = _matrix(doc["R"], (3, 3), where, "R")
    # a rotation's entries lie in [-1, 1]: larger ones are refused before R @ R.T overflows
    if np.abs(R).max() > 1.0 + 1e-6 or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError(where, 'field "R" is not a rotation matrix')
    T = _matrix(doc["T"], (3,), where, "T")
    if np.abs(T).max() > MAX_BASELINE:  # before the norm, which would overflow
        raise InputError(where, f'field "T": a baseline of {np.abs(T).max():.6g} {units} or more is more than {MAX_BASELINE:g}')
    if np.linalg.norm(T) == 0:
        raise InputError(where, 'field "T" is zero: camera and projector cannot share an optical centre')
    return Rig(
        camera=_device(doc["camera"], where, "camera"),
        projector=_device(doc["projector"], where, "projector"),
        R=R,
        T=T,
        units=units,
        radiometry=_radiometry(doc["radiometry"], where) if "radiometry" in doc else None,
    )


def load_rig(path: str | os.PathLike[str]) -> Rig:
    """Read and validate ``rig.json`` (bounded, without blocking: :func:`shared.core.files.read_json`)."""
    p = Path(path)
    doc = read_json(p, "rig file not found")
    return parse_rig(doc, p)


def parse_rig_bytes(data: bytes, where: str) -> Rig:
    """A rig from the bytes of an uploaded file: :func:`~shared.core.jsonsafe.loads_bounded` (more
    than :data:`MAX_RIG_BYTES` is "too large", never cut and called malformed), then :func:`parse_rig`."""
    return parse_rig(loads_bounded(data, where, max_bytes=MAX_RIG_BYTES), where)


def save_rig(rig: Rig, path: str | os.PathLike[str]) -> Path:
    """Write ``rig.json`` atomically."""
    p = Path(path)
    write_json_atomic(p, rig.to_json())
    return p


def check_rig_matches(rig: Rig, camera_size: tuple[int, int], projector_size: tuple[int, int], where: Path | str) -> None:
    """Raise :class:`InputError` if the rig's device sizes (width, height) disagree with the capture's."""
    if (rig.camera.width, rig.camera.height) != tuple(camera_size):
        raise InputError(
            where,
            f"rig camera is {rig.camera.width}x{rig.camera.height} but the images are {camera_size[0]}x{camera_size[1]}",
        )
    if (rig.projector.width, rig.projector.height) != tuple(projector_size):
        raise InputError(
            where,
            f"rig projector is {rig.projector.width}x{rig.projector.height} but the capture's projector is "
            f"{projector_size[0]}x{projector_size[1]}",
        )
