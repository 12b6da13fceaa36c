"""Calibration sessions on disk: loading, corner finding per pose, and the written outputs.

A session is a folder::

    SESSION_DIR/board.json          the printed target (see shared.calib.board)
    SESSION_DIR/<pose>/capture.json one graycode-v1 capture of the board per pose
    SESSION_DIR/<pose>/...          its images

Pose folders are taken in name order; any sub-folder with a ``capture.json`` is a pose.
Each pose must carry row patterns as well as columns (the projector needs both
coordinates of every corner). The board is found in the capture's white frame.

Outputs (:func:`write_outputs`): ``rig.json`` (the contract of :mod:`shared.formats.rig`), a
report JSON with per-pose reprojection errors of both devices, an OpenCV FileStorage
YAML of the same numbers, and a PNG plot of the residuals per pose. Every file is written
under a temporary name and renamed; ``rig.json`` is written last, so a failure leaves no rig.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from shared.calib.board import BOARD_FILE, Board, Detection, detect_board, load_board
from shared.calib.calibrate import (
    CameraCalibration,
    PoseCorners,
    RigCalibration,
    ViewPoints,
    calibrate_camera,
    calibrate_rig,
    distortion_flags,
    plane_fit_rms,
    projector_corners,
    triangulate_corners,
)
from shared.core.errors import InputError
from shared.core.files import atomic_file, write_json_atomic
from shared.core.paths import confine
from shared.formats.capture import CAPTURE_FILE, Capture, load_capture
from shared.formats.images import read_grey
from shared.formats.rig import Device, Rig, save_rig
from shared.scan.albedo import CameraResponse
from shared.scan.decode import DecodeParams, decode_capture

log = logging.getLogger(__name__)

REPORT_FORMAT = "graylight-calibration-v1"

#: Decodes a capture into per-camera-pixel projector (column, row), each (H, W) float, NaN invalid.
DecodeFn = Callable[[Capture], tuple[np.ndarray, np.ndarray]]
#: Called as progress(done, total, message).
ProgressFn = Callable[[int, int, str], None]


def default_decode(capture: Capture, response: CameraResponse | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Decode with the scanner's own decoder (``shared.scan.decode``), sub-pixel projector
    coordinates; ``response`` is the camera's (sRGB by default, see :class:`DecodeParams`)."""

    decoded = decode_capture(capture, subpixel=True, params=DecodeParams(response=response or CameraResponse()))
    return np.asarray(decoded.column, np.float32), np.asarray(decoded.row, np.float32)


@dataclass(frozen=True)
class Session:
    """A loaded session: its folder, board and pose captures (name, capture) in name order."""

    root: Path
    board: Board
    poses: list[tuple[str, Capture]]


def load_session(session_dir: str | os.PathLike[str]) -> Session:
    """Read ``board.json`` and every pose's ``capture.json``; raises :class:`InputError` on bad input."""
    root = Path(session_dir)
    if not root.is_dir():
        raise InputError(root, "calibration session folder not found")
    board = load_board(root / BOARD_FILE)
    poses: list[tuple[str, Capture]] = []
    for sub in sorted(p for p in root.iterdir() if p.is_dir()):
        if not (sub / CAPTURE_FILE).is_file():
            if any(sub.iterdir()):
                log.warning("session %s: folder %s has no %s; not a pose", root, sub.name, CAPTURE_FILE)
            continue
        confine(root, sub.name, where=sub, folder="session folder", kind="dir")  # a pose linked in from elsewhere
        capture = load_capture(sub)
        if not capture.rows:
            raise InputError(sub / CAPTURE_FILE, 'field "rows" is empty: projector calibration needs row patterns too')
        poses.append((sub.name, capture))
    if not poses:
        raise InputError(root, f"no poses: a session needs one sub-folder per board pose, each with a {CAPTURE_FILE}")
    sizes = {(c.projector_width, c.projector_height) for _, c in poses}
    if len(sizes) > 1:
        raise InputError(root, f"poses disagree on the projector size: {sorted(sizes)}")
    return Session(root=root, board=board, poses=poses)


