"""Simulated calibration sessions: a printed chessboard at random poses under the virtual rig.

In: a rig (by default :func:`shared.sim.simulate.make_rig`), a chessboard or ChArUco board, a number of poses
and a seed. Out: a session folder in the layout :mod:`shared.calib.session` reads
(``board.json`` + one ``graycode-v1`` capture per pose, rendered by
:func:`shared.sim.simulate.simulate_capture` with its noise, blur, distortion and falloff),
plus ``truth.json`` holding the true rig and each pose's board pose, so tests can compare
every recovered parameter with the truth. Units are millimetres.

Poses are drawn so the whole board is seen by the camera and lit by the projector, tilted
between ``tilt_deg`` bounds about a random in-plane axis (a spread of orientations is what
makes focal length observable), at distances around the rig's working distance.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from shared.calib.board import BOARD_FILE, Board, load_board
from shared.core.files import write_json_atomic
from shared.formats.rig import Rig, parse_rig
from shared.sim.scenes import Scene, TexturedPlane, rotation_about
from shared.sim.simulate import ImagingParams, make_rig, simulate_capture

log = logging.getLogger(__name__)

TRUTH_FILE = "truth.json"


@dataclass(frozen=True)
class BoardPose:
    """A board pose: board-frame points ``X_b`` (those of :meth:`Board.object_points`) map to the
    camera frame as ``R @ X_b + t`` (mm)."""

    name: str
    R: np.ndarray
    t: np.ndarray


@dataclass(frozen=True)
class SimulatedSession:
    """A written session: its folder, board, the true rig and the true board poses."""

    root: Path
    board: Board
    rig: Rig
    poses: list[BoardPose]

    def true_camera_corners(self, pose: BoardPose) -> np.ndarray:
        """(N, 2) camera pixels of the board's corners at ``pose`` (through the camera's distortion)."""
        return _project(self.rig.camera, self.board.object_points() @ pose.R.T + pose.t)

    def true_projector_corners(self, pose: BoardPose) -> np.ndarray:
        """(N, 2) projector pixels of the board's corners at ``pose``."""
        X = self.board.object_points() @ pose.R.T + pose.t
        return _project(self.rig.projector, X @ self.rig.R.T + self.rig.T)


def _project(device: Any, X: np.ndarray) -> np.ndarray:
    import cv2

    uv, _ = cv2.projectPoints(np.asarray(X, np.float64).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), device.K, device.dist)
    return uv.reshape(-1, 2)


def _board_plane(board: Board, pose: BoardPose, texels_per_square: int = 32) -> TexturedPlane:
    """The printed board as the virtual rig's textured plane at ``pose``."""
    nx, ny = board.inner_corners
    s = board.square_size
    if board.kind == "charuco":
        # Print the ChArUco pattern (OpenCV's own drawing) on a board of matte paper, like the chessboard.
        image, to_board = board.render(texels_per_square / s)
        texture = (0.06 + (0.85 - 0.06) * (image.astype(np.float32) / 255.0)).astype(np.float32)
        k = float(to_board[0, 0])  # mm per texel
        # Texel (r, c) covers plane x in [c, c + 1) k, so its centre (c + 0.5) k is board x = k c + to_board[0, 2].
        offset = np.array([k / 2 - to_board[0, 2], k / 2 - to_board[1, 2]])
        return TexturedPlane(pose.R, pose.t - pose.R[:, :2] @ offset, texture, k)
    # TexturedPlane.chessboard puts inner corner (i, j) at plane coordinates ((i + 1) s + o, (j + 1) s + o),
    # o being its margin; shift its origin so the board frame's corner (0, 0) lands where ours is.
    probe = TexturedPlane.chessboard(np.eye(3), np.zeros(3), (nx, ny), s, texels_per_square=texels_per_square)
    offset = probe.chessboard_corners()[0]  # plane coordinates of board-frame (0, 0)
    t = pose.t - pose.R[:, :2] @ offset
    return TexturedPlane.chessboard(pose.R, t, (nx, ny), s, texels_per_square=texels_per_square)


def _fits(rig: Rig, board: Board, pose: BoardPose, margin_frac: float) -> bool:
    """Whole board (with its outer squares) inside the camera image and the projector frame, with margin."""
    s = board.square_size
    # The outer squares' edge, one square beyond the outermost inner corners.
    lo = board.object_points().min(axis=0).astype(np.float64) - s
    hi = board.object_points().max(axis=0).astype(np.float64) + s
    outline = np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]])
    X = outline @ pose.R.T + pose.t
    if np.any(X[:, 2] <= 0):
        return False
    for dev, pts in ((rig.camera, X), (rig.projector, X @ rig.R.T + rig.T)):
        if np.any(pts[:, 2] <= 0):
            return False
        uv = _project(dev, pts)
        mx, my = margin_frac * dev.width, margin_frac * dev.height
        if np.any(uv[:, 0] < mx) or np.any(uv[:, 0] > dev.width - 1 - mx):
            return False
        if np.any(uv[:, 1] < my) or np.any(uv[:, 1] > dev.height - 1 - my):
            return False
    return True


