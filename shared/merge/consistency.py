"""Free-space consistency of a registration: does each view's geometry sit where the other views saw through?

A captured view's range image says more than where its surface is: along every pixel's ray, the
space in front of the measured depth is empty. Under right poses no view's sample lies in that
space (beyond the decoder's noise and the mixed pixels at silhouettes); under wrong ones, what
sticks out of the overlap (a spout, a handle, an ear) lands where another view saw the backdrop
far behind. Overlap residuals cannot see this on a body that is nearly one of revolution about
the turntable's axis: there the body fits at any angle and the robust fit discounts the parts
that disagree (measured on a teapot, 16 views at 1024x768, views 0.8 deg off: the median
point-to-plane residual of neighbours rose from 0.037 to 0.054 mm, the free-space share of the
worst view from 0.15 % to over 2 %).

- :func:`free_space_pairs`: for every ordered pair (i, k) of views, how many of up to ``samples``
  of view i's samples, moved into view k's camera by the poses, land on a measured pixel of view
  k (``seen``) and how many of those lie in front of everything view k measured around that pixel
  (3x3: a silhouette's mixed pixels do not count) by more than ``tolerance`` sample sizes
  (``violations``; 1.5 sample sizes is many times the decoder's noise, and at 640x480 it found a
  bunny's view 1.5 deg off where 3 did not);
- :func:`free_space_shares`: per view, the violations of the pairs it takes part in (as the view
  whose samples are tested and as the view whose free space is tested) over their seen samples:
  a view put at the wrong angle raises both, its neighbours only the one pair they share with it;
- :func:`repair_slips`: a turntable registration whose views fall into two arcs that each fit
  but slipped against each other about the axis (the joint fit of a near-symmetric body can slide
  at two boundaries of the loop at once, and the loop still closes) is put right by the turn of
  the arc that removes the most violations between the arcs, searched over every arc.

Only captured views (range image and camera matrix) take part; cloud views carry no free space.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import numpy as np

from shared.merge._fusion_kernels import free_space_violations
from shared.merge.geometry import _about_axis, _signed_angle
from shared.merge.views import ViewCloud

log = logging.getLogger(__name__)

__all__ = ["FREE_SPACE_SHARE", "FREE_SPACE_TOLERANCE", "free_space_pairs", "free_space_shares", "repair_slips",
           "repaired"]

#: A view whose pairs put more than this share of their seen samples in free space is misplaced.
FREE_SPACE_SHARE = 0.005
#: Sample sizes (the larger of the two views') a sample must lie in front of the measured surface.
FREE_SPACE_TOLERANCE = 1.5


class _Observer:
    """A captured view as the one whose free space is tested: the nearest measured Z around each
    pixel (3x3 erosion of the range image, 0 where nothing was measured), K, distortion, sample size."""

    def __init__(self, v: ViewCloud) -> None:
        z = np.nan_to_num(np.asarray(v.range_image, np.float32), nan=0.0)
        self.zmin = cv2.erode(z, np.ones((3, 3), np.uint8))
        self.K = np.asarray(v.K, np.float64)
        self.dist = np.zeros(5)
        if v.dist is not None:
            d = np.asarray(v.dist, np.float64).ravel()[:5]
            self.dist[: len(d)] = d
        self.size = float(np.median(v.size)) if len(v) else 0.0


def _captured(v: ViewCloud) -> bool:
    return v.range_image is not None and v.K is not None and len(v) > 0


def _sources(views: Sequence[ViewCloud], samples: int) -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    for v in views:
        step = max(1, len(v) // max(1, samples))
        out.append((np.ascontiguousarray(v.xyz[::step], np.float64), np.ascontiguousarray(v.size[::step], np.float32)))
    return out


def _count(src: tuple[np.ndarray, np.ndarray], obs: _Observer, rel: np.ndarray, tolerance: float,
           seen_too: bool = True) -> tuple[int, int]:
    """(violations, seen) of the samples ``src`` moved by ``rel`` (4, 4) into ``obs``'s camera
    (seen 0 unless ``seen_too``)."""
    x, s = src
    rel = np.ascontiguousarray(rel, np.float64)
    bad = np.zeros(len(x), np.bool_)
    n_bad = free_space_violations(x, s, rel, obs.K, obs.dist, obs.zmin, obs.size, tolerance, 0.0, bad)
    if not seen_too:
        return int(n_bad), 0
    seen = np.zeros(len(x), np.bool_)
    n_seen = free_space_violations(x, s, rel, obs.K, obs.dist, obs.zmin, obs.size, 0.0, -1e30, seen)
    return int(n_bad), int(n_seen)


def free_space_pairs(views: Sequence[ViewCloud], poses: np.ndarray, kept: Sequence[int] | None = None,
                     tolerance: float = FREE_SPACE_TOLERANCE, samples: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """Per ordered pair (i, k) of the ``kept`` views: (violations, seen), each (V, V) int64, the
    counts of up to ``samples`` of view i's samples (own frame, mm) moved by ``poses`` (V, 4, 4)
    into view k's camera (see the module docstring; zero where k is not a captured view)."""
    V = len(views)
    kept = list(range(V)) if kept is None else list(kept)
    bad = np.zeros((V, V), np.int64)
    seen = np.zeros((V, V), np.int64)
    src = _sources(views, samples)
    for k in kept:
        if not _captured(views[k]):
            continue
        obs = _Observer(views[k])
        inv = np.linalg.inv(poses[k])
        for i in kept:
            if i != k and len(views[i]):
                bad[i, k], seen[i, k] = _count(src[i], obs, inv @ poses[i], tolerance)
    return bad, seen