@dataclass
class SessionResult:
    """A calibrated session: the rig calibration, the board, sizes and per-stage timings (seconds)."""

    session: Session
    calibration: RigCalibration
    camera_size: tuple[int, int]
    projector_size: tuple[int, int]
    poses: list[PoseCorners]
    detections: dict[str, Detection]
    timings: dict[str, float] = field(default_factory=dict)

    def board_check(self) -> dict[str, Any]:
        """The board's squares triangulated with the recovered rig: size error and flatness per pose."""
        rig = self.calibration.rig
        board = self.session.board
        pairs = board.grid_neighbours()
        per_pose = []
        all_rel = []
        used = {r.name for r in self.calibration.poses if r.used}
        for p in self.poses:
            if p.name not in used:
                continue
            ok = np.isfinite(p.projector_points).all(axis=1)
            ids = self.detections[p.name].ids
            if ok.sum() < 4:
                continue
            X = np.full((len(ids), 3), np.nan)
            X[ok] = triangulate_corners(rig, p.camera_points[ok], p.projector_points[ok])
            pos = {int(i): X[k] for k, i in enumerate(ids)}
            d = [
                np.linalg.norm(pos[a] - pos[b])
                for a, b in pairs
                if a in pos and b in pos and np.isfinite(pos[a]).all() and np.isfinite(pos[b]).all()
            ]
            if not d:
                continue
            rel = np.asarray(d) / board.square_size - 1.0
            all_rel.append(rel)
            per_pose.append(
                {
                    "name": p.name,
                    "square_mean": float(np.mean(d)),
                    "square_rms_error_pct": float(100 * np.sqrt(np.mean(rel**2))),
                    "plane_rms": plane_fit_rms(X[ok]),
                }
            )
        rel_all = np.concatenate(all_rel) if all_rel else np.array([np.nan])
        return {
            "square_size": board.square_size,
            "square_rms_error_pct": float(100 * np.sqrt(np.mean(rel_all**2))),
            "poses": per_pose,
        }

    def report(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "format": REPORT_FORMAT,
            "session": str(self.session.root),
            "board": self.session.board.to_json(),
            "camera_size": list(self.camera_size),
            "projector_size": list(self.projector_size),
        }
        doc.update(self.calibration.to_json())
        doc["board_check"] = self.board_check()
        doc["timings_s"] = dict(self.timings)
        return doc


def find_pose_corners(
    session: Session,
    decode: DecodeFn | None = None,
    progress: ProgressFn | None = None,
    window: int | None = None,
) -> tuple[list[PoseCorners], dict[str, str], dict[str, Detection], tuple[int, int]]:
    """Detect the board in each pose's white frame, decode it, and map the corners into the projector.

    Returns
    -------
    poses : usable poses' corners (projector NaN where a corner is not lit).
    skipped : pose name -> reason, for poses where the board was not found.
    detections : pose name -> camera detection.
    camera_size : (width, height) of the camera images.
    """
    decode = decode or default_decode
    board = session.board
    kept: list[PoseCorners] = []
    skipped: dict[str, str] = {}
    detections: dict[str, Detection] = {}
    camera_size: tuple[int, int] | None = None
    total = len(session.poses)
    for i, (name, capture) in enumerate(session.poses):
        if progress:
            progress(i, total, f"pose {name}")
        white = read_grey(capture.white)
        size = (white.shape[1], white.shape[0])
        if camera_size is None:
            camera_size = size
        elif size != camera_size:
            raise InputError(
                capture.white, f"image is {size[0]}x{size[1]}, but the session's first pose is {camera_size[0]}x{camera_size[1]}"
            )
        black = read_grey(capture.black, expect=size)
        # White minus black removes ambient light and the projector's black level: a cleaner board.
        contrast = cv2.normalize(
            np.clip(white.astype(np.float32) - black.astype(np.float32), 0, None), None, 0, 255, cv2.NORM_MINMAX
        ).astype(np.uint8)
        det = detect_board(board, contrast)
        if det is None:
            reason = f"board not found in {capture.white.name}"
            log.warning("skipping pose %s: %s", name, reason)
            skipped[name] = reason
            continue
        column, row = decode(capture)
        if column.shape != white.shape or row.shape != white.shape:
            raise InputError(capture.root, f"decoded maps are {column.shape}, the images {white.shape}")
        pc = projector_corners(det.image_points, column, row, **({"window": window} if window else {}))
        detections[name] = det
        kept.append(
            PoseCorners(
                name=name,
                object_points=det.object_points(board),
                camera_points=det.image_points,
                projector_points=pc.points,
            )
        )
    if progress:
        progress(total, total, "corners found")
    if camera_size is None:
        raise InputError(session.root, "no poses")
    if not kept:
        b = board
        what = (
            f"{b.inner_corners[0]}x{b.inner_corners[1]} inner-corner chessboard"
            if b.kind == "chessboard"
            else f"{b.squares[0]}x{b.squares[1]} ChArUco board ({b.dictionary})"
        )
        raise InputError(
            session.root / BOARD_FILE,
            f"the {what} was not found in any of the {total} poses: board.json does not match the images",
        )
    return kept, skipped, detections, camera_size


