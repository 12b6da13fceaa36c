"""Rigid-motion geometry of the merge: poses as 4x4 matrices, rotation angles, the turntable axis.

Poses map a view's frame into the scan set's: ``X_set = P[:3, :3] @ X_view + P[:3, 3]`` (mm).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["TurntableAxis", "axis_from_poses", "pose_error", "rotation_angle_deg"]


@dataclass
class TurntableAxis:
    """A rotation axis in the scan set's frame: ``direction`` (3,) unit, ``point`` (3,) mm on it,
    the signed angle of every view about it in degrees and the RMS misfit of the poses to the model."""

    direction: np.ndarray
    point: np.ndarray
    angles_deg: np.ndarray
    rms_mm: float

    def to_json(self) -> dict[str, Any]:
        return {"direction": [round(float(v), 8) for v in self.direction],
                "point_mm": [round(float(v), 5) for v in self.point],
                "angles_deg": [round(float(v), 5) for v in self.angles_deg], "model_rms_mm": round(self.rms_mm, 5)}


def _rodrigues(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _transform(P: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ P[:3, :3].T + P[:3, 3]


def _rot_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def pose_error(P_est: np.ndarray, P_true: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """Rotation error in degrees and the RMS displacement in mm of ``points`` (N, 3, view frame)
    between two poses: the translation error measured on the object's own points."""
    ang = _rot_angle_deg(P_est[:3, :3] @ P_true[:3, :3].T)
    d = _transform(P_est, points) - _transform(P_true, points)
    return ang, float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def axis_from_poses(poses: np.ndarray, centre: np.ndarray | None = None) -> TurntableAxis:
    """The common rotation axis of poses ``(V, 4, 4)`` that each rotate about one fixed axis.

    The direction minimises ``sum |R_i a - a|^2`` (the null vector of the stacked ``R_i - I``), the
    point solves ``(I - R_i) p = T_i`` in least squares and is moved along the axis to the foot of
    ``centre`` (default: the origin). The direction's sign makes the first non-trivial angle positive.
    """
    M = np.zeros((3, 3))
    for P in poses:
        D = P[:3, :3] - np.eye(3)
        M += D.T @ D
    _, vecs = np.linalg.eigh(M)
    a = vecs[:, 0]
    A = np.concatenate([np.eye(3) - P[:3, :3] for P in poses] + [a[None, :]])
    b = np.concatenate([P[:3, 3] for P in poses] + [np.zeros(1)])
    p = np.linalg.lstsq(A, b, rcond=None)[0]
    c = np.zeros(3) if centre is None else np.asarray(centre, float)
    p = p + a * float(np.dot(c - p, a))
    angles = np.array([_signed_angle(P[:3, :3], a) for P in poses])
    big = np.flatnonzero(np.abs(angles) > 1.0)
    if len(big) and angles[big[0]] < 0:
        a = -a
        angles = -angles
    res = [np.linalg.norm(P[:3, 3] - (np.eye(3) - P[:3, :3]) @ p) for P in poses]
    return TurntableAxis(direction=a, point=p, angles_deg=angles, rms_mm=float(np.sqrt(np.mean(np.square(res)))))


def _signed_angle(R: np.ndarray, a: np.ndarray) -> float:
    # Rotation angle of R about a (sign from the skew part).
    s = 0.5 * np.dot(a, [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = 0.5 * (np.trace(R) - 1.0)
    return float(np.degrees(np.arctan2(s, c)))


def _about_axis(a: np.ndarray, p: np.ndarray, deg: float) -> np.ndarray:
    P = np.eye(4)
    R = _rodrigues(a * np.radians(deg))
    P[:3, :3] = R
    P[:3, 3] = p - R @ p
    return P


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle in degrees of the rotation (3, 3) ``R``."""
    return _rot_angle_deg(R)