def free_space_shares(bad: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(V,) per view: the violations of every pair it takes part in over their seen samples (NaN
    for a view in no pair with a captured view)."""
    num = bad.sum(axis=0) + bad.sum(axis=1)
    den = seen.sum(axis=0) + seen.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.maximum(den, 1), np.nan)


def repair_slips(views: Sequence[ViewCloud], poses: np.ndarray, axis: tuple[np.ndarray, np.ndarray],
                 max_deg: float = 4.0, step_deg: float = 0.2, samples: int = 3000, rounds: int = 3,
                 tolerance: float = FREE_SPACE_TOLERANCE, min_gain: float = 0.3) -> tuple[np.ndarray, list[str]]:
    """Turn arcs of a turntable registration about the axis where that removes free-space violations.

    views : the views (own frames, mm; captured views only take part). poses : (V, 4, 4) the
    registration's poses, view 0 fixed. axis : the turntable's unit direction (3,) and a point
    (3,) mm on it, in the set frame.

    The views are ordered by their angle about the axis; for every ordered pair (i, k) and every
    turn ``d`` of a grid of ``step_deg`` up to ``max_deg`` the violations of view i's samples
    turned by ``d`` in view k's free space are counted once; an arc of consecutive views (not view
    0) turned by ``d`` changes exactly the pairs between the arc and the rest, so every arc and
    turn is scored from those counts. The best turn of the best arc is applied when it removes at
    least ``min_gain`` of the violations between the arc and the rest; up to ``rounds`` times.
    Returns the poses and one line per turn applied (for the log and the report). The turns are a
    start for the joint refinement, not its result.
    """
    a = np.asarray(axis[0], np.float64)
    a = a / np.linalg.norm(a)
    p = np.asarray(axis[1], np.float64)
    poses = np.array(poses, np.float64)
    V = len(views)
    part = [v for v in range(V) if _captured(views[v])]
    if len(part) < 3 or 0 not in part:
        return poses, []
    src = _sources(views, samples)
    obs = {k: _Observer(views[k]) for k in part}
    turns = np.round(np.arange(-max_deg, max_deg + 0.5 * step_deg, step_deg), 6)
    zero = int(np.argmin(np.abs(turns)))
    rot = [_about_axis(a, p, float(d)) for d in turns]
    applied: list[str] = []
    for _round in range(rounds):
        # C[i, k, t]: violations of view i turned by turns[t] in view k's free space.
        n = len(part)
        C = np.zeros((n, n, len(turns)))
        for y, k in enumerate(part):
            inv = np.linalg.inv(poses[k])
            for x, i in enumerate(part):
                if i == k:
                    continue
                for t, R in enumerate(rot):
                    C[x, y, t] = _count(src[i], obs[k], inv @ R @ poses[i], tolerance, seen_too=False)[0]
        ang = np.array([_signed_angle(poses[v][:3, :3], a) % 360.0 for v in part])
        ang[part.index(0)] = -1.0  # view 0 first: it never turns
        order = np.argsort(ang)
        best = (0.0, 0, 0, zero, 0.0)  # (gain, first, last, turn index, before)
        for s in range(1, n):
            for e in range(s, n):
                inside = np.zeros(n, bool)
                inside[order[s:e + 1]] = True
                # The arc's samples turned by d in the rest's free space, the rest's turned by -d in the arc's.
                score = C[inside][:, ~inside].sum(axis=(0, 1)) + C[~inside][:, inside].sum(axis=(0, 1))[::-1]
                t = int(np.argmin(score))
                gain = float(score[zero] - score[t])
                if gain > best[0] and gain >= min_gain * score[zero]:
                    best = (gain, s, e, t, float(score[zero]))
        gain, s, e, t, before = best
        if gain <= 0.0 or t == zero:
            break
        arc = [part[int(x)] for x in order[s:e + 1]]
        for v in arc:
            poses[v] = rot[t] @ poses[v]
        line = (f"views {', '.join(views[v].name for v in arc)} turned {turns[t]:+.2f} deg about the axis: "
                f"{int(before)} -> {int(before - gain)} free-space violations between them and the rest")
        log.info("free-space repair: %s", line)
        applied.append(line)
    return poses, applied


def repaired(views: Sequence[ViewCloud], poses: np.ndarray, axis: tuple[np.ndarray, np.ndarray],
             refine: Callable[[np.ndarray], tuple[np.ndarray, Any]], bound: float = FREE_SPACE_SHARE,
             samples: int = 20000) -> tuple[np.ndarray, Any, list[str]] | None:
    """A turntable registration put right by :func:`repair_slips`, or None when it needs no repair
    (no view's free-space share over ``bound``) or the repair does not lower the worst share.

    refine : the joint refinement from new coarse poses (V, 4, 4), returning (poses, its fits).
    Returns (poses, fits, one line per arc turned).
    """
    before = float(np.nanmax(free_space_shares(*free_space_pairs(views, poses, samples=samples)), initial=0.0))
    if not before > bound:
        return None
    start, lines = repair_slips(views, poses, axis)
    if not lines:
        log.info("free-space repair: worst view %.2f %% in free space, no arc turn lowers it", 100 * before)
        return None
    new, fits = refine(start)
    after = float(np.nanmax(free_space_shares(*free_space_pairs(views, new, samples=samples)), initial=0.0))
    log.info("free-space repair: worst view %.3f %% -> %.3f %% of its pairs' samples in free space", 100 * before,
             100 * after)
    if after >= before:
        return None
    return new, fits, lines
