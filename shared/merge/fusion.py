"""Fusion: one clean cloud from the registered views.

In: the views (:class:`~shared.merge.views.ViewCloud`, own frames, mm) and their poses (V, 4, 4).
Out: a :class:`FusedCloud` in the scan set's frame, in the point-cloud contract (``x y z``, colour,
normal, ``size``) plus a per-point ``view`` (the view that contributed most) and ``confidence``.

1. **Confidence** of every sample: the decoder's contrast (captured views) times the cosine of
   the viewing angle times ``(d_ref / d)^2`` for the distance ``d`` from the sensor (a sample seen
   head-on and near is better), clipped to [0, 1]. Cloud views without a sensor model get 1.
   Captured samples seen at grazing angles (``min_view_cos``) are dropped.
2. **Free-space violations**: a sample of one view that lies, seen from another captured view, in
   front of the surface that view measured (by more than ``free_space_tolerance`` sample sizes,
   at all of the 3x3 pixels around its projection) is in space that view saw through: an outlier
   or a background point; it is removed.
3. **Merge on a grid scaled by the samples' own size**: each sample goes to the grid of its size
   class (powers of two of the smallest size) with cells ``cell_factor`` sizes wide; the samples in
   a cell, from any view, with normals facing the same way (the same of six axis directions: the
   two sides of a thin part or a rim stay apart), merge into one point whose position, normal and
   colour are confidence-weighted means (so overlapping views average their noise instead of
   piling up).
4. **Albedo** (views that carry it, :mod:`shared.scan.albedo`): in each cell, the samples whose
   luminance exceeds the cell's median by more than ``specular_ratio`` are specular highlights
   (a glint lights one view, not the others) and are left out; the rest average weighted by
   confidence times the projector's cosine. Cells without albedo keep weight 0 (renderers use the
   shaded colour there).
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.core.threads import cpu_budget
from shared.formats.ply import CLOUD_DTYPE, read_header, write_ply_records
from shared.merge._fusion_kernels import cell_keys, free_space_violations, gather_moved, ray_terms
from shared.merge._kernels import grid_reduce
from shared.merge.views import ViewCloud
from shared.scan.albedo import encode_srgb

log = logging.getLogger(__name__)

__all__ = ["FUSED_DTYPE", "FusedCloud", "FusionParams", "fuse_views", "read_fused", "sample_confidence",
           "write_fused"]

#: The fused cloud's PLY layout: the cloud contract plus the contributing view and the confidence.
FUSED_DTYPE = np.dtype([*((n, CLOUD_DTYPE[n]) for n in CLOUD_DTYPE.names or ()), ("view", "<u2"),
                        ("confidence", "<f4")])


@dataclass(frozen=True)
class FusionParams:
    """cell_factor : grid cell width in sample sizes. free_space_tolerance : sample sizes a point
    must lie in front of another view's surface to count as a free-space violation (plus
    ``free_space_mm``). min_confidence : samples below it are dropped before merging.
    min_view_cos : captured samples seen more obliquely than this (cosine of the angle between the
    normal and the ray) are dropped: grazing samples carry most of a scan's error, and in a scan set
    another view sees the same surface head-on (measured on the virtual rig: dropping those below
    0.35 halves the merged RMS error). specular_ratio : a sample's albedo luminance over its cell's
    median above which it is taken for a specular highlight and left out of the cell's albedo.
    max_size_factor : no merged point's size exceeds this many median sizes, nor what the distance
    to its neighbours supports (beyond twice the median)."""

    cell_factor: float = 1.0
    free_space_tolerance: float = 6.0
    free_space_mm: float = 0.5
    min_confidence: float = 0.02
    min_view_cos: float = 0.35
    specular_ratio: float = 1.35
    max_size_factor: float = 4.0


@dataclass
class FusedCloud:
    """N merged points in the scan set's frame (mm); arrays row-aligned.

    xyz (N, 3) float32, rgb (N, 3) uint8, normals (N, 3) float32, size (N,) float32 mm,
    view (N,) uint16, confidence (N,) float32 (sum of the merged samples' confidences),
    views_per_point (N,) uint8 (how many views the point merges). ``stats`` counts (JSON-ready).
    albedo (N, 3) float32 and albedo_weight (N,) float32 when any view carries albedo.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    normals: np.ndarray
    size: np.ndarray
    view: np.ndarray
    confidence: np.ndarray
    views_per_point: np.ndarray
    stats: dict
    albedo: np.ndarray | None = None  # (N, 3) float32 linear, NaN where no view measured it
    albedo_weight: np.ndarray | None = None  # (N,) float32, 0 where none

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def _ray_terms(view: ViewCloud) -> tuple[np.ndarray, np.ndarray]:
    """(N,) float64 distance from the sensor (mm) and viewing-angle cosine of every sample."""
    d = np.empty(len(view))
    cos = np.empty(len(view))
    ray_terms(np.ascontiguousarray(view.xyz, np.float64), np.ascontiguousarray(view.normals, np.float32), d, cos)
    return d, cos


def sample_confidence(view: ViewCloud, terms: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(N,) float32 confidence in [0, 1] of each sample of a view (see the module docstring);
    ``terms`` are the view's :func:`_ray_terms` when already computed."""
    conf = view.confidence.astype(np.float64)
    if view.K is None:
        return np.clip(conf, 0.0, 1.0).astype(np.float32)
    d, cos = terms if terms is not None else _ray_terms(view)
    d_ref = float(np.median(d))
    dist_term = np.clip((d_ref / np.maximum(d, 1e-9)) ** 2, 0.0, 1.5)
    return np.clip(conf * np.clip(cos, 0.0, 1.0) * dist_term, 0.0, 1.0).astype(np.float32)


def _free_space_mask(views: list[ViewCloud], poses: np.ndarray, params: FusionParams, threads: int) -> list[np.ndarray]:
    """Per view, True where a sample is NOT in another captured view's free space.

    For each captured view k (its eroded range image built once), every other view's points are
    tested in ``threads`` threads (the kernel releases the GIL), one view per task.
    """
    bad = [np.zeros(len(v), np.bool_) for v in views]
    xyz = [np.ascontiguousarray(v.xyz, np.float64) for v in views]
    size = [np.ascontiguousarray(v.size, np.float32) for v in views]
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        for k, vk in enumerate(views):
            if vk.range_image is None or vk.K is None:
                continue
            z = np.nan_to_num(vk.range_image, nan=0.0).astype(np.float32)
            # The nearest surface around each pixel: a point must be in front of all of them.
            zmin = cv2.erode(z, np.ones((3, 3), np.uint8))
            size_k = float(np.nanmedian(vk.size)) if len(vk) else 0.0
            inv = np.linalg.inv(poses[k])
            K = np.asarray(vk.K, np.float64)
            dist = np.zeros(5)
            if vk.dist is not None:
                dist[: min(5, len(vk.dist))] = vk.dist[:5]

            def test(i: int, k: int = k, inv: np.ndarray = inv, K: np.ndarray = K, dist: np.ndarray = dist,
                     zmin: np.ndarray = zmin, size_k: float = size_k) -> None:
                free_space_violations(xyz[i], size[i], inv @ poses[i], K, dist, zmin, size_k,
                                      params.free_space_tolerance, params.free_space_mm, bad[i])

            list(pool.map(test, [i for i in range(len(views)) if i != k and len(views[i])]))
    return [~b for b in bad]


def fuse_views(views: list[ViewCloud], poses: np.ndarray, params: FusionParams | None = None,
               free_space: bool = True, threads: int | None = None) -> FusedCloud:
    """Fuse registered views into one cloud (see the module docstring).

    Parameters
    ----------
    views : the views in their own frames (mm).
    poses : (V, 4, 4) view -> scan set frame.
    params : see :class:`FusionParams`.
    free_space : remove free-space violations (needs captured views' range images).
    threads : threads of the free-space test (its kernel releases the GIL; None: the process's
        CPU budget, :func:`shared.core.threads.cpu_budget`; the result does not depend on it).
    """
    params = params or FusionParams()
    if not views:
        raise InputError("views", "nothing to fuse")
    poses = np.asarray(poses, np.float64)
    conf, grazing = [], []
    for v in views:
        terms = _ray_terms(v) if v.K is not None else None
        conf.append(sample_confidence(v, terms))
        grazing.append(None if terms is None else terms[1] < params.min_view_cos)
    threads = cpu_budget() if threads is None else threads
    keep = _free_space_mask(views, poses, params, threads) if free_space else [np.ones(len(v), bool) for v in views]
    n_in = int(sum(len(v) for v in views))
    n_free = int(sum(int((~k).sum()) for k in keep))
    keep = [k & (c >= params.min_confidence) for k, c in zip(keep, conf, strict=True)]
    n_oblique = 0
    for k, oblique in zip(keep, grazing, strict=True):
        if oblique is not None:
            n_oblique += int(np.count_nonzero(oblique & k))
            k &= ~oblique
    # The kept samples of every view, moved into the set frame, in one set of arrays (normals,
    # colours and confidences in their own dtypes: float64 copies of 10^7 samples cost gigabytes).
    sel = [np.flatnonzero(k) for k in keep]
    n = int(sum(len(s) for s in sel))
    if n == 0:
        raise InputError("views", "no sample survived the confidence and free-space tests")
    xyz = np.empty((n, 3))
    normals = np.empty((n, 3), np.float32)
    rgb = np.empty((n, 3), np.uint8)
    size = np.empty(n, np.float32)
    c = np.empty(n, np.float32)
    view = np.empty(n, np.uint16)
    with_albedo = any(v.albedo is not None for v in views)
    alb = np.full((n, 3), np.nan, np.float32) if with_albedo else None
    alb_w = np.zeros(n, np.float32) if with_albedo else None
    o = 0
    for v, P, s, cc in zip(views, poses, sel, conf, strict=True):
        part = slice(o, o + len(s))
        if alb is not None and alb_w is not None and v.albedo is not None and v.albedo_weight is not None:
            alb[part] = v.albedo[s]
            alb_w[part] = v.albedo_weight[s] * cc[s]
        gather_moved(np.ascontiguousarray(v.xyz, np.float64), np.ascontiguousarray(v.normals, np.float32), s, P,
                     xyz, normals, o)
        rgb[part] = v.rgb[s] if v.rgb is not None else 200
        size[part] = v.size[s]
        c[part] = cc[s]
        view[part] = v.index
        o += len(s)
    del sel, keep, conf, grazing
    # Size classes: powers of two of the smallest size, each with its own grid; samples whose
    # normals point different ways (the two sides of a thin part, a rim) never merge.
    s0 = max(float(np.min(size[size > 0])) if np.any(size > 0) else 1.0, 1e-6)
    key = np.empty(n, np.int64)
    level = np.empty(n, np.int64)
    cell_keys(xyz, size, normals, s0, params.cell_factor, key, level)
    # One sort gives the cells: runs of equal keys.
    order = np.argsort(key, kind="stable")
    sk = key[order]
    del key
    bounds = np.flatnonzero(sk[1:] != sk[:-1]) + 1
    del sk
    starts = np.concatenate([[0], bounds, [n]]).astype(np.int64)
    first = order[starts[:-1]]
    C = len(first)
    out_xyz = np.empty((C, 3))
    out_n = np.empty((C, 3))
    out_rgb = np.empty((C, 3))
    out_conf = np.empty(C)
    out_view = np.empty(C, np.int64)
    out_count = np.empty(C, np.int64)
    grid_reduce(order, starts, xyz, normals, rgb, c, view, out_xyz, out_n, out_rgb, out_conf, out_view, out_count)
    out_size = (np.float32(s0) * np.exp2(level[first]).astype(np.float32))
    fused_albedo = None
    if alb is not None and alb_w is not None:
        fused_albedo = _fuse_albedo(order, starts, alb, alb_w, params.specular_ratio)
    capped = _cap_sizes(out_xyz, out_size, params.max_size_factor)
    stats = {"samples": n_in, "free_space_violations": n_free,
             "oblique": n_oblique,
             "low_confidence": max(0, int(n_in - n_free - n_oblique - n)),
             "merged_points": int(C), "sizes_capped": capped, "size_classes": int(len(np.unique(level[first]))),
             "points_from_several_views": int(np.count_nonzero(out_count > 1))}
    if fused_albedo is not None:
        stats["albedo"] = fused_albedo[2]
    log.info("fused %d samples into %d points (%d free-space violations)", n_in, C, n_free)
    return FusedCloud(xyz=out_xyz.astype(np.float32), rgb=out_rgb.astype(np.uint8), normals=out_n.astype(np.float32),
                      size=out_size, view=out_view.astype(np.uint16), confidence=out_conf.astype(np.float32),
                      views_per_point=np.minimum(out_count, 255).astype(np.uint8), stats=stats,
                      albedo=None if fused_albedo is None else fused_albedo[0],
                      albedo_weight=None if fused_albedo is None else fused_albedo[1])


def _fuse_albedo(order: np.ndarray, starts: np.ndarray, alb: np.ndarray, weight: np.ndarray,
                 specular_ratio: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """Per cell (``order[starts[c]:starts[c+1]]``) the weighted mean albedo of its samples
    without the specular ones (luminance above ``specular_ratio`` times the cell's median).
    Returns (C, 3) float32 albedo (NaN where none), (C,) float32 summed weight, counts."""
    C = len(starts) - 1
    cell = np.repeat(np.arange(C), np.diff(starts))  # the cell of each sample, in ``order``
    a = alb[order]
    w = weight[order]
    ok = (w > 0) & np.isfinite(a).all(axis=1)
    y = np.where(ok, a @ np.array([0.2126, 0.7152, 0.0722], np.float32), np.inf)
    # Valid samples first within each cell, sorted by luminance: the median is at a fixed offset.
    by = np.lexsort((y, cell))
    n_ok = np.bincount(cell[ok], minlength=C)
    med = y[by[np.clip(starts[:-1] + (n_ok - 1) // 2, 0, max(len(by) - 1, 0))]]
    specular = ok & (n_ok[cell] >= 2) & (y > specular_ratio * med[cell])
    use = ok & ~specular
    wsum = np.bincount(cell[use], weights=w[use], minlength=C)
    out = np.full((C, 3), np.nan, np.float32)
    has = wsum > 0
    for ch in range(3):
        acc = np.bincount(cell[use], weights=(w * a[:, ch])[use], minlength=C)
        out[has, ch] = acc[has] / wsum[has]
    stats = {"samples": int(ok.sum()), "specular_rejected": int(specular.sum()),
             "points_with_albedo": int(has.sum()), "points_without": int(C - has.sum())}
    return out, wsum.astype(np.float32), stats


#: The albedo fields a fused cloud adds after :data:`FUSED_DTYPE` when it carries albedo.
ALBEDO_FIELDS = [("albedo_red", "u1"), ("albedo_green", "u1"), ("albedo_blue", "u1"), ("albedo_weight", "u1")]


def _cap_sizes(xyz: np.ndarray, size: np.ndarray, factor: float) -> int:
    """Shrink, in place, the sizes (C,) of merged points (C, 3) mm that their neighbourhood does not
    support: a point larger than twice the median size gets the mean distance to its 4 nearest merged
    points, clipped to [2, ``factor``] median sizes (an isolated sample of a sparse scan kept its own
    huge spacing: on the real dragon sizes up to 37.3 mm against a median 0.58 mm). Returns how many
    were shrunk."""
    if len(size) < 8:
        return 0
    med = float(np.median(size))
    big = np.flatnonzero(size > 2.0 * med)
    if not len(big):
        return 0
    d, _ = cKDTree(xyz).query(xyz[big], k=5, workers=cpu_budget())
    support = np.clip(d[:, 1:].mean(axis=1), 2.0 * med, factor * med).astype(np.float32)
    new = np.minimum(size[big], support)
    changed = int(np.count_nonzero(new < size[big]))
    size[big] = new
    return changed


def write_fused(path: str | os.PathLike[str], cloud: FusedCloud, comments: tuple[str, ...] = ()) -> Path:
    """Write the fused cloud as binary PLY (:data:`FUSED_DTYPE`, then :data:`ALBEDO_FIELDS` when it
    has albedo: sRGB-encoded, weight 255 times the mean projector cosine), atomically, in chunks."""
    n = len(cloud)
    chunk = 1 << 20
    dtype = FUSED_DTYPE if cloud.albedo is None else np.dtype(FUSED_DTYPE.descr + ALBEDO_FIELDS)

    def chunks():
        for s in range(0, n, chunk):
            sl = slice(s, min(n, s + chunk))
            rec = np.empty(sl.stop - sl.start, dtype)
            rec["x"], rec["y"], rec["z"] = cloud.xyz[sl].T
            rec["red"], rec["green"], rec["blue"] = cloud.rgb[sl].T
            rec["nx"], rec["ny"], rec["nz"] = cloud.normals[sl].T
            rec["size"] = cloud.size[sl]
            rec["view"] = cloud.view[sl]
            rec["confidence"] = cloud.confidence[sl]
            if cloud.albedo is not None and cloud.albedo_weight is not None:
                a = cloud.albedo[sl]
                none = ~np.isfinite(a).all(axis=1)
                enc = encode_srgb(np.nan_to_num(a, nan=0.0))
                enc[none] = 0
                rec["albedo_red"], rec["albedo_green"], rec["albedo_blue"] = enc.T
                cnt = np.maximum(cloud.views_per_point[sl], 1)
                wq = np.clip(np.rint(255 * cloud.albedo_weight[sl] / cnt), 1, 255)
                rec["albedo_weight"] = np.where(none, 0, wq)
            yield rec

    return write_ply_records(path, chunks(), n, dtype, comments=("units mm", "frame scan set (view 0 camera)",
                                                                          *comments))


def read_fused(path: str | os.PathLike[str]) -> np.ndarray:
    """The records of a fused cloud PLY (structured array with ``view`` and ``confidence``)."""
    path = Path(path)
    header = read_header(path)
    names = set(header.dtype.names or ())
    if not {"view", "confidence"} <= names:
        raise InputError(path, "not a fused cloud: no 'view' and 'confidence' properties")
    if header.fmt == "ascii":
        raise InputError(path, "fused clouds are binary PLY")
    return np.array(np.memmap(path, dtype=header.dtype, mode="r", offset=header.data_offset, shape=(header.count,)))
