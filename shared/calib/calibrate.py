"""Camera and projector calibration: intrinsics, distortion and the rig's extrinsics.

In: board corners seen by the camera (pixels) with their board coordinates (the board's
units, usually mm), and for a projector-camera session the Gray-code decode of each pose
(per camera pixel, the projector column and row it sees). Out: a :class:`~shared.formats.rig.Rig`
(``X_projector = R @ X_camera + T``) with per-pose reprojection errors of both devices.

The projector is calibrated as an inverse camera (Moreno and Taubin, "Simple, Accurate,
and Robust Projector-Camera Calibration", 3DIMPVT 2012): each board corner is mapped into
projector pixels by a homography fitted robustly (RANSAC) to the decoded correspondences
in a small camera window around it, the projector is calibrated from those corners like a
camera, and ``cv2.stereoCalibrate`` refines both devices and their pose together.
Views and corners that fit badly (a shiny patch, a misdetected board) are dropped and the
fit repeated.

:func:`shared.calib.session.calibrate_session` runs a whole session folder
and writes ``rig.json`` with its report: it is the stage the CLI and the job service call.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from shared.core.errors import InputError
from shared.formats.rig import Device, Rig

log = logging.getLogger(__name__)

#: Fewest views (board poses) a calibration accepts.
MIN_VIEWS = 3
#: A view whose reprojection RMS exceeds this many times the median is dropped and the fit redone.
REJECT_FACTOR = 3.0
#: ... unless its error is below this many pixels: a uniformly good set is not whittled down.
REJECT_FLOOR_PX = 0.5
#: The board's normals must spread over at least this angle, or focal length is not observable.
MIN_TILT_SPREAD_DEG = 5.0
#: Camera window (pixels, odd) around each corner used to fit the local homography.
HOMOGRAPHY_WINDOW = 47
#: RANSAC inlier threshold of the local homography, in projector pixels.
HOMOGRAPHY_RANSAC_PX = 1.5
#: Single corners off the fit by more than CORNER_FACTOR x the median corner error (and at least
#: CORNER_FLOOR_PX) are left out, up to CORNER_MAX_SHARE of a view's corners.
CORNER_FACTOR = 4.0
CORNER_FLOOR_PX = 1.0
CORNER_MAX_SHARE = 0.2
#: A pose whose fraction of corners with a projector position falls below this is skipped.
MIN_LIT_FRACTION = 0.5

_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
#: Default calibration flags: OpenCV's five-parameter model (k1, k2, p1, p2, k3) with k3 held at 0.
#: With a handful of board poses that never reach the image corners, a free k3 fits the noise
#: and bends the periphery: on the simulated sessions it doubled the scan error outside the
#: boards' area while lowering the reprojection RMS by under 1 %. ``k3=True`` frees it.
DEFAULT_FLAGS = cv2.CALIB_FIX_K3


def distortion_flags(k3: bool = False) -> int:
    """OpenCV calibration flags for the five-parameter model, ``k3`` estimated or held at 0."""
    return 0 if k3 else DEFAULT_FLAGS


@dataclass(frozen=True)
class ViewPoints:
    """One view of the board: (N, 3) float32 board coordinates and their (N, 2) float64 image positions."""

    name: str
    object_points: np.ndarray
    image_points: np.ndarray


@dataclass
class CameraCalibration:
    """Result of calibrating one device (a camera, or a projector as an inverse camera).

    ``views`` are the names of the views used, in the order of ``rvecs``/``tvecs``/``per_view_rms``;
    ``rejected`` maps dropped views to the reason.
    """

    device: Device
    rms: float
    views: list[str]
    per_view_rms: list[float]
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]
    std_intrinsics: np.ndarray
    rejected: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "device": self.device.to_json(),
            "rms": self.rms,
            "views": [
                {"name": n, "rms": e} for n, e in zip(self.views, self.per_view_rms, strict=True)
            ],
            "rejected": dict(self.rejected),
        }


def _as_cv_points(pts: np.ndarray, dim: int) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(pts, dtype=np.float32).reshape(-1, 1, dim))


def board_normals(rvecs: Sequence[np.ndarray]) -> np.ndarray:
    """Unit normals of the board plane in the device frame, one per view: (V, 3) float64."""
    return np.array([cv2.Rodrigues(np.asarray(r, np.float64))[0][:, 2] for r in rvecs])


def tilt_spread_deg(rvecs: Sequence[np.ndarray]) -> float:
    """Largest angle (degrees) between the board normals of any two views."""
    n = board_normals(rvecs)
    cos = np.clip(np.abs(n @ n.T), 0.0, 1.0)  # a half-turned board is the same plane direction
    return float(np.degrees(np.arccos(cos.min())))


def check_pose_diversity(rvecs: Sequence[np.ndarray], where: Path | str, what: str = "camera") -> None:
    """Raise :class:`InputError` when every view shows the board in (nearly) the same orientation.

    Zhang's method cannot separate focal length from distance when all board planes are
    parallel (all fronto-parallel, or the same pose repeated); the fit then "succeeds"
    with a meaningless focal length, so refuse it.
    """
    spread = tilt_spread_deg(rvecs)
    if spread < MIN_TILT_SPREAD_DEG:
        raise InputError(
            where,
            f"degenerate set of poses: the board planes seen by the {what} differ by at most {spread:.1f} degrees "
            f"(need at least {MIN_TILT_SPREAD_DEG:.0f}); tilt the board differently between poses",
        )


@contextlib.contextmanager
def _serial_solver() -> Iterator[None]:
    """OpenCV on one thread while a calibration solver runs, then as before.

    ``calibrateCamera`` and ``stereoCalibrate`` accumulate their normal equations over parallel
    stripes in whichever order the threads finish, so two runs on the same corners differed in
    the 10th digit (the real session's fx: 3436.377960201 against 3436.377960143). On one thread
    the rig is the same to the last bit, run after run, and the session calibrates in the same
    time (these solvers spend next to nothing in parallel code; 7.1 s either way). The setting
    is process-wide: corner detection, which does gain from threads, never runs meanwhile.
    """
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _calibrate_once(
    views: Sequence[ViewPoints], image_size: tuple[int, int], flags: int, K0: np.ndarray | None, d0: np.ndarray | None
) -> tuple[float, np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray], np.ndarray, np.ndarray]:
    obj = [_as_cv_points(v.object_points, 3) for v in views]
    img = [_as_cv_points(v.image_points, 2) for v in views]
    K = None if K0 is None else K0.copy()
    d = None if d0 is None else d0.copy()
    with _serial_solver():
        rms, K, d, rvecs, tvecs, std_in, _std_ex, per_view = cv2.calibrateCameraExtended(
            obj, img, tuple(int(s) for s in image_size), K, d, flags=flags, criteria=_CRITERIA
        )
    if not (np.isfinite(rms) and np.all(np.isfinite(K)) and np.all(np.isfinite(d))):
        raise cv2.error("calibration diverged (non-finite result)")
    return float(rms), K, d.ravel()[:5], list(rvecs), list(tvecs), np.asarray(std_in).ravel(), np.asarray(per_view).ravel()


def calibrate_camera(
    views: Sequence[ViewPoints],
    image_size: tuple[int, int],
    *,
    where: Path | str = "views",
    what: str = "camera",
    reject_factor: float = REJECT_FACTOR,
    reject_floor_px: float = REJECT_FLOOR_PX,
    min_views: int = MIN_VIEWS,
    flags: int = DEFAULT_FLAGS,
    K0: np.ndarray | None = None,
    dist0: np.ndarray | None = None,
) -> CameraCalibration:
    """Calibrate one device from views of a planar board, dropping views that fit badly.

    Parameters
    ----------
    views : board views; each needs at least 4 points (in practice many more).
    image_size : (width, height) of the device in pixels.
    where : names the input in error messages (the session folder, the image list).
    what : "camera" or "projector", for messages.
    reject_factor, reject_floor_px : a view whose robust reprojection error (1.2 x its median corner
        error) exceeds both ``reject_factor`` x the median over views and ``reject_floor_px`` is
        dropped, worst first, and the fit repeated.
    flags, K0, dist0 : passed to ``cv2.calibrateCamera`` (default :data:`DEFAULT_FLAGS`: the
        five-parameter distortion model with k3 held at 0; see :func:`distortion_flags`).

    Raises :class:`InputError` with fewer than ``min_views`` usable views or a degenerate pose set.
    """
    live = [v for v in views if len(v.object_points) >= 6]
    rejected = {v.name: "fewer than 6 points" for v in views if len(v.object_points) < 6}
    if len(live) < min_views:
        raise InputError(
            where,
            f"only {len(live)} usable {what} view(s) ({', '.join(v.name for v in live) or 'none'}); "
            f"calibration needs at least {min_views}",
        )
    while True:
        try:
            rms, K, d, rvecs, tvecs, std_in, per_view = _calibrate_once(live, image_size, flags, K0, dist0)
        except cv2.error as exc:
            # OpenCV gives up on some degenerate inputs (collinear corners, identical views).
            msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "no solution"
            raise InputError(where, f"{what} calibration failed on these views ({msg}); the poses may be degenerate") from None
        # Judge views by a robust error (1.2 x the median corner error, the RMS of clean Gaussian
        # residuals): a view with a few bad corners keeps its good ones, which the corner-level
        # pass (``_drop_outlier_corners``) then cleans; only a view that is wrong throughout goes.
        score = np.array([
            1.2 * float(np.median(np.linalg.norm(
                _residuals(v.object_points, v.image_points, r, t, Device(0, 0, K, d)), axis=1)))
            for v, r, t in zip(live, rvecs, tvecs, strict=True)
        ])
        med = float(np.median(score))
        worst = int(np.argmax(score))
        bad = score[worst] > max(reject_factor * med, reject_floor_px)
        if not bad or len(live) <= min_views:
            break
        name = live[worst].name
        rejected[name] = (
            f"{what} reprojection error {score[worst]:.2f} px (robust RMS) is over {reject_factor:g}x "
            f"the median {med:.2f} px"
        )
        log.warning("%s: dropping view %s: %s", what, name, rejected[name])
        live = [v for i, v in enumerate(live) if i != worst]
    check_pose_diversity(rvecs, where, what)
    device = Device(width=int(image_size[0]), height=int(image_size[1]), K=K, dist=d)
    return CameraCalibration(
        device=device,
        rms=rms,
        views=[v.name for v in live],
        per_view_rms=[float(e) for e in per_view],
        rvecs=[np.asarray(r, np.float64).ravel() for r in rvecs],
        tvecs=[np.asarray(t, np.float64).ravel() for t in tvecs],
        std_intrinsics=std_in,
        rejected=rejected,
    )


# --------------------------------------------------------------------------------------------
# Board corners in projector pixels


@dataclass(frozen=True)
class ProjectorCorners:
    """Board corners mapped into projector pixels.

    ``points`` (N, 2) float64 projector (column, row), NaN where no reliable estimate;
    ``support`` (N,) int64 decoded pixels the local homography was fitted to (its inliers);
    ``residual`` (N,) float64 RMS of the homography over its inliers, projector pixels.
    """

    points: np.ndarray
    support: np.ndarray
    residual: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.points).all(axis=1)


def projector_corners(
    image_points: np.ndarray,
    column: np.ndarray,
    row: np.ndarray,
    *,
    window: int = HOMOGRAPHY_WINDOW,
    ransac_px: float = HOMOGRAPHY_RANSAC_PX,
    min_support_fraction: float = 0.25,
) -> ProjectorCorners:
    """Map camera-pixel board corners to projector pixels by local homographies (Moreno and Taubin).

    Parameters
    ----------
    image_points : (N, 2) camera pixel positions of the corners.
    column, row : (H, W) float projector column and row decoded at each camera pixel, NaN where invalid.
    window : side of the square camera window around each corner, pixels.
    ransac_px : RANSAC inlier threshold in projector pixels.
    min_support_fraction : a corner needs at least this fraction of its window decoded (as RANSAC
        inliers), else it gets NaN: too little light, or the window leaves the projected area.

    Returns
    -------
    :class:`ProjectorCorners`.
    """
    pts = np.asarray(image_points, np.float64).reshape(-1, 2)
    h, w = column.shape
    half = window // 2
    out = np.full((len(pts), 2), np.nan)
    support = np.zeros(len(pts), np.int64)
    residual = np.full(len(pts), np.nan)
    need = max(16, int(min_support_fraction * window * window))
    for k, (x, y) in enumerate(pts):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        xi, yi = int(round(x)), int(round(y))
        x0, x1 = max(0, xi - half), min(w, xi + half + 1)
        y0, y1 = max(0, yi - half), min(h, yi + half + 1)
        if x1 - x0 < 3 or y1 - y0 < 3:
            continue
        c = column[y0:y1, x0:x1]
        r = row[y0:y1, x0:x1]
        ok = np.isfinite(c) & np.isfinite(r)
        if ok.sum() < need:
            continue
        yy, xx = np.nonzero(ok)
        # Centre the camera coordinates on the corner so the fit is well conditioned.
        src = np.stack([xx + x0 - x, yy + y0 - y], axis=1).astype(np.float64)
        dst = np.stack([c[ok], r[ok]], axis=1).astype(np.float64)
        H, inl = cv2.findHomography(src, dst, cv2.RANSAC, ransac_px, maxIters=2000, confidence=0.999)
        if H is None or inl is None:
            continue
        inl = inl.ravel().astype(bool)
        if inl.sum() < need:
            continue
        p = H @ np.array([0.0, 0.0, 1.0])
        if abs(p[2]) < 1e-12:
            continue
        proj = (H @ np.column_stack([src[inl], np.ones(inl.sum())]).T).T
        proj = proj[:, :2] / proj[:, 2:3]
        out[k] = p[:2] / p[2]
        support[k] = int(inl.sum())
        residual[k] = float(np.sqrt(np.mean(np.sum((proj - dst[inl]) ** 2, axis=1))))
    return ProjectorCorners(points=out, support=support, residual=residual)


def nearest_code_corners(image_points: np.ndarray, column: np.ndarray, row: np.ndarray) -> np.ndarray:
    """The plain approach: the decoded projector (column, row) at each corner's nearest camera pixel.

    Returns
    -------
    (N, 2) float64, NaN where that pixel did not decode. Used as the baseline in benchmarks.
    """
    pts = np.asarray(image_points, np.float64).reshape(-1, 2)
    h, w = column.shape
    xi = np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
    yi = np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1)
    return np.stack([column[yi, xi], row[yi, xi]], axis=1).astype(np.float64)


# --------------------------------------------------------------------------------------------
# Camera + projector


@dataclass(frozen=True)
class PoseCorners:
    """One board pose of a projector-camera session.

    ``object_points`` (N, 3) float32 board coordinates; ``camera_points`` (N, 2) camera pixels;
    ``projector_points`` (N, 2) projector pixels, NaN where the corner has no projector position.
    """

    name: str
    object_points: np.ndarray
    camera_points: np.ndarray
    projector_points: np.ndarray


@dataclass
class PoseResult:
    """Per-pose outcome: whether it was used, and its reprojection errors (pixels) in both devices."""

    name: str
    used: bool
    reason: str | None = None
    corners: int = 0
    projector_corners: int = 0
    camera_rms: float | None = None
    projector_rms: float | None = None
    camera_residuals: np.ndarray | None = None  # (M, 2) observed - reprojected, camera pixels
    projector_residuals: np.ndarray | None = None  # (M, 2) projector pixels

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "used": self.used,
            "reason": self.reason,
            "corners": self.corners,
            "projector_corners": self.projector_corners,
            "camera_rms_px": self.camera_rms,
            "projector_rms_px": self.projector_rms,
            "camera_max_px": None
            if self.camera_residuals is None
            else float(np.linalg.norm(self.camera_residuals, axis=1).max()),
            "projector_max_px": None
            if self.projector_residuals is None
            else float(np.linalg.norm(self.projector_residuals, axis=1).max()),
        }


@dataclass
class RigCalibration:
    """A calibrated rig with the evidence for it.

    ``camera_rms``/``projector_rms`` are the reprojection RMS (pixels) of each device after the
    joint refinement, over the poses used; ``stereo_rms`` is OpenCV's combined figure.
    ``camera_alone``/``projector_alone`` are the separate calibrations that seeded it.
    """

    rig: Rig
    camera_rms: float
    projector_rms: float
    stereo_rms: float
    poses: list[PoseResult]
    camera_alone: CameraCalibration
    projector_alone: CameraCalibration
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]

    def to_json(self) -> dict[str, Any]:
        return {
            "rms_px": {"camera": self.camera_rms, "projector": self.projector_rms, "stereo": self.stereo_rms},
            "camera_alone_rms_px": self.camera_alone.rms,
            "projector_alone_rms_px": self.projector_alone.rms,
            "baseline": self.rig.baseline,
            "units": self.rig.units,
            "poses": [p.to_json() for p in self.poses],
            "rig": self.rig.to_json(),
        }


def _residuals(obj: np.ndarray, img: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, dev: Device) -> np.ndarray:
    proj, _ = cv2.projectPoints(
        np.asarray(obj, np.float64).reshape(-1, 1, 3), np.asarray(rvec, np.float64), np.asarray(tvec, np.float64),
        dev.K, dev.dist,
    )
    return np.asarray(img, np.float64).reshape(-1, 2) - proj.reshape(-1, 2)


def _rms(res: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if len(res) else float("nan")


def _drop_outlier_corners(
    views: list[ViewPoints],
    calib: CameraCalibration,
    factor: float = CORNER_FACTOR,
    floor_px: float = CORNER_FLOOR_PX,
    max_share: float = CORNER_MAX_SHARE,
) -> tuple[list[ViewPoints], int]:
    """Remove single corners far off the fit (a bad decode on a shiny spot), at most ``max_share`` of a view."""
    by_name = {v.name: v for v in views}
    out: list[ViewPoints] = []
    dropped = 0
    for name, rvec, tvec in zip(calib.views, calib.rvecs, calib.tvecs, strict=True):
        v = by_name[name]
        err = np.linalg.norm(_residuals(v.object_points, v.image_points, rvec, tvec, calib.device), axis=1)
        limit = max(floor_px, factor * float(np.median(err)))
        keep = err <= limit
        if (~keep).sum() > max_share * len(err):
            keep = err <= np.quantile(err, 1.0 - max_share)
        dropped += int((~keep).sum())
        out.append(ViewPoints(name, v.object_points[keep], v.image_points[keep]))
    return out, dropped


def calibrate_rig(
    poses: Sequence[PoseCorners],
    camera_size: tuple[int, int],
    projector_size: tuple[int, int],
    *,
    units: str = "mm",
    where: Path | str = "session",
    skipped: dict[str, str] | None = None,
    min_lit_fraction: float = MIN_LIT_FRACTION,
    k3: bool = False,
) -> RigCalibration:
    """Calibrate camera, projector and their relative pose from board poses.

    Parameters
    ----------
    poses : board corners per pose, in both devices (projector NaN where unknown).
    camera_size, projector_size : (width, height) in pixels.
    units : unit of the board coordinates, carried into the rig.
    where : names the session in error messages.
    skipped : poses already skipped upstream (board not found ...), reported alongside.
    min_lit_fraction : a pose with fewer corners mapped into the projector is skipped.
    k3 : estimate the third radial distortion coefficient of both devices (default held at 0).

    Raises :class:`InputError` when fewer than three poses are usable or the poses are degenerate.
    """
    results: dict[str, PoseResult] = {}
    for name, reason in (skipped or {}).items():
        results[name] = PoseResult(name=name, used=False, reason=reason)
    # 1. The camera alone, from every pose where the board was found.
    cam_views = [ViewPoints(p.name, p.object_points, p.camera_points) for p in poses]
    flags = distortion_flags(k3)
    cam = calibrate_camera(cam_views, camera_size, where=where, what="camera", flags=flags)
    for name, reason in cam.rejected.items():
        results[name] = PoseResult(name=name, used=False, reason=reason)
    # 2. The projector alone, from the poses where enough corners have a projector position.
    proj_views: list[ViewPoints] = []
    for p in poses:
        if p.name in cam.rejected:
            continue
        valid = np.isfinite(p.projector_points).all(axis=1)
        n, k = len(valid), int(valid.sum())
        if k < max(6, min_lit_fraction * n):
            reason = f"board out of the projector's light: only {k} of {n} corners decoded"
            log.warning("skipping pose %s: %s", p.name, reason)
            results[p.name] = PoseResult(name=p.name, used=False, reason=reason, corners=n, projector_corners=k)
            continue
        proj_views.append(ViewPoints(p.name, p.object_points[valid], p.projector_points[valid]))
    proj = calibrate_camera(proj_views, projector_size, where=where, what="projector", flags=flags)
    proj_views, n_dropped = _drop_outlier_corners([v for v in proj_views if v.name in proj.views], proj)
    if n_dropped:
        log.info("projector: dropped %d corners far off the fit; refitting", n_dropped)
        proj = calibrate_camera(proj_views, projector_size, where=where, what="projector", flags=flags)
    for name, reason in proj.rejected.items():
        results[name] = PoseResult(name=name, used=False, reason=reason)
    # 3. Each pose gives its own camera-to-projector transform; drop poses that disagree with the
    # consensus (a wrong decode, a half-turned labelling) before they can drag the joint fit away,
    # and start the joint fit from the consensus.
    by_name = {p.name: p for p in poses}
    stereo_views = [v for v in proj_views if v.name in proj.views]
    R0, T0, inconsistent = _consensus_extrinsics(cam, proj, [v.name for v in stereo_views])
    for name, reason in inconsistent.items():
        log.warning("dropping pose %s: %s", name, reason)
        results[name] = PoseResult(name=name, used=False, reason=reason)
    stereo_views = [v for v in stereo_views if v.name not in inconsistent]
    corners_cleaned = False
    if len(stereo_views) < MIN_VIEWS:
        raise InputError(
            where,
            f"only {len(stereo_views)} poses agree on where the projector is ({', '.join(inconsistent)} do not); "
            f"calibration needs at least {MIN_VIEWS}",
        )
    while True:
        obj, ic, ip = [], [], []
        for v in stereo_views:
            p = by_name[v.name]
            keep = _match_rows(p.object_points, v.object_points)
            obj.append(_as_cv_points(v.object_points, 3))
            ic.append(_as_cv_points(p.camera_points[keep], 2))
            ip.append(_as_cv_points(v.image_points, 2))
        try:
            with _serial_solver():
                (stereo_rms, Kc, dc, Kp, dp, R, T, _E, _F, rvecs, tvecs, per_view) = cv2.stereoCalibrateExtended(
                    obj, ic, ip,
                    cam.device.K.copy(), cam.device.dist.copy(), proj.device.K.copy(), proj.device.dist.copy(),
                    tuple(int(s) for s in camera_size), R0.copy(), T0.reshape(3, 1).copy(),
                    flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_USE_EXTRINSIC_GUESS | flags, criteria=_CRITERIA,
                )
        except cv2.error as exc:
            msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "no solution"
            raise InputError(where, f"the joint camera-projector calibration failed ({msg})") from None
        per_pose = np.asarray(per_view).reshape(len(stereo_views), -1).mean(axis=1)
        med = float(np.median(per_pose))
        worst = int(np.argmax(per_pose))
        if per_pose[worst] > max(REJECT_FACTOR * med, REJECT_FLOOR_PX) and len(stereo_views) > MIN_VIEWS:
            name = stereo_views[worst].name
            reason = f"joint reprojection RMS {per_pose[worst]:.2f} px is over {REJECT_FACTOR:g}x the median {med:.2f} px"
            log.warning("dropping pose %s: %s", name, reason)
            results[name] = PoseResult(name=name, used=False, reason=reason)
            stereo_views = [v for i, v in enumerate(stereo_views) if i != worst]
            continue
        if not corners_cleaned:
            # Once: leave out single corners far off the joint fit in either device (a glint on the
            # board spoils a camera corner and its projector position alike), then refit.
            corners_cleaned = True
            cam_dev = Device(0, 0, Kc, np.asarray(dc).ravel())
            proj_dev = Device(0, 0, Kp, np.asarray(dp).ravel())
            errs = []
            for ob, icam, iproj, rvec, tvec in zip(obj, ic, ip, rvecs, tvecs, strict=True):
                rvec = np.asarray(rvec, np.float64).ravel()
                tvec = np.asarray(tvec, np.float64).ravel()
                Rb = cv2.Rodrigues(np.asarray(R, np.float64) @ cv2.Rodrigues(rvec)[0])[0].ravel()
                Tb = np.asarray(R, np.float64) @ tvec + np.asarray(T, np.float64).ravel()
                errs.append((np.linalg.norm(_residuals(ob, icam, rvec, tvec, cam_dev), axis=1),
                             np.linalg.norm(_residuals(ob, iproj, Rb, Tb, proj_dev), axis=1)))
            lim_c = max(CORNER_FLOOR_PX, CORNER_FACTOR * float(np.median(np.concatenate([e[0] for e in errs]))))
            lim_p = max(CORNER_FLOOR_PX, CORNER_FACTOR * float(np.median(np.concatenate([e[1] for e in errs]))))
            cleaned, n_out = [], 0
            for v, (ec, ep) in zip(stereo_views, errs, strict=True):
                keep = (ec <= lim_c) & (ep <= lim_p)
                if (~keep).sum() > CORNER_MAX_SHARE * len(keep):
                    keep = np.ones(len(keep), bool)  # a view that bad is judged as a whole, not corner by corner
                n_out += int((~keep).sum())
                cleaned.append(ViewPoints(v.name, v.object_points[keep], v.image_points[keep]))
            if n_out:
                log.info("joint fit: left out %d corners far off it; refitting", n_out)
                stereo_views = cleaned
                continue
        break
    camera = Device(int(camera_size[0]), int(camera_size[1]), Kc, np.asarray(dc).ravel()[:5])
    projector = Device(int(projector_size[0]), int(projector_size[1]), Kp, np.asarray(dp).ravel()[:5])
    R = np.asarray(R, np.float64)
    T = np.asarray(T, np.float64).ravel()
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(T)) and np.linalg.norm(T) > 0):
        raise InputError(where, "the joint calibration did not converge (non-finite or zero camera-projector offset)")
    rig = Rig(camera=camera, projector=projector, R=R, T=T, units=units)
    all_cam, all_proj = [], []
    rv_out, tv_out = [], []
    for v, rvec, tvec, ob, icam, iproj in zip(stereo_views, rvecs, tvecs, obj, ic, ip, strict=True):
        rvec = np.asarray(rvec, np.float64).ravel()
        tvec = np.asarray(tvec, np.float64).ravel()
        rc = _residuals(ob, icam, rvec, tvec, camera)
        Rb = R @ cv2.Rodrigues(rvec)[0]
        rp = _residuals(ob, iproj, cv2.Rodrigues(Rb)[0].ravel(), R @ tvec + T, projector)
        all_cam.append(rc)
        all_proj.append(rp)
        rv_out.append(rvec)
        tv_out.append(tvec)
        p = by_name[v.name]
        results[v.name] = PoseResult(
            name=v.name, used=True, corners=len(p.object_points), projector_corners=len(ob),
            camera_rms=_rms(rc), projector_rms=_rms(rp), camera_residuals=rc, projector_residuals=rp,
        )
    order = [p.name for p in poses] + [n for n in (skipped or {}) if n not in by_name]
    pose_results = [results[n] for n in order if n in results]
    pose_results += [r for n, r in results.items() if n not in order]
    return RigCalibration(
        rig=rig,
        camera_rms=_rms(np.concatenate(all_cam)),
        projector_rms=_rms(np.concatenate(all_proj)),
        stereo_rms=float(stereo_rms),
        poses=pose_results,
        camera_alone=cam,
        projector_alone=proj,
        rvecs=rv_out,
        tvecs=tv_out,
    )


#: A pose whose own camera-to-projector rotation differs from the consensus by more than this
#: (degrees), or whose translation differs by more than ``MAX_POSE_T_SHARE`` of the baseline, is
#: dropped. The real session scatters by up to 0.4 degrees and 3 %; a wrong pose by tens of degrees.
MAX_POSE_ANGLE_DEG = 2.0
MAX_POSE_T_SHARE = 0.10


def _consensus_extrinsics(
    cam: CameraCalibration, proj: CameraCalibration, names: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, dict[str, str]]:
    """The camera-to-projector transform most poses agree on, and the poses that disagree.

    Per pose, the board's pose in the camera and in the projector give ``R_i = R_p R_c^T``,
    ``T_i = t_p - R_i t_c``. The medoid (the pose closest to all others) is the consensus.

    Returns
    -------
    R : (3, 3), T : (3,), and pose name -> reason for the poses that disagree.
    """
    ci = {n: i for i, n in enumerate(cam.views)}
    pi = {n: i for i, n in enumerate(proj.views)}
    Rs, Ts = [], []
    for n in names:
        Rc = cv2.Rodrigues(cam.rvecs[ci[n]])[0]
        Rp = cv2.Rodrigues(proj.rvecs[pi[n]])[0]
        R = Rp @ Rc.T
        Rs.append(R)
        Ts.append(proj.tvecs[pi[n]] - R @ cam.tvecs[ci[n]])
    m = len(names)
    ang = np.zeros((m, m))
    dt = np.zeros((m, m))
    for a in range(m):
        for b in range(m):
            ang[a, b] = np.degrees(np.linalg.norm(cv2.Rodrigues(Rs[a] @ Rs[b].T)[0]))
            dt[a, b] = np.linalg.norm(Ts[a] - Ts[b])
    scale = max(float(np.median([np.linalg.norm(t) for t in Ts])), 1e-9)
    cost = np.median(ang / MAX_POSE_ANGLE_DEG + dt / (MAX_POSE_T_SHARE * scale), axis=1)
    best = int(np.argmin(cost))
    bad: dict[str, str] = {}
    for k, n in enumerate(names):
        if ang[k, best] > MAX_POSE_ANGLE_DEG or dt[k, best] > MAX_POSE_T_SHARE * scale:
            bad[n] = (
                f"camera and projector disagree on the board's pose: this pose puts the projector "
                f"{ang[k, best]:.2f} degrees and {dt[k, best]:.1f} units away from where the others do"
            )
    return Rs[best], np.asarray(Ts[best], np.float64).ravel(), bad


def _match_rows(full: np.ndarray, subset: np.ndarray) -> np.ndarray:
    """Indices into ``full`` of the rows of ``subset`` (both (N, 3) board points; subset in full's order)."""
    full = np.asarray(full)
    subset = np.asarray(subset)
    d = np.abs(full[None, :, :] - subset[:, None, :]).sum(axis=2)
    return np.argmin(d, axis=1)


def triangulate_corners(rig: Rig, camera_points: np.ndarray, projector_points: np.ndarray) -> np.ndarray:
    """Triangulate matched camera and projector pixels with a rig (linear, after undistortion).

    Parameters
    ----------
    camera_points, projector_points : (N, 2) pixels.

    Returns
    -------
    (N, 3) float64 points in the camera frame, in the rig's units.
    """
    c = cv2.undistortPoints(np.asarray(camera_points, np.float64).reshape(-1, 1, 2), rig.camera.K, rig.camera.dist)
    p = cv2.undistortPoints(
        np.asarray(projector_points, np.float64).reshape(-1, 1, 2), rig.projector.K, rig.projector.dist
    )
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([rig.R, rig.T.reshape(3, 1)])
    X = cv2.triangulatePoints(P1, P2, c.reshape(-1, 2).T, p.reshape(-1, 2).T)
    return (X[:3] / X[3]).T


def plane_fit_rms(points: np.ndarray) -> float:
    """RMS distance of (N, 3) points from their least-squares plane."""
    pts = np.asarray(points, np.float64)
    centred = pts - pts.mean(axis=0)
    return float(np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(pts)))
