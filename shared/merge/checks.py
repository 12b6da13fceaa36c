"""The registration checks its own result: no view is called registered when the structure says it is not.

Fitness and inlier RMS do not flag a registration that locked onto the wrong geometry (a wall
behind a turntable fits perfectly at the identity), so the result's structure is checked too:

- **Identical views** (before registration): two views whose samples coincide in their own frames
  (``identical_share`` of each within a few sample spacings of the other) are the same capture
  twice, or the table did not turn.
- **Unchanged geometry**: a view whose fitted correspondences with a neighbour also hold with no
  motion at all (``unchanged_share`` of them) fits on geometry the other view sees unchanged: a
  static background, not the object.
- **The turn** (turntable sets: one fixed rig, or angles given): every view must turn about one
  axis (each pose's rotation within ``axis_tolerance_deg`` of the rotation about the common axis
  by its own angle), distinct views must not sit at the identity (``min_turn_deg``), and with the
  angles given each view's angle must be the given one (``angle_tolerance_deg``; the sign of the
  whole set and the zero are free).
- **Loop closure**: the pairwise fits chained around the loop must come back within
  ``loop_deg`` and ``loop_voxels`` sample steps.
- **Free space** (captured views): no view's samples may lie where another view saw through to
  something farther (:mod:`shared.merge.consistency`): per view, the share of the samples of the
  pairs it takes part in that lie more than ``free_space_tolerance`` sample sizes in front of the
  other view's measured surface must stay under ``free_space_share``. A misplaced view raises its
  neighbours' shares too, so the views are named worst first, each one's pairs set aside before
  the rest are judged again. Overlap, residuals and the
  loop do not flag a near-symmetric body registered a degree off about the axis (its body fits at
  any angle); its spout and handle land in front of the backdrop another view saw. Measured at
  1024x768 without roi or hints (worst view): right poses 0.06-0.15 % (bunny, teapot, spot, 8 and
  16 views, the truth and the registration); one view turned 0.8 deg about the axis 1.7-2.7 %, 0.4
  deg 0.2-1.0 %; the teapot's 16 views registered with ten of them 0.8 deg off 1.37 %. At 640x480
  (bunny, 8 views): right 0.18 %, one view 1.5 deg off 2.3 %, 0.8 deg 0.2-0.5 % (the limit there).

:func:`check_registration` returns a :class:`Checks`: the JSON block (every figure, per view and
per pair) and the failures, each naming its views.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.merge.consistency import (
    FREE_SPACE_SHARE,
    FREE_SPACE_TOLERANCE,
    free_space_pairs,
    free_space_shares,
)
from shared.merge.geometry import _about_axis, axis_from_poses, rotation_angle_deg
from shared.merge.registration import Registration
from shared.merge.views import ViewCloud

log = logging.getLogger(__name__)

__all__ = ["CheckParams", "Checks", "check_registration", "identical_views", "register_checked"]


@dataclass(frozen=True)
class CheckParams:
    """Bounds of the checks (degrees, shares, sample steps); see the module docstring."""

    identical_share: float = 0.9
    unchanged_share: float = 0.6
    min_turn_deg: float = 0.5
    axis_tolerance_deg: float = 1.0
    angle_tolerance_deg: float = 2.0
    loop_deg: float = 1.0
    loop_voxels: float = 3.0
    free_space_share: float = FREE_SPACE_SHARE
    free_space_tolerance: float = FREE_SPACE_TOLERANCE
    probe: int = 3000
    free_space_samples: int = 20000


@dataclass
class Checks:
    """doc : the JSON block. failures : (view indices, one-line message) of every failed check."""

    doc: dict[str, Any]
    failures: list[tuple[list[int], str]] = field(default_factory=list)

    @property
    def failed_views(self) -> list[int]:
        return sorted({v for views, _ in self.failures for v in views})

    def message(self, names: Sequence[str]) -> tuple[str, str]:
        """(where, problem) of an error naming every failed view and what was found."""
        where = ", ".join(f"views[{v}] ({names[v]})" for v in self.failed_views)
        return where, "; ".join(m for _, m in self.failures)


class _Probe:
    """A view's samples for the checks: up to ``n`` probes and a k-d tree over up to 20 n points,
    with the spacing of that tree's points (mm)."""

    def __init__(self, v: ViewCloud, n: int, rng: np.random.Generator) -> None:
        pick = rng.choice(len(v), size=min(len(v), n), replace=False)
        self.xyz = v.xyz[pick]
        dense = v.xyz if len(v) <= 20 * n else v.xyz[rng.choice(len(v), size=20 * n, replace=False)]
        self.tree = cKDTree(dense)
        d, _ = self.tree.query(dense[:: max(1, len(dense) // 2000)], k=2)
        self.spacing = float(np.median(d[:, 1]))

    def share_near(self, other: _Probe, T: np.ndarray | None = None, xyz: np.ndarray | None = None) -> np.ndarray:
        """(n,) bool: which probes (moved by ``T`` (4, 4) when given) lie within reach of ``other``."""
        x = self.xyz if xyz is None else xyz
        if T is not None:
            x = x @ T[:3, :3].T + T[:3, 3]
        reach = 3.0 * max(self.spacing, other.spacing)
        d, _ = other.tree.query(x, distance_upper_bound=reach)
        return np.isfinite(d)


def identical_views(views: Sequence[ViewCloud], params: CheckParams | None = None, seed: int = 0
                    ) -> list[tuple[int, int, float]]:
    """Pairs (i, j, share) of views whose samples coincide in their own frames (see the module docstring)."""
    params = params or CheckParams()
    rng = np.random.default_rng(seed)
    probes = [_Probe(v, params.probe, rng) for v in views]
    out = []
    for i in range(len(views)):
        for j in range(i + 1, len(views)):
            a = float(probes[i].share_near(probes[j]).mean())
            if a < params.identical_share:
                continue
            b = float(probes[j].share_near(probes[i]).mean())
            if b >= params.identical_share:
                out.append((i, j, min(a, b)))
    return out


def _names(names: Sequence[str], views: Sequence[int]) -> str:
    return ", ".join(names[v] for v in views)


def check_registration(reg: Registration, views: Sequence[ViewCloud], names: Sequence[str], *, turntable: bool,
                       angles_deg: np.ndarray | None = None, identical: Sequence[tuple[int, int, float]] = (),
                       params: CheckParams | None = None, seed: int = 0) -> Checks:
    """Check a registration of ``views`` (the samples it fitted, own frames, mm); see the module docstring.

    turntable : the set is a turntable set (one fixed rig, or angles given): the turn is checked.
    angles_deg : (V,) the given table angles, or None.
    identical : the pairs :func:`identical_views` found (reported, and not held against the turn).
    """
    params = params or CheckParams()
    rng = np.random.default_rng(seed)
    V = len(views)
    kept = [v for v in range(V) if v not in reg.dropped]
    probes = {v: _Probe(views[v], params.probe, rng) for v in kept}
    failures: list[tuple[list[int], str]] = []
    flags: dict[int, list[str]] = {v: [] for v in range(V)}
    same = {(i, j) for i, j, _ in identical} | {(j, i) for i, j, _ in identical}
    for i, j, share in identical:
        flags[i].append("identical")
        flags[j].append("identical")
        # The later of the two is the one to leave out.
        failures.append(([j], f"{names[i]} and {names[j]} are identical ({100 * share:.0f} % of their samples "
                                 "coincide with no turn: the same capture twice, or the table did not turn)"))
    # Per pair: how much of the fit also holds with no motion (geometry the other view sees unchanged).
    pairs = []
    for e in reg.edges:
        i, j = e["views"]
        rel = np.linalg.solve(reg.poses[j], reg.poses[i])  # view i -> view j
        fit = probes[i].share_near(probes[j], rel)
        still = probes[i].share_near(probes[j])
        unchanged = float((fit & still).sum() / max(1, fit.sum()))
        turn = rotation_angle_deg(rel[:3, :3])
        pairs.append({**e, "names": [names[i], names[j]], "turn_deg": round(turn, 4),
                      "unchanged_share": round(unchanged, 4)})
        if unchanged >= params.unchanged_share and (i, j) not in same:
            for v in (i, j):
                if "fits_unchanged_geometry" not in flags[v]:
                    flags[v].append("fits_unchanged_geometry")
    unchanged_views = [v for v in kept if "fits_unchanged_geometry" in flags[v]]
    if unchanged_views:
        failures.append((unchanged_views, f"{_names(names, unchanged_views)} fit only on geometry the other views see "
                                          "unchanged (a static background, not the object)"))
    turn_doc = None
    if turntable and len(kept) >= 2:
        turn_doc = _check_turn(reg, kept, names, angles_deg, same, params, flags, failures)
    loop = reg.loop_closure
    loop_doc = None
    if loop is not None:
        closes = loop["chained_pairwise_deg"] <= params.loop_deg and loop["chained_pairwise_mm"] <= (
            params.loop_voxels * reg.voxel_mm)
        loop_doc = {**loop, "bound_deg": params.loop_deg, "bound_mm": round(params.loop_voxels * reg.voxel_mm, 4),
                    "closes": bool(closes)}
        if not closes:
            order = loop["order"]
            failures.append((list(order), f"the loop {names[order[0]]} ... {names[order[-1]]} does not close: the "
                                          f"pairwise fits chained around it end {loop['chained_pairwise_deg']:.3f} deg "
                                          f"/ {loop['chained_pairwise_mm']:.3f} mm from where they started"))
    free, free_doc = _check_free_space(reg, views, kept, names, params, flags, failures)
    per_view = []
    for v in range(V):
        entry: dict[str, Any] = {"view": v, "name": names[v], "registered": v in kept, "flags": flags[v]}
        if v in kept:
            entry.update({"rms_mm": round(float(reg.rms_mm[v]), 5), "overlap": round(float(reg.overlap[v]), 4),
                          "inlier_share": round(float(reg.inlier_share[v]), 4),
                          "free_space_share": None if not np.isfinite(free[v]) else round(float(free[v]), 5)})
        per_view.append(entry)
    doc = {"passed": not failures, "views": per_view, "pairs": pairs, "loop_closure": loop_doc, "turn": turn_doc,
           "free_space": free_doc,
           "identical_pairs": [{"views": [i, j], "names": [names[i], names[j]], "share": round(s, 4)}
                               for i, j, s in identical],
           "failures": [{"views": [names[v] for v in vs], "problem": m} for vs, m in failures],
           "bounds": {k: v for k, v in params.__dict__.items() if k not in ("probe", "free_space_samples")}}
    return Checks(doc=doc, failures=failures)


def _check_free_space(reg: Registration, views: Sequence[ViewCloud], kept: list[int], names: Sequence[str],
                      params: CheckParams, flags: dict[int, list[str]], failures: list[tuple[list[int], str]]
                      ) -> tuple[np.ndarray, dict[str, Any] | None]:
    """The free-space check (module docstring): per view its share (NaN where no captured view
    tests it) and the JSON block (None when fewer than two captured views take part)."""
    bad, seen = free_space_pairs(views, reg.poses, kept, params.free_space_tolerance, params.free_space_samples)
    share = free_space_shares(bad, seen)
    tested = [v for v in kept if np.isfinite(share[v])]
    if len(tested) < 2:
        return share, None
    # A misplaced view raises its neighbours' shares too (their pairs with it): the worst view is
    # named first, its pairs set aside, and the rest judged again.
    over: list[int] = []
    rest = np.ones(len(share), bool)
    while True:
        b, s = bad[np.ix_(rest, rest)], seen[np.ix_(rest, rest)]
        left = np.flatnonzero(rest)
        sub = free_space_shares(b, s)
        cand = [x for x in range(len(left)) if np.isfinite(sub[x]) and sub[x] > params.free_space_share]
        if not cand:
            break
        worst_x = max(cand, key=lambda x: sub[x])
        over.append(int(left[worst_x]))
        rest[left[worst_x]] = False
    over.sort()
    for v in over:
        flags[v].append("in_free_space")
    if over:
        detail = ", ".join(f"{names[v]} {100 * share[v]:.2f} %" for v in over)
        failures.append((over, f"{_names(names, over)} put samples where other views saw through to something "
                               f"farther (free-space violations {detail} of the samples their pairs see, bound "
                               f"{100 * params.free_space_share:.2f} %): registered at a wrong angle or offset"))
    worst = max(tested, key=lambda v: share[v])
    return share, {"views_tested": len(tested), "worst_view": names[worst],
                   "worst_share": round(float(share[worst]), 5), "median_share": round(float(np.median(share[tested])), 5),
                   "violations": int(bad.sum()), "seen": int(seen.sum()), "bound_share": params.free_space_share,
                   "tolerance_sample_sizes": params.free_space_tolerance}


def _check_turn(reg: Registration, kept: list[int], names: Sequence[str], angles_deg: np.ndarray | None,
                same: set[tuple[int, int]], params: CheckParams, flags: dict[int, list[str]],
                failures: list[tuple[list[int], str]]) -> dict[str, Any]:
    """The turntable checks (one axis, no identity between distinct views, the given angles)."""
    poses = reg.poses
    ref = kept[0]
    rel = np.stack([np.linalg.solve(poses[ref], poses[v]) for v in kept])
    axis = axis_from_poses(rel)
    a = axis.direction
    per_view = []
    off_axis, at_identity, wrong_angle = [], [], []
    sign = 1.0
    if angles_deg is not None:
        given = np.array([angles_deg[v] - angles_deg[ref] for v in kept])
        found = axis.angles_deg
        # The sign of the whole set is free: take the one that fits.
        err = {s: np.abs((found - s * given + 180.0) % 360.0 - 180.0) for s in (1.0, -1.0)}
        sign = 1.0 if np.median(err[1.0]) <= np.median(err[-1.0]) else -1.0
    for k, v in enumerate(kept):
        model = _about_axis(a, axis.point, float(axis.angles_deg[k]))
        misfit = rotation_angle_deg(model[:3, :3] @ rel[k][:3, :3].T)
        entry: dict[str, Any] = {"name": names[v], "angle_deg": round(float(axis.angles_deg[k]), 4),
                                 "axis_misfit_deg": round(misfit, 4)}
        if misfit > params.axis_tolerance_deg:
            off_axis.append(v)
            flags[v].append("off_axis")
        if angles_deg is not None:
            want = sign * float(angles_deg[v] - angles_deg[ref])
            diff = float((axis.angles_deg[k] - want + 180.0) % 360.0 - 180.0)
            entry.update({"given_deg": round(float(angles_deg[v]), 4), "angle_error_deg": round(diff, 4)})
            if abs(diff) > params.angle_tolerance_deg:
                wrong_angle.append(v)
                flags[v].append("angle_disagrees")
        per_view.append(entry)
    for x, i in enumerate(kept):
        for j in kept[x + 1:]:
            if (i, j) in same:
                continue
            if rotation_angle_deg(np.linalg.solve(poses[i], poses[j])[:3, :3]) < params.min_turn_deg:
                at_identity += [v for v in (i, j) if v not in at_identity]
    for v in at_identity:
        flags[v].append("at_identity")
    if at_identity:
        failures.append((sorted(at_identity), f"{_names(names, sorted(at_identity))} registered less than "
                                              f"{params.min_turn_deg} deg apart although they differ: a turntable set "
                                              "must turn (degenerate: the fit holds on what does not turn)"))
    if off_axis:
        worst = max(per_view[kept.index(v)]["axis_misfit_deg"] for v in off_axis)
        failures.append((off_axis, f"{_names(names, off_axis)} do not turn about the set's one axis (up to "
                                   f"{worst:.2f} deg off, bound {params.axis_tolerance_deg})"))
    if wrong_angle:
        detail = ", ".join(f"{names[v]} turned {per_view[kept.index(v)]['angle_deg']:.1f} deg, given "
                           f"{float(angles_deg[v]):.1f}" for v in wrong_angle)  # type: ignore[index]
        failures.append((wrong_angle, f"turntable.angles_deg disagree with the registration ({detail}; relative to "
                                      f"{names[ref]}, sign {'+' if sign > 0 else '-'}): angles wrong by a sign or an "
                                      "offset?"))
    return {"axis": axis.to_json(), "reference": names[ref], "angle_sign": int(sign), "per_view": per_view}


def _expand(sub: Registration, idx: list[int], V: int) -> Registration:
    """A registration of the views ``idx`` as one of all ``V`` views (the others dropped)."""
    poses = np.tile(np.eye(4), (V, 1, 1))
    rms, overlap, inl = np.full(V, np.nan), np.zeros(V), np.zeros(V)
    poses[idx], rms[idx], overlap[idx], inl[idx] = sub.poses, sub.rms_mm, sub.overlap, sub.inlier_share
    edges = [{**e, "views": [idx[e["views"][0]], idx[e["views"][1]]]} for e in sub.edges]
    axis = None
    if sub.axis is not None:
        angles = np.zeros(V)
        angles[idx] = sub.axis.angles_deg
        axis = type(sub.axis)(direction=sub.axis.direction, point=sub.axis.point, angles_deg=angles,
                              rms_mm=sub.axis.rms_mm)
    loop = None if sub.loop_closure is None else {**sub.loop_closure,
                                                  "order": [idx[v] for v in sub.loop_closure["order"]]}
    dropped = sorted({v for v in range(V) if v not in idx} | {idx[v] for v in sub.dropped})
    return Registration(poses=poses, method=sub.method, rms_mm=rms, overlap=overlap, inlier_share=inl, edges=edges,
                        axis=axis, loop_closure=loop, dropped=dropped, voxel_mm=sub.voxel_mm, seconds=sub.seconds)


def register_checked(register: Callable[[list[int]], Registration], views: Sequence[ViewCloud],
                     names: Sequence[str], *, turntable: bool, angles_deg: np.ndarray | None,
                     drop_unregistered: bool, registered: Registration | None = None,
                     params: CheckParams | None = None) -> tuple[Registration, Checks]:
    """Register and check; a failed check is an :class:`~shared.core.errors.InputError` naming the
    views and what was found, or with ``drop_unregistered`` those views are left out (with a
    warning) and the rest registered and checked again.

    register : registers the views of the given indices (a registration of them only, view
        indices relative to the list).
    views : every view's samples that the registration fits (own frames, mm).
    registered : a registration of all views already made (checked, not redone).
    """
    V = len(views)
    identical = identical_views(views, params)
    if identical and not drop_unregistered:
        i, j, share = identical[0]
        raise InputError(", ".join(f"views[{v}] ({names[v]})" for v in (i, j)),
                         f"identical: {100 * share:.0f} % of their samples coincide with no turn (the same capture "
                         "twice, or the table did not turn; --drop-unregistered leaves the later out)")
    active = list(range(V))
    if drop_unregistered:
        later = sorted({j for _, j, _ in identical})
        if later:
            log.warning("left out views identical to an earlier one: %s", ", ".join(names[v] for v in later))
        active = [v for v in active if v not in later]
    # One view that does not belong (another object, a wrong angle) can bend its neighbours' fits
    # enough that they fail the checks too: views are left out one at a time, the worst first, and
    # the rest registered again, so the consensus of the others decides (at most half the set).
    for _attempt in range(max(3, V // 2 + 1)):
        reg = registered if registered is not None and len(active) == V else _expand(register(active), active, V)
        checks = check_registration(reg, views, names, turntable=turntable, angles_deg=angles_deg,
                                    identical=identical, params=params)
        if not checks.failures:
            return reg, checks
        if not drop_unregistered:
            raise InputError(*checks.message(names))
        # A loop that does not close names no view to leave out: it stays an error.
        droppable = [v for vs, m in checks.failures if "does not close" not in m for v in vs]
        if len(droppable) < sum(len(vs) for vs, _ in checks.failures):
            raise InputError(*checks.message(names))
        lost = sorted(v for v in reg.dropped if v in active)
        worst = _worst_view(checks, [v for v in droppable if v in active], names)
        bad = sorted(set(lost) | ({worst} if worst is not None else set()))
        left = [v for v in active if v not in bad]
        if not bad or len(left) < 2 or len(left) < 0.5 * V:
            raise InputError(*checks.message(names))
        log.warning("left out views that fail the registration's checks: %s (%s)", ", ".join(names[v] for v in bad),
                    checks.message(names)[1])
        active = left
    raise InputError(*checks.message(names))


def _worst_view(checks: Checks, flagged: Sequence[int], names: Sequence[str]) -> int | None:
    """Of the views the failed checks name, the one to leave out first: named by the most checks,
    then the farthest off the common axis or the given angle."""
    if not flagged:
        return None
    count = {v: flagged.count(v) for v in set(flagged)}
    off = {}
    turn = checks.doc.get("turn") or {}
    by_name = {e["name"]: e for e in turn.get("per_view", [])}
    free = {e["name"]: e.get("free_space_share") or 0.0 for e in checks.doc.get("views", [])}
    for v in count:
        e = by_name.get(names[v], {})
        # A free-space share of 1 % weighs as a degree off.
        off[v] = (float(e.get("axis_misfit_deg", 0.0)) + abs(float(e.get("angle_error_deg", 0.0)))
                  + 100.0 * float(free.get(names[v], 0.0)))
    return max(count, key=lambda v: (count[v], off[v], v))
