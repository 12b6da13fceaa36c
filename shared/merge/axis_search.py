"""Coarse turntable poses from a known axis: the views' angles about it, found by a 1-D search.

On a fixed rig the plate's disc gives the turntable's axis before any view is registered (its
normal and centre: :mod:`shared.merge.isolate`), and every view's pose is a rotation about it:
``P_v = about(a, p, theta_v)``. What is left is one angle per view, found by scoring every angle
on a grid (the share of the view's samples that meet its already placed neighbour, normals
agreeing) and refining the best. Feature matching has no such model: on an object that is nearly
a surface of revolution about the axis (a teapot's body) FPFH+RANSAC and ICP settle at the
identity, where the body fits and only the spout and the handle disagree; the angle search sees
the spout and the handle raise the score at the right angle.

Given turntable angles (sign unknown), the poses follow from the axis directly; the sign is the
one under which neighbouring views overlap more.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from shared.merge.geometry import _about_axis

__all__ = ["AxisView", "poses_about_axis"]


class AxisView:
    """A view's samples for the search: up to ``n`` sources (N, 3) mm with unit normals, a k-d tree
    over its targets with their unit normals (T, 3) (own frame, which on a fixed rig is the
    camera's: the set frame), and its whole range image with the camera matrix (3, 3)."""

    def __init__(self, xyz: np.ndarray, normals: np.ndarray, tree: cKDTree, target_normals: np.ndarray,
                 range_image: np.ndarray, K: np.ndarray, n: int = 1500) -> None:
        step = max(1, len(xyz) // n)
        self.xyz = np.asarray(xyz[::step], np.float64)
        self.normals = np.asarray(normals[::step], np.float64)
        self.tree = tree
        self.target_normals = target_normals
        self.range_image = range_image  # (H, W) float32 mm, depth along the optical axis; NaN unseen
        self.K = np.asarray(K, np.float64)


def _score(v: AxisView, u: AxisView, a: np.ndarray, p: np.ndarray, deg: np.ndarray, dist: float,
           cos_min: float, free_tol: float) -> np.ndarray:
    """(len(deg),) how well v turned by each angle of ``deg`` about the axis (a, p) agrees with u:
    the share of v's sources that meet u's targets within ``dist`` mm, normals agreeing, less
    ``VIOLATION_WEIGHT`` times the share that would float in front of what u's camera measured
    (more than ``free_tol`` mm nearer than u's range image at their pixel: u would have seen them).
    Overlap alone favours the identity on a body of revolution (each view sees the same side of
    it); free space does not: the spout and the handle land where the other view saw the backdrop."""
    out = np.zeros(len(deg))
    H, W = u.range_image.shape
    for k, d in enumerate(deg):
        T = _about_axis(a, p, float(d))
        x = v.xyz @ T[:3, :3].T + T[:3, 3]
        dd, idx = u.tree.query(x, distance_upper_bound=dist)
        ok = np.isfinite(dd)
        match = 0.0
        if ok.any():
            cos = np.einsum("ij,ij->i", v.normals[ok] @ T[:3, :3].T, u.target_normals[idx[ok]])
            match = np.count_nonzero(cos >= cos_min) / len(x)
        z = x[:, 2]
        front = z > 1e-6
        col = np.round(u.K[0, 0] * x[front, 0] / z[front] + u.K[0, 2]).astype(np.int64)
        row = np.round(u.K[1, 1] * x[front, 1] / z[front] + u.K[1, 2]).astype(np.int64)
        inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
        seen = u.range_image[row[inside], col[inside]]
        with np.errstate(invalid="ignore"):
            floating = np.count_nonzero(z[front][inside] < seen - free_tol)
        out[k] = match - VIOLATION_WEIGHT * floating / len(x)
    return out


VIOLATION_WEIGHT = 4.0


def _best_turn(v: AxisView, u: AxisView, a: np.ndarray, p: np.ndarray, dist: float, cos_min: float,
               step_deg: float) -> tuple[float, float]:
    """The angle (deg) that turns v onto u about the axis, and its score: a grid over the full
    turn, then two finer grids around the best."""
    grid = np.arange(0.0, 360.0, step_deg)
    s = _score(v, u, a, p, grid, 2.0 * dist, cos_min, 2.0 * dist)
    best = float(grid[int(np.argmax(s))])
    # Finer angles with a shorter reach: a reach of a few millimetres cannot tell a degree apart.
    for width, reach in ((step_deg / 4.0, dist), (step_deg / 16.0, 0.25 * dist), (step_deg / 64.0, 0.25 * dist)):
        fine = best + np.arange(-4, 5) * width
        s = _score(v, u, a, p, fine, reach, cos_min, 2.0 * dist)
        best = float(fine[int(np.argmax(s))])
    return best, float(s.max())


def poses_about_axis(views: Sequence[AxisView], a: np.ndarray, p: np.ndarray, dist: float, cos_min: float,
                     min_score: float, angles_deg: np.ndarray | None = None, step_deg: float = 2.0
                     ) -> tuple[np.ndarray, list[int]]:
    """Coarse poses (V, 4, 4) of views that turn about the axis (``a`` (3,) unit, ``p`` (3,) mm),
    view 0 at the identity, and the views that could not be placed (their best turn met fewer than
    ``min_score`` of their samples with the previous placed view; their pose is the identity).

    dist : mm, the reach of a match (a few sample steps). cos_min : least cosine of the normals.
    angles_deg : (V,) the table's angles, sign unknown: the poses follow from them.
    """
    V = len(views)
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    p = np.asarray(p, np.float64)
    if angles_deg is not None:
        rel = np.asarray(angles_deg, np.float64) - float(angles_deg[0])
        best: tuple[float, np.ndarray] | None = None
        for sign in (1.0, -1.0):
            poses = np.stack([_about_axis(a, p, sign * float(t)) for t in rel])
            order = np.argsort(rel % 360.0)
            score = np.mean([_score(views[int(order[k])], views[int(order[k - 1])], a, p,
                                    np.array([sign * float(rel[order[k]] - rel[order[k - 1]])]), dist, cos_min,
                                    2.0 * dist)[0]
                             for k in range(V)])
            if best is None or score > best[0]:
                best = (float(score), poses)
        assert best is not None
        return best[1], []
    theta = np.zeros(V)
    lost: list[int] = []
    last = 0
    for v in range(1, V):
        turn, score = _best_turn(views[v], views[last], a, p, dist, cos_min, step_deg)
        if score < min_score:
            lost.append(v)
            continue
        theta[v] = theta[last] + turn
        last = v
    poses = np.stack([_about_axis(a, p, float(t)) if v not in lost else np.eye(4) for v, t in enumerate(theta)])
    return poses, lost
