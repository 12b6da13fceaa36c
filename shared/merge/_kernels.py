"""Compiled kernels of the merge (numba): normal equations of point-to-plane residuals, grid reductions."""

from __future__ import annotations

import numba
import numpy as np

from shared.core.jit import empty, zeros


@numba.njit(cache=True, nogil=True)
def point_to_plane_system(p, m, r, w):  # pragma: no cover
    """Normal equations of weighted point-to-plane residuals for a small rigid motion.

    p : (N, 3) float64 points (set frame), m : (N, 3) float64 target normals, r : (N,) residuals
    ``m . (p - q)``, w : (N,) weights. The motion ``x = (omega, v)`` moves ``p`` to
    ``p + omega x p + v``; residual ``r + J x`` with ``J = [p x m, m]``.
    Returns H (6, 6) = sum w J^T J, g (6,) = sum w J^T r, and the weighted squared-residual sum.
    """
    H = zeros((6, 6), np.float64)
    g = zeros(6, np.float64)
    e = 0.0
    J = empty(6, np.float64)
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
    sx = zeros(3, np.float64)
    sn = zeros(3, np.float64)
    sc = zeros(3, np.float64)
    seen = zeros(64, np.bool_)
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
def track_correspondences(src, src_n, rel, tgt, tgt_n, nbr, idx, descend, dmax, cos_min, q_out, m_out,
                          r_out):  # pragma: no cover
    """Point-to-plane correspondences of moved source samples, found or followed on the target's
    neighbour graph.

    src, src_n : (N, 3) float64 source samples (mm) and unit normals in their own frame; rel : (4, 4)
    float64 source -> target frame. tgt, tgt_n : (T, 3) float64 target samples and unit normals;
    nbr : (T, K) int32 each target's K nearest other targets. idx : (N,) int64, in: a target per
    source sample (-1: none), out: with ``descend``, the target reached by greedy descent on the
    graph from it (the nearest target when the start was near: poses change little between the
    iterations of a fit, so this replaces a k-d tree search). A pair is kept when the distance is at
    most ``dmax`` (mm) and the normals' cosine at least ``cos_min``. Writes the kept pairs compacted
    into q_out (N, 3) (moved source, target frame), m_out (N, 3) (target normal), r_out (N,)
    (``m . (q - target)``, mm) and returns how many.
    """
    n = src.shape[0]
    K = nbr.shape[1]
    d2max = dmax * dmax
    c = 0
    for k in range(n):
        t = idx[k]
        if t < 0:
            continue
        q0 = rel[0, 0] * src[k, 0] + rel[0, 1] * src[k, 1] + rel[0, 2] * src[k, 2] + rel[0, 3]
        q1 = rel[1, 0] * src[k, 0] + rel[1, 1] * src[k, 1] + rel[1, 2] * src[k, 2] + rel[1, 3]
        q2 = rel[2, 0] * src[k, 0] + rel[2, 1] * src[k, 1] + rel[2, 2] * src[k, 2] + rel[2, 3]
        e0 = q0 - tgt[t, 0]
        e1 = q1 - tgt[t, 1]
        e2 = q2 - tgt[t, 2]
        best = e0 * e0 + e1 * e1 + e2 * e2
        if descend:
            for _step in range(256):
                move = -1
                for a in range(K):
                    u = nbr[t, a]
                    f0 = q0 - tgt[u, 0]
                    f1 = q1 - tgt[u, 1]
                    f2 = q2 - tgt[u, 2]
                    d = f0 * f0 + f1 * f1 + f2 * f2
                    if d < best:
                        best = d
                        move = u
                if move < 0:
                    break
                t = move
            idx[k] = t
        if best > d2max:
            continue
        n0 = rel[0, 0] * src_n[k, 0] + rel[0, 1] * src_n[k, 1] + rel[0, 2] * src_n[k, 2]
        n1 = rel[1, 0] * src_n[k, 0] + rel[1, 1] * src_n[k, 1] + rel[1, 2] * src_n[k, 2]
        n2 = rel[2, 0] * src_n[k, 0] + rel[2, 1] * src_n[k, 1] + rel[2, 2] * src_n[k, 2]
        if n0 * tgt_n[t, 0] + n1 * tgt_n[t, 1] + n2 * tgt_n[t, 2] < cos_min:
            continue
        q_out[c, 0] = q0
        q_out[c, 1] = q1
        q_out[c, 2] = q2
        m_out[c, 0] = tgt_n[t, 0]
        m_out[c, 1] = tgt_n[t, 1]
        m_out[c, 2] = tgt_n[t, 2]
        r_out[c] = (tgt_n[t, 0] * (q0 - tgt[t, 0]) + tgt_n[t, 1] * (q1 - tgt[t, 1])
                    + tgt_n[t, 2] * (q2 - tgt[t, 2]))
        c += 1
    return c


@numba.njit(cache=True, nogil=True)
def voxel_representatives(order, starts, xyz, normals, out_xyz, out_n):  # pragma: no cover
    """One representative sample per voxel.

    ``order`` (N,) int64 sorts the points by voxel (stably: within a voxel in input order) and
    ``starts`` (C + 1,) int64 bounds each voxel's run in it; xyz, normals (N, 3) float64 (mm, unit).
    Per voxel, writes the point nearest the voxel's mean (the first such in input order) to
    out_xyz (C, 3) and the voxel's summed normal (not normalised) to out_n (C, 3).
    """
    C = starts.shape[0] - 1
    for c in range(C):
        s, e = starts[c], starts[c + 1]
        m0 = 0.0
        m1 = 0.0
        m2 = 0.0
        n0 = 0.0
        n1 = 0.0
        n2 = 0.0
        for t in range(s, e):
            k = order[t]
            m0 += xyz[k, 0]
            m1 += xyz[k, 1]
            m2 += xyz[k, 2]
            n0 += normals[k, 0]
            n1 += normals[k, 1]
            n2 += normals[k, 2]
        cnt = e - s
        m0 /= cnt
        m1 /= cnt
        m2 /= cnt
        best = np.inf
        bk = order[s]
        for t in range(s, e):
            k = order[t]
            d = (xyz[k, 0] - m0) ** 2 + (xyz[k, 1] - m1) ** 2 + (xyz[k, 2] - m2) ** 2
            if d < best:
                best = d
                bk = k
        out_xyz[c, 0] = xyz[bk, 0]
        out_xyz[c, 1] = xyz[bk, 1]
        out_xyz[c, 2] = xyz[bk, 2]
        out_n[c, 0] = n0
        out_n[c, 1] = n1
        out_n[c, 2] = n2
