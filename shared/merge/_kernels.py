"""Compiled kernels of the merge (numba): normal equations of point-to-plane residuals, grid reductions."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def point_to_plane_system(p, m, r, w):  # pragma: no cover
    """Normal equations of weighted point-to-plane residuals for a small rigid motion.

    p : (N, 3) float64 points (set frame), m : (N, 3) float64 target normals, r : (N,) residuals
    ``m . (p - q)``, w : (N,) weights. The motion ``x = (omega, v)`` moves ``p`` to
    ``p + omega x p + v``; residual ``r + J x`` with ``J = [p x m, m]``.
    Returns H (6, 6) = sum w J^T J, g (6,) = sum w J^T r, and the weighted squared-residual sum.
    """
    H = np.zeros((6, 6))
    g = np.zeros(6)
    e = 0.0
    J = np.empty(6)
    for k in range(p.shape[0]):
        wk = w[k]
        if wk <= 0.0:
            continue
        J[0] = p[k, 1] * m[k, 2] - p[k, 2] * m[k, 1]
        J[1] = p[k, 2] * m[k, 0] - p[k, 0] * m[k, 2]
        J[2] = p[k, 0] * m[k, 1] - p[k, 1] * m[k, 0]
        J[3] = m[k, 0]
        J[4] = m[k, 1]
        J[5] = m[k, 2]
        for a in range(6):
            ja = wk * J[a]
            g[a] += ja * r[k]
            for b in range(a, 6):
                H[a, b] += ja * J[b]
        e += wk * r[k] * r[k]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, e


@numba.njit(cache=True, nogil=True)
def grid_reduce(order, starts, xyz, normals, rgb, conf, view, out_xyz, out_n, out_rgb, out_conf, out_view,
                out_count):  # pragma: no cover
    """Confidence-weighted merge of the points of each grid cell.

    ``order`` sorts the points by cell; ``starts`` (C + 1,) bounds each cell's run in it. Per cell:
    position, normal and colour are the confidence-weighted means of its points (the normal
    renormalised), ``out_conf`` the sum of confidences, ``out_view`` the view of the most confident
    point and ``out_count`` the number of distinct views in the cell.
    """
    C = starts.shape[0] - 1
    # Scratch allocated once: an allocation per cell costs more than the cell's arithmetic.
    sx = np.zeros(3)
    sn = np.zeros(3)
    sc = np.zeros(3)
    seen = np.zeros(64, np.bool_)
    for c in range(C):
        sw = 0.0
        for a in range(3):
            sx[a] = 0.0
            sn[a] = 0.0
            sc[a] = 0.0
        best = -1.0
        bv = -1
        nviews = 0
        for t in range(starts[c], starts[c + 1]):
            k = order[t]
            wk = max(conf[k], 1e-6)
            sw += wk
            for a in range(3):
                sx[a] += wk * xyz[k, a]
                sn[a] += wk * normals[k, a]
                sc[a] += wk * rgb[k, a]
            if wk > best:
                best = wk
                bv = view[k]
            vk = view[k] % 64
            if not seen[vk]:
                seen[vk] = True
                nviews += 1
        nn = np.sqrt(sn[0] * sn[0] + sn[1] * sn[1] + sn[2] * sn[2])
        for a in range(3):
            out_xyz[c, a] = sx[a] / sw
            out_n[c, a] = sn[a] / nn if nn > 0 else 0.0
            out_rgb[c, a] = min(255.0, sc[a] / sw + 0.5)
        out_conf[c] = sw
        out_view[c] = bv
        out_count[c] = nviews
        for t in range(starts[c], starts[c + 1]):
            seen[view[order[t]] % 64] = False


@numba.njit(cache=True, nogil=True)
def free_space_hits(q, K, dist, zmin, tol, bad):  # pragma: no cover
    """Mark points that lie in front of a view's measured surface.

    q : (N, 3) float64 points in that view's camera frame (mm); K (3, 3), dist (5,) OpenCV
    k1 k2 p1 p2 k3; zmin (H, W) float32 nearest measured Z around each pixel (0: nothing measured);
    tol (N,) mm. Sets ``bad[k]`` when point k projects into the image and ``Z < zmin - tol``.
    """
    H, W = zmin.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for k in range(q.shape[0]):
        z = q[k, 2]
        if z <= 1e-6:
            continue
        x = q[k, 0] / z
        y = q[k, 1] / z
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        u = int(np.floor(fx * xd + cx + 0.5))
        v = int(np.floor(fy * yd + cy + 0.5))
        if u < 0 or u >= W or v < 0 or v >= H:
            continue
        zs = zmin[v, u]
        if zs > 0.0 and z < zs - tol[k]:
            bad[k] = True