def run_session(
    session_dir: Path,
    *,
    decode: DecodeFn | None = None,
    progress: ProgressFn | None = None,
    window: int | None = None,
    k3: bool = False,
    camera_response: CameraResponse | None = None,
) -> SessionResult:
    """Calibrate a session folder in memory (nothing written). Raises :class:`InputError` on bad input.

    ``camera_response`` is the camera's response (sRGB by default): the default decoder reads
    patterns without inverses against the midpoint of linear light through it, and the rig
    records it (``radiometry.camera_response``) for the scans that use the rig.
    ``decode`` maps a pose's capture to its (column, row) maps (default :func:`default_decode`);
    ``progress(done, total, message)`` is called per pose; ``window`` overrides the local
    homography's window (pixels); ``k3`` estimates the third radial distortion coefficient of
    both devices (held at 0 by default, see :func:`shared.calib.calibrate.distortion_flags`).
    """
    t0 = time.perf_counter()
    session = load_session(session_dir)
    response = camera_response or CameraResponse()
    if decode is None:
        def decode(capture: Capture) -> tuple[np.ndarray, np.ndarray]:
            return default_decode(capture, response)
    poses, skipped, detections, camera_size = find_pose_corners(session, decode, progress, window)
    t1 = time.perf_counter()
    projector_size = (session.poses[0][1].projector_width, session.poses[0][1].projector_height)
    calibration = calibrate_rig(
        poses, camera_size, projector_size, units=session.board.units, where=session.root, skipped=skipped, k3=k3
    )
    calibration = replace(calibration, rig=replace(calibration.rig, radiometry={"camera_response": response.rig_value()}))
    t2 = time.perf_counter()
    log.info(
        "calibrated %s: camera %.3f px, projector %.3f px RMS over %d poses",
        session.root, calibration.camera_rms, calibration.projector_rms, sum(p.used for p in calibration.poses),
    )
    return SessionResult(
        session=session,
        calibration=calibration,
        camera_size=camera_size,
        projector_size=projector_size,
        poses=poses,
        detections=detections,
        timings={"corners": t1 - t0, "calibration": t2 - t1},
    )


# --------------------------------------------------------------------------------------------
# Outputs


def write_opencv_yaml(path: Path, *, rig: Rig | None = None, camera: Device | None = None, extra: dict[str, float] | None = None) -> Path:
    """Write an OpenCV FileStorage YAML: camera_matrix/camera_distortion, projector_..., R, T (atomic).

    Readable with ``cv2.FileStorage(path, cv2.FILE_STORAGE_READ)``.
    """
    path = Path(path)
    with atomic_file(path, suffix=".yaml") as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        dev = rig.camera if rig is not None else camera
        if dev is None:
            raise ValueError("write_opencv_yaml needs a rig or a camera")
        fs.write("camera_width", int(dev.width))
        fs.write("camera_height", int(dev.height))
        fs.write("camera_matrix", np.asarray(dev.K, np.float64))
        fs.write("camera_distortion", np.asarray(dev.dist, np.float64).reshape(1, -1))
        if rig is not None:
            fs.write("projector_width", int(rig.projector.width))
            fs.write("projector_height", int(rig.projector.height))
            fs.write("projector_matrix", np.asarray(rig.projector.K, np.float64))
            fs.write("projector_distortion", np.asarray(rig.projector.dist, np.float64).reshape(1, -1))
            fs.write("R", np.asarray(rig.R, np.float64))
            fs.write("T", np.asarray(rig.T, np.float64).reshape(3, 1))
            fs.write("units", rig.units)
        for k, v in (extra or {}).items():
            fs.write(k, float(v))
        fs.release()
    return path