def random_board_poses(
    rig: Rig,
    board: Board,
    n: int,
    seed: int = 0,
    tilt_deg: tuple[float, float] = (15.0, 40.0),
    distance: tuple[float, float] = (0.8, 1.1),
    working_distance: float = 1000.0,
    margin_frac: float = 0.02,
) -> list[BoardPose]:
    """``n`` board poses, each fully seen and lit, with tilts in ``tilt_deg`` about axes spread evenly
    around the board normal (so the set is never degenerate). ``tilt_deg=(0, 0)`` gives fronto-parallel poses.
    """
    rng = np.random.default_rng(seed)
    centre_b = board.object_points().mean(axis=0).astype(np.float64)
    poses: list[BoardPose] = []
    attempts = 0
    while len(poses) < n:
        attempts += 1
        if attempts > 2000 * n:
            raise ValueError(f"could not place {n} board poses in view of both devices; use a smaller board")
        k = len(poses)
        # Spread tilt axes evenly, jittered, so orientations differ from pose to pose.
        phi = 2 * np.pi * (k + rng.uniform(-0.25, 0.25)) / n
        axis = np.array([np.cos(phi), np.sin(phi), 0.0])
        tilt = rng.uniform(*tilt_deg)
        spin = rng.uniform(-12, 12)
        R = rotation_about(axis, tilt) @ rotation_about([0, 0, 1], spin)
        z = working_distance * rng.uniform(*distance)
        # Push boards towards the edges and corners of the view: distortion is only learnt where
        # the boards have been (poses that do not fit both devices are drawn again).
        psi = rng.uniform(0, 2 * np.pi)
        reach = rng.uniform(0.4, 1.0)
        centre = np.array([0.11 * z * reach * np.cos(psi), 0.08 * z * reach * np.sin(psi), z])
        t = centre - R @ centre_b
        pose = BoardPose(name=f"pose_{k:02d}", R=R, t=t)
        if _fits(rig, board, pose, margin_frac):
            poses.append(pose)
    return poses


def simulate_session(
    out_dir: str | os.PathLike[str],
    *,
    n_poses: int = 8,
    camera_size: tuple[int, int] = (2048, 1536),
    projector_size: tuple[int, int] = (1024, 768),
    seed: int = 0,
    board: Board | None = None,
    rig: Rig | None = None,
    poses: list[BoardPose] | None = None,
    imaging: ImagingParams | None = None,
    tilt_deg: tuple[float, float] = (15.0, 40.0),
    distance: tuple[float, float] = (0.8, 1.1),
    inverses: bool = True,
) -> SimulatedSession:
    """Render a calibration session into ``out_dir`` (created; must not hold poses already).

    Parameters
    ----------
    n_poses : number of board poses (ignored when ``poses`` is given).
    camera_size, projector_size : (width, height) of the devices of the default rig.
    seed : drives the rig, the poses and the sensor noise.
    board : a chessboard (default 9 x 7 inner corners of 30 mm) or a ChArUco board.
    rig : the true rig (default ``make_rig(camera_size, projector_size, seed)``).
    poses : explicit board poses instead of random ones.
    imaging : the virtual rig's imaging parameters (noise, blur ...).
    tilt_deg, distance : ranges of the board's tilt (degrees) and distance (times the working
        distance) for random poses.
    inverses : also capture each pattern's inverse. Without them a pose takes 22 images instead
        of 42 (the decoder then thresholds against the white/black mid level), which halves
        the rendering time of tests.

    Returns
    -------
    :class:`SimulatedSession` (also written as ``truth.json`` in ``out_dir``).
    """
    board = board or Board("chessboard", (9, 7), 30.0)
    rig = rig or make_rig(camera_size=camera_size, projector_size=projector_size, seed=seed)
    poses = poses or random_board_poses(rig, board, n_poses, seed=seed, tilt_deg=tilt_deg, distance=distance)
    root = Path(out_dir).absolute()
    root.mkdir(parents=True, exist_ok=True)
    write_json_atomic(root / BOARD_FILE, board.to_json())
    imaging = imaging or ImagingParams(interreflection=False)
    for k, pose in enumerate(poses):
        scene = Scene(name=f"board {pose.name}", surfaces=[_board_plane(board, pose)], description="calibration board")
        simulate_capture(
            scene, rig, root / pose.name, seed=seed * 1000 + k, imaging=replace(imaging, inverses=inverses), write_truth=False
        )
        log.info("simulated calibration pose %s (%d of %d)", pose.name, k + 1, len(poses))
    truth = {
        "rig": rig.to_json(),
        "poses": [{"name": p.name, "R": p.R.tolist(), "t": p.t.tolist()} for p in poses],
    }
    write_json_atomic(root / TRUTH_FILE, truth)
    return SimulatedSession(root=root, board=board, rig=rig, poses=list(poses))


def load_simulated_session(path: str | os.PathLike[str]) -> SimulatedSession:
    """Read back a session written by :func:`simulate_session` (its ``truth.json`` and ``board.json``)."""

    root = Path(path).absolute()
    doc = json.loads((root / TRUTH_FILE).read_text(encoding="utf-8"))
    poses = [BoardPose(p["name"], np.asarray(p["R"], float), np.asarray(p["t"], float)) for p in doc["poses"]]
    return SimulatedSession(root=root, board=load_board(root), rig=parse_rig(doc["rig"], root / TRUTH_FILE), poses=poses)
