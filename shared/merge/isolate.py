"""Find the object of a fixed-rig scan set: remove what does not turn, the support it stands on, and clutter.

On a turntable the camera and projector stand still, so the backdrop, the table and the
turntable's base sit at the same pixel with the same depth in every view; the plate and the
support plane it forms look the same in every view too (they are rotationally symmetric). Only the
object moves. Registration from overlap alone locks onto whatever fills most of the image, so the
views are reduced to the object first:

1. **Static samples** (captured views of one fixed rig: the same image size and camera): for every
   pixel, the views whose depths agree within ``agree_sigmas`` robust noise deviations of the
   decoder (measured on the set itself, in sample sizes ``Z / f``) are counted; a sample that at
   least ``min_agree_views`` views share is static. Where the object passes in front of the
   background in all but one or two views the count cannot tell, so the static depth is filled into
   those pixels from around them (a normalised box filter), and a sample on that filled background
   is static too. The object's own samples agree at one pixel across views only where its surface
   is locally one of revolution about the axis (a sliver near the axis, measured 0.4 % of them).
2. **Support plane**: a RANSAC plane fit to the static samples next to the object, among those that
   leave the object on one side and touch it (the plate's top, whose normal is the turntable's
   axis); the plate's disc is the plane's static samples around the object's foot. Samples on or
   below the plane are left out (``keep_support`` keeps the disc for the fusion: it carries nothing
   for the registration, being the same in every view).
3. **The object**: the non-static samples of all views pooled (one frame: the rig did not move),
   clustered by connectivity on a grid of a few sample sizes; the object is the largest cluster
   that at least half the views see. Its bounding sphere is reported (the scan set's ``roi``
   syntax), so a user can correct it; an explicit ``roi`` replaces the cluster search.

Cloud views (other scanners) and sets whose captures do not share one camera are left as they are,
cropped to the ``roi`` when one is given. Sets whose rig moves (an orbit) see the world move:
nothing but surfaces of revolution about the orbit's axis (a floor) looks static there.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.formats.scanset import Roi, ScanSet
from shared.merge.views import ViewCloud, crop_to_roi

log = logging.getLogger(__name__)

__all__ = ["Isolation", "IsolationParams", "fixed_rig", "isolate_object", "static_samples", "support_plane"]


@dataclass(frozen=True)
class IsolationParams:
    """Parameters with physical meaning.

    agree_sigmas : two views' depths at one pixel agree within this many robust standard
        deviations of the decoder's noise (measured across the set, in sample sizes).
    min_agree_views : a sample that this many views share (itself included) is static (two for a
        set of two or three views).
    fill_fraction : the static depth is filled into pixels the object hides, from within this
        share of the image width.
    support_tolerance : samples within this many sample sizes of the support plane (or below it)
        belong to the support.
    support_gap : the object's lowest seen samples may stand this share of its height above the
        support plane (:func:`support_plane`).
    disc_reach : the plate's disc is sought among the support plane's samples within this many of
        the object's sphere radii of its centre.
    cluster_step : the object's samples are connected on a grid of this many sample sizes.
    min_object_share : the object (what moves, above the support) must hold at least this share of
        the set's samples, else the set is all backdrop.
    foreign_static_ratio : a view whose share of static samples is under this ratio of the other
        views' median does not share their background (measured: 2 % static for a view of another
        session's scene among views 71-81 % static); it is left out of the object's search.
    keep_support : keep the plate's disc in the fused cloud (never in the registration).
    """

    agree_sigmas: float = 5.0
    min_agree_views: int = 3
    fill_fraction: float = 0.03
    support_tolerance: float = 1.5
    support_gap: float = 0.15
    disc_reach: float = 2.5
    cluster_step: float = 3.0
    min_object_share: float = 0.01
    foreign_static_ratio: float = 0.5
    keep_support: bool = False


@dataclass
class Isolation:
    """The views reduced to the object, and what was left out.

    registration : per view the object's samples (what the registration fits).
    fusion : per view what is fused: the object's samples, plus the plate's disc with ``keep_support``.
    report : JSON-ready figures (samples static, support, clutter and kept per view; the noise;
        the support plane and disc; the object's sphere and whether it was found or given).
    axis : the turntable's axis from the plate, unit direction (3,) and point (3,) mm in the
        views' common frame (the support plane's normal through the disc's centre), or None.
    """

    registration: list[ViewCloud]
    fusion: list[ViewCloud]
    report: dict[str, Any] = field(default_factory=dict)
    object_roi: Roi | None = None
    axis: tuple[np.ndarray, np.ndarray] | None = None


def fixed_rig(views: Sequence[ViewCloud], scanset: ScanSet) -> bool:
    """True when every view is a capture by one rig: the same image size, camera intrinsics and
    distortion (a turntable set; ``turntable`` angles given count only with such captures, since a
    static test needs the views' pixels to line up)."""
    if len(views) < 2 or any(v.range_image is None or v.K is None or v.pixel is None for v in views):
        return False
    first = views[0]
    return all(v.range_image.shape == first.range_image.shape and np.allclose(v.K, first.K)
               and np.allclose(v.dist, first.dist) for v in views)


def static_samples(views: Sequence[ViewCloud], params: IsolationParams) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Per view, a (N,) bool mask of the samples that do not move between views (see the module
    docstring); and the figures: the noise in sample sizes and the depth tolerance used.

    views : captured views of one fixed rig (:func:`fixed_rig`), range images (H, W) float32 mm.
    """
    V = len(views)
    f = float(views[0].K[0, 0])
    Z = np.stack([np.asarray(v.range_image, np.float32) for v in views])  # (V, H, W) mm
    finite = np.isfinite(Z)
    seen = finite.sum(axis=0)
    shared = seen >= 2
    # Noise in sample sizes: the median deviation from the per-pixel median where a pixel is seen
    # twice or more; most pixels of a turntable image are static, so the median is the noise's.
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pixels no view saw: NaN, as meant
        med = np.nanmedian(np.where(shared[None], Z, np.nan), axis=0)
        dev = np.abs(Z - med[None]) / (Z / f)
    dev_ok = dev[finite & shared[None]]
    sigma = 1.4826 * float(np.median(dev_ok)) if dev_ok.size else 0.1
    sigma = max(sigma, 0.01)
    tol_units = params.agree_sigmas * sigma
    need = params.min_agree_views if V > 3 else 2
    count = np.zeros(Z.shape, np.int16)
    with np.errstate(invalid="ignore"):
        tol = np.float32(tol_units / f) * Z  # (V, H, W) mm
        for w in range(V):
            count += np.abs(Z - Z[w][None]) <= tol
        strict = finite & (count >= need)
        # The static depth at every pixel seen as static, filled into what the object hides.
        zsum = np.where(strict, Z, 0.0).sum(axis=0, dtype=np.float64)
        n = strict.sum(axis=0)
        background = np.where(n > 0, zsum / np.maximum(n, 1), 0.0).astype(np.float32)
        have = (n > 0).astype(np.float32)
        r = max(2, int(round(params.fill_fraction * Z.shape[2])))
        box = (2 * r + 1, 2 * r + 1)
        num = cv2.boxFilter(background * have, -1, box, normalize=False, borderType=cv2.BORDER_REPLICATE)
        den = cv2.boxFilter(have, -1, box, normalize=False, borderType=cv2.BORDER_REPLICATE)
        filled = np.where(have > 0, background, np.where(den > 0.25 * box[0] * box[1], num / np.maximum(den, 1e-6),
                                                         np.nan)).astype(np.float32)
        # A smooth background only: a blend across a depth step (a wall behind a table) matches nothing.
        on_background = finite & (np.abs(Z - filled[None]) <= tol)
    static_px = strict | on_background
    masks = [static_px[i][v.pixel[:, 1], v.pixel[:, 0]] for i, v in enumerate(views)]
    figures = {"noise_sample_sizes": round(sigma, 4), "tolerance_sample_sizes": round(tol_units, 4),
               "views_that_must_agree": int(need)}
    return masks, figures


# --------------------------------------------------------------------------------------- support plane


def _ransac_planes(xyz: np.ndarray, tol: float, planes: int, rng: np.random.Generator,
                   hypotheses: int = 400) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Up to ``planes`` planes found one after another by RANSAC on ``xyz`` (N, 3) mm, each refined
    by least squares on its inliers; returns (unit normal, offset d with n.x + d = 0, inlier mask)."""
    out = []
    left = np.ones(len(xyz), bool)
    for _ in range(planes):
        idx = np.flatnonzero(left)
        if len(idx) < 50:
            break
        pts = xyz[idx]
        sub = pts[rng.choice(len(pts), size=min(len(pts), 4000), replace=False)]
        tri = sub[rng.integers(0, len(sub), size=(hypotheses, 3))]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(nrm, axis=1)
        ok = length > 1e-9
        nrm, tri = nrm[ok] / length[ok, None], tri[ok]
        if not len(nrm):
            break
        d = -np.einsum("ij,ij->i", nrm, tri[:, 0])
        score = (np.abs(sub @ nrm.T + d) <= tol).sum(axis=0)
        best = int(np.argmax(score))
        n, dd = nrm[best], d[best]
        for _ in range(2):  # refine on the inliers
            inl = np.abs(pts @ n + dd) <= tol
            if inl.sum() < 3:
                break
            c = pts[inl].mean(axis=0)
            _, _, vt = np.linalg.svd(pts[inl] - c, full_matrices=False)
            n = vt[2]
            dd = -float(n @ c)
        inl = np.abs(pts @ n + dd) <= tol
        if inl.sum() < 50:
            break
        mask = np.zeros(len(xyz), bool)
        mask[idx[inl]] = True
        out.append((n, float(dd), mask))
        left &= ~mask
    return out


def support_plane(static_xyz: np.ndarray, object_xyz: np.ndarray, tol: float,
                  max_gap_share: float = IsolationParams.support_gap,
                  seed: int = 0) -> tuple[np.ndarray, float] | None:
    """The plane the object stands on: of the planes RANSAC finds among the static samples near the
    object (``static_xyz`` (N, 3) mm), the one with (almost) all of ``object_xyz`` (M, 3) on one
    side that comes closest to touching it. Returns (unit normal pointing to the object, offset d
    with ``n.x + d`` the signed height above the plane in mm) or None.

    The object's lowest seen samples (1st percentile of their heights) may stand up to
    ``max_gap_share`` of its height above the plane, or 20 tolerances if that is more: a camera
    above the table does not see under a rounded body's foot (the simulated teapot's lowest seen
    samples are 9.8 mm above its plate), and a bound in sample sizes alone made the plate vanish
    when the camera's resolution doubled."""
    if len(static_xyz) < 50 or len(object_xyz) < 50:
        return None
    rng = np.random.default_rng(seed)
    best: tuple[float, np.ndarray, float] | None = None
    for n, d, mask in _ransac_planes(static_xyz, tol, 4, rng):
        h = object_xyz @ n + d
        if np.median(h) < 0:
            n, d, h = -n, -d, -h
        above = float(np.mean(h >= -3.0 * tol))
        gap, top = (float(x) for x in np.percentile(h, [1, 99]))
        if above < 0.97 or gap > max(20.0 * tol, max_gap_share * top) or mask.sum() < 0.02 * len(static_xyz):
            continue
        if best is None or gap < best[0]:
            best = (gap, n, d)
    return None if best is None else (best[1], best[2])


# --------------------------------------------------------------------------------------- the object


def _clusters(xyz: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Connected clusters of points (N, 3) mm on a grid of ``step`` mm (cells touching by a face,
    an edge or a corner connect). Returns each point's cluster label (N,) and the labels' sizes."""
    keys = np.floor(xyz / step).astype(np.int64)
    cells, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    pairs = cKDTree(cells.astype(np.float64)).query_pairs(1.75, output_type="ndarray")
    C = len(cells)
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(C, C))
    _, cell_label = connected_components(graph, directed=False)
    label = cell_label[inverse]
    return label, np.bincount(label)


def _sphere(xyz: np.ndarray, margin: float) -> Roi:
    lo, hi = np.percentile(xyz, 0.1, axis=0), np.percentile(xyz, 99.9, axis=0)
    centre = 0.5 * (lo + hi)
    # A few stray samples (mixed pixels at the silhouette) must not inflate the sphere.
    radius = float(np.percentile(np.linalg.norm(xyz - centre, axis=1), 99.9)) + margin
    return Roi(center=centre, radius=radius)


def isolate_object(views: Sequence[ViewCloud], scanset: ScanSet,
                   params: IsolationParams | None = None) -> Isolation:
    """The views reduced to the object (see the module docstring).

    Raises :class:`~shared.core.errors.InputError` when nothing but static geometry is left (a set
    that is all backdrop), naming the share found static.
    """
    params = params or IsolationParams()
    names = [v.name for v in views]
    if not fixed_rig(views, scanset):
        cropped = [crop_to_roi(v, scanset.roi) for v in views]
        rep = {"fixed_rig": False, "object": None if scanset.roi is None else {**scanset.roi.to_json(), "source": "roi"}}
        return Isolation(registration=cropped, fusion=cropped, report=rep, object_roi=scanset.roi)
    static, figures = static_samples(views, params)
    size = float(np.median(np.concatenate([v.size[:: max(1, len(v) // 20000)] for v in views])))
    total = int(sum(len(v) for v in views))
    n_static = int(sum(int(m.sum()) for m in static))
    foreign = _foreign_backgrounds(static, params)
    if foreign:
        log.warning("views whose background differs from the rest's (not this rig's scene?): %s; their samples are "
                    "cropped to the object found in the others", ", ".join(names[i] for i in foreign))
    # A view whose background is not the others' looks all moving: left out of the object's search
    # (its backdrop would join the object's cluster), cropped to the object found in the others below.
    moving = [np.zeros(0, np.int64) if i in foreign else np.flatnonzero(~m) for i, m in enumerate(static)]
    pooled = np.concatenate([v.xyz[k] for v, k in zip(views, moving, strict=True)])
    owner = np.concatenate([np.full(len(k), i, np.int32) for i, k in enumerate(moving)])
    if len(pooled) < params.min_object_share * total or len(pooled) < 200:
        raise InputError("views", f"every view shows only geometry that does not turn ({100.0 * n_static / total:.1f} % "
                                  "of the samples static at the same pixel and depth in every view): all backdrop, "
                                  "no object on the turntable?")
    if scanset.roi is not None:
        d = pooled - scanset.roi.center
        region = np.einsum("ij,ij->i", d, d) <= scanset.roi.radius**2
        roi, source = scanset.roi, "roi"
    else:
        label, sizes = _clusters(pooled, params.cluster_step * size)
        region = _object_cluster(label, sizes, owner, len(views))
        roi, source = None, "found"
    if region.sum() < 200:
        raise InputError("views", f"no object is left once the static geometry is removed ({int(region.sum())} samples "
                                  f"move between views, {100.0 * n_static / total:.1f} % are static): all backdrop?")
    first = _sphere(pooled[region], 0.0)
    # The support: planes among the static samples near the object.
    tol = params.support_tolerance * size
    near = []
    for v, m in zip(views, static, strict=True):
        s = v.xyz[m]
        d = s - first.center
        near.append(s[np.einsum("ij,ij->i", d, d) <= (1.15 * first.radius) ** 2])
    near_xyz = np.concatenate(near)
    plane = support_plane(near_xyz[:: max(1, len(near_xyz) // 200000)], pooled[region][:: max(1, int(region.sum()) // 50000)],
                          tol, params.support_gap)
    support_removed = 0
    disc = None
    if plane is not None:
        n, d = plane
        above = pooled @ n + d > tol
        support_removed = int((region & ~above).sum())
        region &= above
        if source == "found":  # the foot's ring of plate may have joined the object: cluster again
            label, sizes = _clusters(pooled[region], params.cluster_step * size)
            keep = _object_cluster(label, sizes, owner[region], len(views))
            idx = np.flatnonzero(region)
            region[idx[~keep]] = False
        disc = _disc(_plane_samples(views, static, n, d, tol, first.center, params.disc_reach * first.radius), n, d, tol,
                     pooled[region])
    if region.sum() < max(200, params.min_object_share * total):
        raise InputError("views", f"every view shows only geometry that does not turn ({100.0 * n_static / total:.1f} % "
                                  f"of the samples static, {100.0 * support_removed / total:.1f} % support; what moves "
                                  f"and stands on it, {100.0 * region.sum() / total:.2f} %, is under the "
                                  f"{100 * params.min_object_share:g} % an object needs): all backdrop, no object on "
                                  "the turntable?")
    if roi is None:
        roi = _sphere(pooled[region], 2.0 * params.cluster_step * size)
    reg_views, fus_views, per_view = [], [], []
    starts = np.concatenate([[0], np.cumsum([len(k) for k in moving])])
    for i, v in enumerate(views):
        keep = moving[i][region[starts[i]:starts[i + 1]]]
        if i in foreign:
            d = v.xyz - roi.center
            inside = ~static[i] & (np.einsum("ij,ij->i", d, d) <= roi.radius**2)
            if plane is not None:
                inside &= v.xyz @ plane[0] + plane[1] > tol
            keep = np.flatnonzero(inside)
        obj = v.subset(keep)
        reg_views.append(obj)
        sup = np.zeros(0, np.int64)
        if params.keep_support and disc is not None:
            h = v.xyz @ disc["normal"] + disc["offset"]
            r = np.linalg.norm((v.xyz - disc["centre"]) - np.outer(h, disc["normal"]), axis=1)
            sup = np.flatnonzero((np.abs(h) <= tol) & (r <= disc["radius"]))
            sup = np.setdiff1d(sup, keep)
        fus_views.append(obj if not len(sup) else v.subset(np.sort(np.concatenate([keep, sup]))))
        per_view.append({"name": names[i], "samples": len(v), "static": int(static[i].sum()),
                         "object": len(keep), "support_kept": len(sup),
                         "other": int(len(v) - static[i].sum() - len(keep))})
    report = {
        "fixed_rig": True, **figures,
        "samples": total, "static": n_static, "support_removed": support_removed,
        "clutter_removed": int(len(pooled) - region.sum() - support_removed),
        "object_samples": int(region.sum()), "support_kept": bool(params.keep_support and disc is not None),
        "support_plane": None if plane is None else {
            "normal": [round(float(x), 6) for x in plane[0]], "offset_mm": round(float(plane[1]), 4),
            "disc": None if disc is None else {"centre_mm": [round(float(x), 3) for x in disc["centre"]],
                                               "radius_mm": round(float(disc["radius"]), 3)}},
        "object": {**roi.to_json(), "source": source},
        "foreign_background": [names[i] for i in foreign],
        "per_view": per_view,
    }
    log.info("static removal: %d of %d samples static, %d support, object %d samples in %s (%s)", n_static, total,
             support_removed, int(region.sum()), roi.to_json(), source)
    axis = None if disc is None else (np.asarray(disc["normal"], np.float64), np.asarray(disc["centre"], np.float64))
    return Isolation(registration=reg_views, fusion=fus_views, report=report, object_roi=roi, axis=axis)


def _foreign_backgrounds(static: Sequence[np.ndarray], params: IsolationParams) -> list[int]:
    """Views whose share of static samples is under ``foreign_static_ratio`` of the other views'
    median: their background is not the one the rest share (a capture from another session or rig),
    so almost all of it looks as if it moved. Needs four views or more (a median of the others)."""
    share = np.array([float(m.mean()) if len(m) else 0.0 for m in static])
    if len(share) < 4:
        return []
    out = []
    for i in range(len(share)):
        others = float(np.median(np.delete(share, i)))
        if others >= 0.2 and share[i] < params.foreign_static_ratio * others:
            out.append(i)
    return out if len(out) < 0.5 * len(share) else []


def _object_cluster(label: np.ndarray, sizes: np.ndarray, owner: np.ndarray, n_views: int) -> np.ndarray:
    """(N,) bool: the points of the largest cluster that at least half the views contribute to."""
    seen_by = np.zeros((len(sizes), n_views), bool)
    seen_by[label, owner] = True
    # A cluster counts for a view when the view holds a few of its points, not one stray sample.
    counts = np.zeros((len(sizes), n_views), np.int64)
    np.add.at(counts, (label, owner), 1)
    views_in = (counts >= 20).sum(axis=1)
    ok = views_in >= max(1, (n_views + 1) // 2)
    if not ok.any():
        ok = views_in == views_in.max()
    best = int(np.argmax(np.where(ok, sizes, -1)))
    return label == best


def _plane_samples(views: Sequence[ViewCloud], static: Sequence[np.ndarray], n: np.ndarray, d: float, tol: float,
                   centre: np.ndarray, reach: float) -> np.ndarray:
    """(N, 3) mm the static samples within ``tol`` of the plane ``n.x + d = 0`` and ``reach`` mm of
    ``centre``: the plate's disc, which reaches past the object's sphere (the simulated teapot's
    sphere is centred 106 mm off the axis of a 201 mm plate; cut at the sphere, the disc's visible
    rim came out one-sided and its centre 13.8 mm off the axis, and the angle search failed)."""
    out = []
    for v, m in zip(views, static, strict=True):
        s = v.xyz[m]
        dc = s - centre
        out.append(s[(np.abs(s @ n + d) <= tol) & (np.einsum("ij,ij->i", dc, dc) <= reach**2)])
    return np.concatenate(out)


def _disc(static_xyz: np.ndarray, n: np.ndarray, d: float, tol: float, obj: np.ndarray) -> dict[str, Any] | None:
    """The plate's disc: the support plane's static samples around the object's foot (centre in the
    middle of those samples, radius where they thin out beyond the fullest ring: :func:`_rim`)."""
    on = static_xyz[np.abs(static_xyz @ n + d) <= tol]
    if len(on) < 50 or not len(obj):
        return None
    c = obj.mean(axis=0)
    centre = c - n * float(c @ n + d)
    radius = _rim(on, n, centre, tol)
    # The object's centroid is off the axis (it need not stand centred, and is not symmetric): the
    # disc's centre and radius come from its rim where the camera sees it whole, left and right
    # (across the line of sight) and the near side (the far side hides behind the object).
    toward = -(centre - n * float(centre @ n))  # the camera (origin) seen from the centre, in the plane
    if np.linalg.norm(toward) < 1e-6:
        return {"normal": n, "offset": d, "centre": centre, "radius": radius}
    e2 = toward / np.linalg.norm(toward)
    e1 = np.cross(n, e2)
    rel = on - centre
    inside = rel[np.linalg.norm(rel - np.outer(rel @ n, n), axis=1) <= radius]
    if len(inside) >= 50:
        lo, hi = np.percentile(inside @ e1, [0.5, 99.5])
        near = float(np.percentile(inside @ e2, 99.5))
        half = 0.5 * float(hi - lo)
        centre = centre + e1 * 0.5 * float(lo + hi) + e2 * (near - half)
        radius = min(radius, _rim(on, n, centre, tol))
    return {"normal": n, "offset": d, "centre": centre, "radius": radius}


def _rim(on: np.ndarray, n: np.ndarray, centre: np.ndarray, tol: float) -> float:
    """The radius (mm) where the plane's samples ``on`` (N, 3) thin out beyond their fullest ring
    about ``centre``: the object hides the disc's middle, and past the rim only a few mixed pixels
    of the silhouette (the rim's depth blended with the table's) and whatever else crosses the plane
    are left. Checked against the simulator's labels: the first ring under a tenth of the fullest
    ring's density (samples per unit area) is the rim; an empty ring never came (mixed pixels
    reached 181 mm on a 146 mm plate)."""
    r = np.linalg.norm((on - centre) - np.outer((on - centre) @ n, n), axis=1)
    width = max(4.0 * tol, 1e-3)
    rings = np.bincount(np.minimum((r / width).astype(np.int64), 100000)).astype(np.float64)
    density = rings / (np.arange(len(rings)) + 0.5)  # per unit area of each ring
    full = int(np.argmax(rings))
    thin = np.flatnonzero(density[full:] < 0.1 * density[full])
    return float(width * (full + thin[0])) if len(thin) else float(r.max())
