"""Camera paths for preview videos: an arc around the scanner's viewpoint, an orbit around the
object, a dolly through it, or keyframes from a JSON file.

In: the scene's tight bounding box (world units, e.g. mm), a frame count and, for framing, a
sample of the points. Out: one :class:`CameraPose` a frame (eye, target, up, vertical field
of view in degrees).

Graylight clouds live in the scanner camera's frame (x right, y down, z forward, the scanner
at the origin), so the default "up" is -y and the default views look along +z, as the
scanner did. ``"auto"`` (the default) picks the arc for a single-view scan, whose back is
empty (:func:`is_single_view`: along the scanner's rays the cloud holds one surface), and the
full orbit for a model merged from views all around. Both frame the object: pose by pose, the
camera is placed where every sampled point (bar the 0.2 % farthest out on each axis, stray
points) projects inside :data:`FILL` of the frame, as large as it fits, centred.

A path file is JSON::

    {"fov": 50, "up": [0, -1, 0],
     "keyframes": [{"t": 0.0, "eye": [x, y, z], "target": [x, y, z]}, ...]}

``t`` (optional, increasing, 0..1) places a keyframe in time; without it keyframes are evenly
spaced. Poses between keyframes are interpolated linearly. A path whose eye wanders farther
than :data:`MAX_DISTANCE_FACTOR` scene diagonals from the scene is rejected (InputError).
A keyframe whose target is its eye looks at the scene's centre.

Only the CLI reads a file (``--path FILE``, a local user's own; bounded and without blocking,
:func:`read_path_file`). A job names no file: its keyframes come inline in
``params.preview.camera`` (``fov`` and at most :data:`MAX_INLINE_KEYFRAMES` keyframes of ``eye``
and ``target``), validated at intake by :func:`parse_camera_doc`, so a path on the worker (a
FIFO, ``/dev/zero``, another tenant's file) is never opened.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError
from shared.core.jsonsafe import finite_number, read_json_bounded

DEFAULT_UP = (0.0, -1.0, 0.0)
DEFAULT_FOV = 50.0
#: Fraction of the frame's half-width and half-height the framed object reaches at most.
FILL = 0.9
#: The arc's swing around the object, left to right (degrees), and its elevation swing.
ARC_SWEEP = 70.0
ARC_ELEVATION = 12.0
#: Where a Graylight cloud's scanner is: the origin of the camera frame.
SCANNER = (0.0, 0.0, 0.0)
#: How far (in scene diagonals, from the box) a path file's eye may go.
MAX_DISTANCE_FACTOR = 5.0
#: Keyframes a path may hold: a file, and the inline form of a job's parameters (whose JSON
#: must stay under the parameters' 16 KiB).
MAX_KEYFRAMES = 10000
MAX_INLINE_KEYFRAMES = 64
#: Largest coordinate magnitude of an eye, a target or ``up``.
MAX_COORDINATE = 1e9
#: The path names a job may give in ``params.preview.path`` (a keyframe path goes inline in
#: ``params.preview.camera``: a job never names a file on the worker).
NAMED_PATHS = ("auto", "arc", "orbit", "dolly")


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


def core_points(points: np.ndarray, trim: float = 0.002) -> np.ndarray:
    """The points bar the ``trim`` fraction farthest out at either end of each axis (stray
    points that would shrink the object in the frame). ``points`` (N, 3); returns (M, 3) float64."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if p.shape[0] < 50:
        return p
    lo = np.quantile(p, trim, axis=0)
    hi = np.quantile(p, 1 - trim, axis=0)
    return p[np.all((p >= lo) & (p <= hi), axis=1)]


