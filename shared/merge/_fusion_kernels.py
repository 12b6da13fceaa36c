"""Compiled kernels of the fusion (numba, ``nogil``: the fusion runs them from several threads).

- :func:`free_space_violations`: the points of one view that another captured view saw through
  (the rigid motion and the tolerance are applied per point, so no moved copy of the view and no
  tolerance array is allocated for each of the ``V (V - 1)`` pairs);
- :func:`cell_keys`: the merge grid's cell key of every sample in two passes, without the (N, 3)
  integer and float temporaries of the same arithmetic in numpy.
"""

from __future__ import annotations

import numba
import numpy as np

from shared.core.jit import full


@numba.njit(cache=True, nogil=True)
def free_space_violations(xyz, size, rel, K, dist, zmin, size_k, tol_factor, tol_mm, bad):  # pragma: no cover
    """Mark the points of a view that lie in front of another view's measured surface.

    xyz : (N, 3) float64 points in their own view's frame (mm); size : (N,) float32 their sample
    sizes (mm). rel : (4, 4) float64 motion from that frame into view k's camera frame. K (3, 3),
    dist (5,) float64: view k's intrinsics (pixels) and OpenCV distortion k1 k2 p1 p2 k3. zmin :
    (H, W) float32 the nearest measured Z around each of view k's pixels (0: nothing measured).
    A point is a violation (``bad[i] = True``; other entries are left alone) when it projects into
    the image with ``Z < zmin - (tol_factor * max(size[i], size_k) + tol_mm)``. Returns the
    number of points newly marked.
    """
    H, W = zmin.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    marked = 0
    for i in range(xyz.shape[0]):
        x0, y0, z0 = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        z = rel[2, 0] * x0 + rel[2, 1] * y0 + rel[2, 2] * z0 + rel[2, 3]
        if z <= 1e-6:
            continue
        x = (rel[0, 0] * x0 + rel[0, 1] * y0 + rel[0, 2] * z0 + rel[0, 3]) / z
        y = (rel[1, 0] * x0 + rel[1, 1] * y0 + rel[1, 2] * z0 + rel[1, 3]) / z
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        u = int(np.floor(fx * xd + cx + 0.5))
        v = int(np.floor(fy * yd + cy + 0.5))
        if u < 0 or u >= W or v < 0 or v >= H:
            continue
        zs = zmin[v, u]
        if zs <= 0.0:
            continue
        tol = tol_factor * max(np.float64(size[i]), size_k) + tol_mm
        if z < zs - tol and not bad[i]:
            bad[i] = True
            marked += 1
    return marked


@numba.njit(cache=True, nogil=True)
def cell_keys(xyz, size, normals, s0, cell_factor, keys, level):  # pragma: no cover
    """Cell key of every sample on the size-scaled merge grid.

    xyz : (N, 3) float64 mm; size : (N,) float32 mm; normals : (N, 3) float32 unit; s0 : the
    smallest positive size (mm); cell_factor : cell width in sample sizes. A sample's size class is
    ``level = round(log2(max(size, s0) / s0))``, its cell ``floor(xyz / (cell_factor * s0 *
    2**level))`` (offset so the smallest index is 0), its side the normal's dominant axis and sign
    (0..5). Writes keys (N,) int64 ``(((level * D0 + i) * D1 + j) * D2 + k) * 6 + side`` (levels
    offset to start at 0) and level (N,) int64 (not offset).
    """
    n = xyz.shape[0]
    lo = full(3, np.iinfo(np.int64).max, np.int64)
    hi = full(3, np.iinfo(np.int64).min, np.int64)
    lmin = np.iinfo(np.int64).max
    for p in range(n):
        s = max(np.float64(size[p]), s0)
        lv = np.int64(np.floor(np.log2(s / s0) + 0.5))
        level[p] = lv
        lmin = min(lmin, lv)
        cell = cell_factor * s0 * np.exp2(np.float64(lv))
        for a in range(3):
            c = np.int64(np.floor(xyz[p, a] / cell))
            lo[a] = min(lo[a], c)
            hi[a] = max(hi[a], c)
    d1 = hi[1] - lo[1] + 1
    d2 = hi[2] - lo[2] + 1
    d0 = hi[0] - lo[0] + 1
    for p in range(n):
        cell = cell_factor * s0 * np.exp2(np.float64(level[p]))
        i = np.int64(np.floor(xyz[p, 0] / cell)) - lo[0]
        j = np.int64(np.floor(xyz[p, 1] / cell)) - lo[1]
        k = np.int64(np.floor(xyz[p, 2] / cell)) - lo[2]
        ax = 0
        best = abs(normals[p, 0])
        for a in range(1, 3):
            if abs(normals[p, a]) > best:
                best = abs(normals[p, a])
                ax = a
        side = 2 * ax + (1 if normals[p, ax] > 0 else 0)
        keys[p] = ((((level[p] - lmin) * d0 + i) * d1 + j) * d2 + k) * 6 + side


@numba.njit(cache=True, nogil=True)
def ray_terms(xyz, normals, dist, cos):  # pragma: no cover
    """Distance from the sensor and cosine of the viewing angle of every sample of a view.

    xyz : (N, 3) float64 mm in the view's own frame (the sensor at the origin); normals : (N, 3)
    float32 unit, facing the sensor. Writes dist (N,) float64 mm and cos (N,) float64
    ``-n . x / |x|`` (1: seen head-on).
    """
    for i in range(xyz.shape[0]):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        d = np.sqrt(x * x + y * y + z * z)
        dist[i] = d
        cos[i] = -(normals[i, 0] * x + normals[i, 1] * y + normals[i, 2] * z) / max(d, 1e-9)


@numba.njit(cache=True, nogil=True)
def gather_moved(xyz, normals, sel, P, out_xyz, out_n, offset):  # pragma: no cover
    """Copy the selected samples of a view, moved by a rigid motion, into the fused arrays.

    xyz : (N, 3) float64 mm; normals : (N, 3) float32; sel : (M,) int64 indices of the samples
    kept; P : (4, 4) float64 view -> set frame. Writes rows ``offset .. offset + M`` of out_xyz
    (float64) and out_n (float32): ``R x + T`` and ``R n``. One pass, no (M, 3) temporaries
    (numpy's ``(M, 3) @ (3, 3)`` measured 4x slower than this on 750 000 samples).
    """
    for m in range(sel.shape[0]):
        i = sel[m]
        o = offset + m
        for a in range(3):
            out_xyz[o, a] = P[a, 0] * xyz[i, 0] + P[a, 1] * xyz[i, 1] + P[a, 2] * xyz[i, 2] + P[a, 3]
            out_n[o, a] = P[a, 0] * normals[i, 0] + P[a, 1] * normals[i, 1] + P[a, 2] * normals[i, 2]
