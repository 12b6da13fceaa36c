"""Camera paths for preview videos: an orbit around a scene's bounds, a dolly through them, or
keyframes from a JSON file.

In: the scene's tight bounding box (world units, e.g. mm), a frame count. Out: one
:class:`CameraPose` a frame (eye, target, up, vertical field of view in degrees).

Graylight clouds live in the scanner camera's frame (x right, y down, z forward), so the
default "up" is -y and the default views look along +z, as the scanner did.

A path file is JSON::

    {"fov": 50, "up": [0, -1, 0],
     "keyframes": [{"t": 0.0, "eye": [x, y, z], "target": [x, y, z]}, ...]}

``t`` (optional, increasing, 0..1) places a keyframe in time; without it keyframes are evenly
spaced. Poses between keyframes are interpolated linearly. A path whose eye wanders farther
than :data:`MAX_DISTANCE_FACTOR` scene diagonals from the scene is rejected (InputError).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.core.errors import InputError

DEFAULT_UP = (0.0, -1.0, 0.0)
DEFAULT_FOV = 50.0
#: How far (in scene diagonals, from the box) a path file's eye may go.
MAX_DISTANCE_FACTOR = 5.0


@dataclass(frozen=True)
class CameraPose:
    """Where a frame's camera is: ``eye`` and ``target`` (3,) world, ``up`` (3,), ``fov_y`` degrees."""

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_y: float


def _box(box_min, box_max) -> tuple[np.ndarray, np.ndarray, float]:
    lo = np.asarray(box_min, np.float64)
    hi = np.asarray(box_max, np.float64)
    diag = float(np.linalg.norm(hi - lo))
    return lo, hi, diag if diag > 0 else 1.0


def orbit_path(
    box_min, box_max, frames: int, *, up=DEFAULT_UP, fov_y: float = DEFAULT_FOV, elevation_deg: float = 20.0
) -> list[CameraPose]:
    """A full turn around the box's vertical axis, starting on the -z side (the scanner's view),
    at a distance that fits the whole box in view."""
    lo, hi, diag = _box(box_min, box_max)
    centre = (lo + hi) / 2
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    dist = 0.5 * diag / math.tan(math.radians(fov_y) / 2) * 1.05
    # Horizontal frame: the start direction is -z with its component along ``up`` removed.
    minus_z = np.array([0.0, 0.0, -1.0])
    start = minus_z - up * float(minus_z @ up)
    if np.linalg.norm(start) < 1e-6:
        start = np.array([1.0, 0.0, 0.0])
    start /= np.linalg.norm(start)
    side = np.cross(up, start)
    el = math.radians(elevation_deg)
    poses = []
    for k in range(frames):
        a = 2 * math.pi * k / max(frames, 1)
        horiz = math.cos(a) * start + math.sin(a) * side
        eye = centre + dist * (math.cos(el) * horiz + math.sin(el) * up)
        poses.append(CameraPose(eye=eye, target=centre.copy(), up=up, fov_y=fov_y))
    return poses


def dolly_path(
    box_min, box_max, frames: int, *, up=DEFAULT_UP, fov_y: float = DEFAULT_FOV
) -> list[CameraPose]:
    """A straight move along +z from in front of the box into its middle, looking ahead."""
    lo, hi, diag = _box(box_min, box_max)
    centre = (lo + hi) / 2
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    start = np.array([centre[0], centre[1], lo[2] - 0.6 * diag])
    end = np.array([centre[0], centre[1], centre[2]])
    poses = []
    for k in range(frames):
        s = k / max(frames - 1, 1)
        s = s * s * (3 - 2 * s)  # ease in and out
        eye = start + s * (end - start)
        poses.append(CameraPose(eye=eye, target=eye + np.array([0.0, 0.0, diag]), up=up, fov_y=fov_y))
    return poses


def _vec3(value, where: str) -> np.ndarray:
    try:
        v = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise InputError(where, "must be a list of 3 numbers") from None
    if v.shape != (3,) or not np.isfinite(v).all():
        raise InputError(where, "must be a list of 3 finite numbers")
    return v


def load_path_file(path: Path, frames: int, box_min, box_max) -> list[CameraPose]:
    """Poses from a JSON keyframe file (format in the module docstring); InputError when the
    file is malformed or its eye leaves the scene by far."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "camera path file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"camera path is not valid JSON: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("keyframes"), list) or not doc["keyframes"]:
        raise InputError(path, "camera path needs a non-empty 'keyframes' list")
    fov = doc.get("fov", DEFAULT_FOV)
    if not isinstance(fov, int | float) or not 1 <= fov <= 170:
        raise InputError(f"{path}: fov", f"must be a number of degrees in [1, 170], got {fov!r}")
    up = _vec3(doc.get("up", DEFAULT_UP), f"{path}: up")
    if np.linalg.norm(up) == 0:
        raise InputError(f"{path}: up", "must not be zero")
    keys = doc["keyframes"]
    eyes, targets, times = [], [], []
    for i, kf in enumerate(keys):
        if not isinstance(kf, dict):
            raise InputError(f"{path}: keyframes[{i}]", "must be an object with 'eye' and 'target'")
        eyes.append(_vec3(kf.get("eye"), f"{path}: keyframes[{i}].eye"))
        targets.append(_vec3(kf.get("target"), f"{path}: keyframes[{i}].target"))
        if np.allclose(eyes[-1], targets[-1]):
            raise InputError(f"{path}: keyframes[{i}]", "eye and target coincide")
        times.append(kf.get("t", i / max(len(keys) - 1, 1)))
    t = np.asarray(times, np.float64)
    if not np.isfinite(t).all() or np.any(np.diff(t) < 0):
        raise InputError(f"{path}: keyframes", "times 't' must be finite and increasing")
    lo, hi, diag = _box(box_min, box_max)
    limit = MAX_DISTANCE_FACTOR * diag
    for i, e in enumerate(eyes):
        outside = float(np.linalg.norm(np.maximum(0, np.maximum(lo - e, e - hi))))
        if outside > limit:
            raise InputError(
                f"{path}: keyframes[{i}].eye",
                f"is {outside:.4g} units outside the scene's bounds (allowed {limit:.4g}: {MAX_DISTANCE_FACTOR:g} diagonals)",
            )
    E = np.stack(eyes)
    T = np.stack(targets)
    span = t[-1] - t[0]
    poses = []
    for k in range(frames):
        s = t[0] + span * k / max(frames - 1, 1) if span > 0 else t[0]
        e = np.array([np.interp(s, t, E[:, a]) for a in range(3)])
        g = np.array([np.interp(s, t, T[:, a]) for a in range(3)])
        if np.allclose(e, g):
            g = e + (T[-1] - E[-1])
        poses.append(CameraPose(eye=e, target=g, up=up, fov_y=float(fov)))
    return poses


def make_path(spec: str | Path, box_min, box_max, frames: int) -> list[CameraPose]:
    """``"orbit"``, ``"dolly"`` or the path of a JSON keyframe file."""
    if str(spec) == "orbit":
        return orbit_path(box_min, box_max, frames)
    if str(spec) == "dolly":
        return dolly_path(box_min, box_max, frames)
    return load_path_file(Path(spec), frames, box_min, box_max)