def _basis(forward: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image right and image up (unit) of a camera looking along ``forward``."""
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, [1.0, 0.0, 0.0] if abs(forward[0]) < 0.9 else [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return right, np.cross(right, forward)


def fit_view(
    points: np.ndarray,
    centre: np.ndarray,
    direction: np.ndarray,
    up=DEFAULT_UP,
    fov_y: float = DEFAULT_FOV,
    aspect: float = 16 / 9,
    fill: float = FILL,
) -> tuple[np.ndarray, np.ndarray]:
    """Eye and target of the camera that looks along ``-direction`` (unit, (3,): from the
    object towards the eye) and sees ``points`` (N, 3) as large as they fit: within ``fill`` of
    the frame's half-width and half-height, centred on screen. ``aspect`` = width / height.

    With the camera's right/up offsets ``a``, ``b`` from ``centre`` and distance ``t``, a point
    at (x, y, z) (camera axes, relative to ``centre``) projects to (x - a) / (t + z); both sides
    within ``tan(fov / 2) * fill`` is linear in (a, t), and the smallest ``t`` is exact:
    ``t = (P - Q) / 2 tan``, ``a = (P + Q) / 2`` with ``P = max(x - tan z)``, ``Q = min(x + tan z)``.
    """
    c = np.asarray(centre, np.float64)
    p = np.asarray(points, np.float64) - c
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    fwd = -d
    right, cam_up = _basis(fwd, up)
    if p.shape[0] == 0:
        return c + d, c.copy()
    z = p @ fwd
    ty = math.tan(math.radians(fov_y) / 2) * fill
    tx = ty * aspect
    out = []
    for axis, t in ((right, tx), (cam_up, ty)):
        x = p @ axis
        P, Q = float(np.max(x - t * z)), float(np.min(x + t * z))
        out.append(((P - Q) / (2 * t), (P + Q) / 2))
    dist = max(out[0][0], out[1][0], 1e-6 * (1.0 + float(np.abs(p).max())))
    # Keep the nearest point in front of the camera whatever the object's shape.
    dist = max(dist, float(-z.min()) * 1.05 + 1e-9)
    target = c + out[0][1] * right + out[1][1] * cam_up
    return target + dist * d, target


def is_single_view(points: np.ndarray, viewpoint=SCANNER, bins: int = 48, spread: float = 0.15) -> bool:
    """Whether a cloud is one view seen from ``viewpoint``: along the viewpoint's rays it holds
    one surface (a range image's points), not a front and a back.

    The rays are binned in a ``bins`` x ``bins`` grid over the cloud's angular extent; a bin
    whose depths spread over more than ``spread`` of the cloud's depth extent holds two
    surfaces. A single view has such bins only along occlusion edges; a model merged from
    views around the object has them wherever its back lies behind its front. ``points``
    (N, 3) world; False when the viewpoint lies inside the cloud's bounds.
    """
    p = np.asarray(points, np.float64) - np.asarray(viewpoint, np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    if p.shape[0] < 100:
        return True
    lo, hi = p.min(axis=0), p.max(axis=0)
    if np.all((lo < 0) & (hi > 0)):
        return False
    centre = core_points(p).mean(axis=0)
    fwd = centre / max(np.linalg.norm(centre), 1e-12)
    right, cam_up = _basis(fwd, np.array(DEFAULT_UP))
    depth = p @ fwd
    front = depth > 1e-9
    if front.mean() < 0.99:  # points beside or behind the viewpoint: not what it saw
        return False
    a = np.arctan2(p[front] @ right, depth[front])
    b = np.arctan2(p[front] @ cam_up, depth[front])
    r = np.linalg.norm(p[front], axis=1)
    ia = np.minimum(((a - a.min()) / max(np.ptp(a), 1e-12) * bins).astype(np.int64), bins - 1)
    ib = np.minimum(((b - b.min()) / max(np.ptp(b), 1e-12) * bins).astype(np.int64), bins - 1)
    cell = ia * bins + ib
    rmin = np.full(bins * bins, np.inf)
    rmax = np.full(bins * bins, -np.inf)
    np.minimum.at(rmin, cell, r)
    np.maximum.at(rmax, cell, r)
    used = np.isfinite(rmin)
    extent = max(float(np.ptp(r)), 1e-12)
    doubled = (rmax[used] - rmin[used]) > spread * extent
    return bool(doubled.mean() < 0.2)


def arc_path(
    points: np.ndarray,
    frames: int,
    *,
    viewpoint=SCANNER,
    up=DEFAULT_UP,
    fov_y: float = DEFAULT_FOV,
    aspect: float = 16 / 9,
    sweep_deg: float = ARC_SWEEP,
    elevation_deg: float = ARC_ELEVATION,
) -> list[CameraPose]:
    """An arc around the object that stays on the scanner's side: starting from the scanner's
    direction, the eye swings ``sweep_deg / 2`` to one side, up by ``elevation_deg`` over the
    middle, to the other side and back (a closed loop, an ellipse in yaw and pitch), always looking at the object's centre, at the distance
    that frames the object from that pose (:func:`fit_view`). ``points`` (N, 3) world:
    a sample of the cloud (the framing uses :func:`core_points`)."""
    core = core_points(points)
    if core.shape[0] == 0:
        raise InputError("points", "the scene holds no finite points to frame")
    lo, hi = core.min(axis=0), core.max(axis=0)
    centre = (lo + hi) / 2
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    home = np.asarray(viewpoint, np.float64) - centre
    if np.linalg.norm(home) < 1e-9:
        home = np.array([0.0, 0.0, -1.0])
    home /= np.linalg.norm(home)
    side = np.cross(up, home)
    if np.linalg.norm(side) < 1e-6:  # looking straight down the up axis
        side = np.cross(home, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    lift = np.cross(home, side)
    lift *= np.sign(lift @ up) or 1.0
    dirs = []
    for k in range(frames):
        phase = 2 * math.pi * k / max(frames, 1)
        yaw = math.radians(sweep_deg / 2) * math.sin(phase)
        pitch = math.radians(elevation_deg / 2) * (1 - math.cos(phase))  # an ellipse: up and back
        d = math.cos(pitch) * (math.cos(yaw) * home + math.sin(yaw) * side) + math.sin(pitch) * lift
        dirs.append(d / np.linalg.norm(d))
    return _framed(core, centre, dirs, up, fov_y, aspect)


def _framed(core, centre, dirs, up, fov_y, aspect) -> list[CameraPose]:
    """Poses looking at ``centre`` from each direction, each at its own framing distance (the
    distances change smoothly along a smooth path, so the object keeps its size on screen)."""
    poses = []
    for d in dirs:
        eye, target = fit_view(core, centre, d, up, fov_y, aspect)
        poses.append(CameraPose(eye=eye, target=target, up=up, fov_y=fov_y))
    return poses


def orbit_path(
    box_min,
    box_max,
    frames: int,
    *,
    up=DEFAULT_UP,
    fov_y: float = DEFAULT_FOV,
    elevation_deg: float = 20.0,
    points: np.ndarray | None = None,
    aspect: float = 16 / 9,
) -> list[CameraPose]:
    """A full turn around the box's vertical axis, starting on the -z side (the scanner's view).

    With ``points`` (N, 3), a sample of the cloud, the orbit turns around their centre, each
    pose at the distance that frames them (:func:`fit_view`); without, at one distance
    that fits the box's bounding sphere."""
    lo, hi, diag = _box(box_min, box_max)
    centre = (lo + hi) / 2
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    dist = 0.5 * diag / math.tan(math.radians(fov_y) / 2) * 1.05
    core = core_points(points) if points is not None else np.empty((0, 3))
    if core.shape[0]:
        centre = (core.min(axis=0) + core.max(axis=0)) / 2
    # Horizontal frame: the start direction is -z with its component along ``up`` removed.
    minus_z = np.array([0.0, 0.0, -1.0])
    start = minus_z - up * float(minus_z @ up)
    if np.linalg.norm(start) < 1e-6:
        start = np.array([1.0, 0.0, 0.0])
    start /= np.linalg.norm(start)
    side = np.cross(up, start)
    el = math.radians(elevation_deg)
    dirs = []
    for k in range(frames):
        a = 2 * math.pi * k / max(frames, 1)
        horiz = math.cos(a) * start + math.sin(a) * side
        dirs.append(math.cos(el) * horiz + math.sin(el) * up)
    if core.shape[0]:
        return _framed(core, centre, dirs, up, fov_y, aspect)
    return [CameraPose(eye=centre + dist * d, target=centre.copy(), up=up, fov_y=fov_y) for d in dirs]


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
    ok = isinstance(value, list) and len(value) == 3 and all(finite_number(v) for v in value)
    v = np.asarray(value, np.float64) if ok else None
    if v is None or np.abs(v).max() > MAX_COORDINATE:
        raise InputError(where, f"must be a list of 3 finite numbers of magnitude at most {MAX_COORDINATE:g}")
    return v


@dataclass(frozen=True)
class KeyframePath:
    """A validated keyframe camera path: ``eyes``/``targets`` (K, 3) float64 world, ``times`` (K,)
    increasing, ``up`` (3,), ``fov_y`` degrees. A keyframe whose target is its eye has NaN targets:
    it looks at the scene's centre (known only when rendering)."""

    eyes: np.ndarray
    targets: np.ndarray
    times: np.ndarray
    up: np.ndarray
    fov_y: float


def _unknown(obj: dict, known: tuple[str, ...], where: str) -> None:
    for k in obj:
        if k not in known:
            raise InputError(f"{where}.{str(k)[:40]}", f"unknown field (allowed: {', '.join(known)})")


def parse_camera_doc(doc: Any, where: str, *, inline: bool = False) -> KeyframePath:
    """Validate a keyframe camera path document without the scene; :class:`InputError` names
    ``where`` and the field. ``inline`` is the job parameter's form (``params.preview.camera``):
    ``fov`` and at most :data:`MAX_INLINE_KEYFRAMES` keyframes of ``eye`` and ``target``, evenly
    spaced, up the scanner's; every value its JSON Schema allows is accepted. A file (the CLI's
    ``--path FILE``) may also give ``up`` and each keyframe's time ``t``."""
    keys = ("fov", "keyframes") if inline else ("fov", "up", "keyframes")
    kf_keys = ("eye", "target") if inline else ("t", "eye", "target")
    limit = MAX_INLINE_KEYFRAMES if inline else MAX_KEYFRAMES
    if not isinstance(doc, dict) or not isinstance(doc.get("keyframes"), list) or not doc["keyframes"]:
        raise InputError(where, "camera path needs a non-empty 'keyframes' list")
    _unknown(doc, keys, where)
    fov = doc.get("fov", DEFAULT_FOV)
    if not isinstance(fov, int | float) or isinstance(fov, bool) or not 1 <= fov <= 170:
        raise InputError(f"{where}.fov", f"must be a number of degrees in [1, 170], got {str(fov)[:40]}")
    up = _vec3(doc.get("up", list(DEFAULT_UP)), f"{where}.up")
    if np.linalg.norm(up) == 0:
        raise InputError(f"{where}.up", "must not be zero")
    frames = doc["keyframes"]
    if len(frames) > limit:
        raise InputError(f"{where}.keyframes", f"{len(frames)} keyframes, at most {limit}")
    eyes, targets, times = [], [], []
    for i, kf in enumerate(frames):
        at = f"{where}.keyframes[{i}]"
        if not isinstance(kf, dict) or "eye" not in kf or "target" not in kf:
            raise InputError(at, "must be an object with 'eye' and 'target'")
        _unknown(kf, kf_keys, at)
        eyes.append(_vec3(kf["eye"], f"{at}.eye"))
        target = _vec3(kf["target"], f"{at}.target")
        targets.append(np.full(3, np.nan) if np.allclose(eyes[-1], target) else target)
        t = kf.get("t", i / max(len(frames) - 1, 1))
        if not finite_number(t):
            raise InputError(f"{at}.t", f"must be a finite number, got {str(t)[:40]}")
        times.append(t)
    t = np.asarray(times, np.float64)
    if not np.isfinite(t).all() or np.any(np.diff(t) < 0):
        raise InputError(f"{where}.keyframes", "times 't' must be finite and increasing")
    return KeyframePath(eyes=np.stack(eyes), targets=np.stack(targets), times=t, up=up, fov_y=float(fov))


def read_path_file(path: str | Path) -> dict:
    """A local keyframe file's JSON (the CLI's ``--path FILE``): read without blocking, bounded in
    size, depth and number length (:func:`shared.core.jsonsafe.read_json_bounded`)."""
    return read_json_bounded(Path(path), str(path), missing="camera path file not found")


def poses_from_keyframes(kp: KeyframePath, frames: int, box_min, box_max, where: str) -> list[CameraPose]:
    """``frames`` poses interpolated linearly along ``kp``; :class:`InputError` naming ``where``
    when an eye wanders more than :data:`MAX_DISTANCE_FACTOR` scene diagonals from the scene."""
    lo, hi, diag = _box(box_min, box_max)
    limit = MAX_DISTANCE_FACTOR * diag
    for i, e in enumerate(kp.eyes):
        outside = float(np.linalg.norm(np.maximum(0, np.maximum(lo - e, e - hi))))
        if outside > limit:
            raise InputError(
                f"{where}.keyframes[{i}].eye",
                f"is {outside:.4g} units outside the scene's bounds (allowed {limit:.4g}: {MAX_DISTANCE_FACTOR:g} diagonals)",
            )
    centre = (lo + hi) / 2
    E = kp.eyes
    # A keyframe whose target was its eye looks at the scene's centre (along +z, as the scanner
    # did, when it stands there itself).
    T = np.where(np.isnan(kp.targets), centre, kp.targets)
    same = np.all(np.isclose(E, T), axis=1)
    T[same] = E[same] + np.array([0.0, 0.0, diag])
    t = kp.times
    span = t[-1] - t[0]
    poses = []
    for k in range(frames):
        s = t[0] + span * k / max(frames - 1, 1) if span > 0 else t[0]
        e = np.array([np.interp(s, t, E[:, a]) for a in range(3)])
        g = np.array([np.interp(s, t, T[:, a]) for a in range(3)])
        if np.allclose(e, g):
            g = e + (T[-1] - E[-1])
        poses.append(CameraPose(eye=e, target=g, up=kp.up, fov_y=kp.fov_y))
    return poses


def load_path_file(path: Path, frames: int, box_min, box_max) -> list[CameraPose]:
    """Poses from a local JSON keyframe file (format in the module docstring); InputError when
    the file is malformed or its eye leaves the scene by far."""
    where = str(path)
    return poses_from_keyframes(parse_camera_doc(read_path_file(path), where), frames, box_min, box_max, where)


def make_path(
    spec: str | Path,
    box_min,
    box_max,
    frames: int,
    *,
    points: np.ndarray | None = None,
    aspect: float = 16 / 9,
    camera: KeyframePath | None = None,
    camera_where: str = "params.preview.camera",
    up=DEFAULT_UP,
) -> list[CameraPose]:
    """``"auto"``, ``"arc"``, ``"orbit"``, ``"dolly"`` or the path of a local JSON keyframe file;
    ``camera`` (validated keyframes, :func:`parse_camera_doc`), when given, wins, and its errors
    name ``camera_where``.

    ``points`` (N, 3) world, a sample of the cloud, frames the arc and the orbit and lets
    ``"auto"`` choose between them (:func:`is_single_view`); ``aspect`` = width / height.
    Without points, ``"auto"`` and ``"arc"`` use the box's corners as the sample."""
    if camera is not None:
        return poses_from_keyframes(camera, frames, box_min, box_max, camera_where)
    name = str(spec)
    if name in ("auto", "arc") and points is None:
        lo, hi = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
        points = np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi) for c in (lo, hi)])
    if name == "auto":
        name = "arc" if is_single_view(points) else "orbit"
    if name == "arc":
        return arc_path(points, frames, aspect=aspect)
    if name == "orbit":
        # ``up``: the object's up (a turntable's axis), which the orbit turns around.
        return orbit_path(box_min, box_max, frames, points=points, aspect=aspect, up=up)
    if str(spec) == "dolly":
        return dolly_path(box_min, box_max, frames)
    return load_path_file(Path(spec), frames, box_min, box_max)