def plot_residuals(path: Path, poses: Sequence[Any], title: str = "Reprojection residuals") -> Path:
    """PNG plot: per-pose RMS bars for both devices and the residual vectors of every corner (atomic).

    ``poses`` are :class:`~shared.calib.calibrate.PoseResult` records (only used ones are drawn).
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    used = [p for p in poses if p.used]
    fig = Figure(figsize=(13, 4.5), dpi=100)
    ax_bar, ax_cam, ax_proj = fig.subplots(1, 3)
    x = np.arange(len(used))
    ax_bar.bar(x - 0.2, [p.camera_rms for p in used], 0.4, label="camera")
    ax_bar.bar(x + 0.2, [p.projector_rms or 0.0 for p in used], 0.4, label="projector")
    ax_bar.set_xticks(x, [p.name for p in used], rotation=45, ha="right")
    ax_bar.set_ylabel("RMS reprojection error (px)")
    ax_bar.set_title("per pose")
    ax_bar.legend()
    for ax, attr, label in ((ax_cam, "camera_residuals", "camera"), (ax_proj, "projector_residuals", "projector")):
        for p in used:
            r = getattr(p, attr)
            if r is not None and len(r):
                ax.scatter(r[:, 0], r[:, 1], s=6, label=p.name)
        ax.axhline(0, color="0.6", lw=0.5)
        ax.axvline(0, color="0.6", lw=0.5)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("dx (px)")
        ax.set_ylabel("dy (px)")
        ax.set_title(f"{label} residuals")
    if used:
        ax_proj.legend(fontsize=7, markerscale=2)
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_file(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    return path


def write_outputs(
    result: SessionResult,
    *,
    rig_path: Path,
    report_path: Path | None = None,
    yaml_path: Path | None = None,
    plot_path: Path | None = None,
) -> dict[str, Any]:
    """Write the report, YAML, plot and finally ``rig.json``; returns the report document."""
    report = result.report()
    report["outputs"] = {
        k: str(v) for k, v in (("rig", rig_path), ("report", report_path), ("opencv_yaml", yaml_path), ("plot", plot_path)) if v
    }
    cal = result.calibration
    if report_path is not None:
        write_json_atomic(Path(report_path), report)
    if yaml_path is not None:
        write_opencv_yaml(
            Path(yaml_path), rig=cal.rig,
            extra={"camera_rms": cal.camera_rms, "projector_rms": cal.projector_rms, "stereo_rms": cal.stereo_rms},
        )
    if plot_path is not None:
        plot_residuals(Path(plot_path), cal.poses, title=f"{result.session.root.name}: reprojection residuals")
    save_rig(cal.rig, rig_path)
    return report


# --------------------------------------------------------------------------------------------
# Camera only


@dataclass
class CameraOnlyResult:
    """A camera calibrated from board photos: the calibration and per-image outcome."""

    calibration: CameraCalibration
    board: Board
    images: list[dict[str, Any]]

    def to_json(self) -> dict[str, Any]:
        cal = self.calibration
        rms = dict(zip(cal.views, cal.per_view_rms, strict=True))
        images = []
        for entry in self.images:
            e = dict(entry)
            if e["name"] in rms:
                e["rms_px"] = rms[e["name"]]
                e["used"] = True
            else:
                e["used"] = False
                e.setdefault("reason", cal.rejected.get(e["name"]))
            images.append(e)
        return {
            "format": "graylight-camera-v1",
            "units": self.board.units,
            "camera": cal.device.to_json(),
            "rms_px": cal.rms,
            "board": self.board.to_json(),
            "images": images,
        }


def calibrate_camera_images(paths: Sequence[Path], board: Board, *, k3: bool = False) -> CameraOnlyResult:
    """Calibrate a camera from photos of a board; images without the board are skipped with a warning.
    ``k3`` estimates the third radial distortion coefficient (held at 0 by default).

    Raises :class:`InputError` for unreadable images, mixed sizes, fewer than three usable
    images or a degenerate set of views.
    """
    if not paths:
        raise InputError("images", "no images given")
    views: list[ViewPoints] = []
    images: list[dict[str, Any]] = []
    first = read_grey(Path(paths[0]))
    size = (first.shape[1], first.shape[0])
    names: set[str] = set()
    for i, p in enumerate(map(Path, paths)):
        img = first if i == 0 else read_grey(p, expect=size)
        name = p.name if p.name not in names else str(p)
        names.add(name)
        det = detect_board(board, img)
        if det is None:
            log.warning("skipping image %s: board not found", p)
            images.append({"name": name, "path": str(p), "reason": "board not found"})
            continue
        images.append({"name": name, "path": str(p), "corners": len(det)})
        views.append(ViewPoints(name, det.object_points(board), det.image_points))
    if not views:
        raise InputError(
            "board.json", f"the board was not found in any of the {len(paths)} images: board.json does not match them"
        )
    where = Path(paths[0]).parent
    calibration = calibrate_camera(views, size, where=where, what="camera", flags=distortion_flags(k3))
    return CameraOnlyResult(calibration=calibration, board=board, images=images)


def calibrate_session(session_dir: Path, out_dir: Path, **kwargs: Any) -> dict[str, Any]:
    """The calibration stage: calibrate a session folder and write ``rig.json`` and its report.

    Parameters
    ----------
    session_dir : a folder with ``board.json`` and one capture folder per pose.
    out_dir : receives ``rig.json``, ``calibration.json`` (report), ``calibration.yaml``
        (OpenCV FileStorage) and ``residuals.png``.
    kwargs : passed to :func:`run_session` (``decode``, ``progress``).

    Returns
    -------
    The report document (also written to ``calibration.json``). Raises :class:`InputError`
    on bad input, leaving no ``rig.json`` behind.
    """
    out_dir = Path(out_dir)
    result = run_session(Path(session_dir), **kwargs)
    return write_outputs(
        result,
        rig_path=out_dir / "rig.json",
        report_path=out_dir / "calibration.json",
        yaml_path=out_dir / "calibration.yaml",
        plot_path=out_dir / "residuals.png",
    )
