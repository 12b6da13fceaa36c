"""Seam levelling of the photograph bake: a smooth colour correction per view over the surface.

Waechter, Moehrle and Goesele ("Let There Be Color! Large-Scale Texturing of 3D Reconstructions",
ECCV 2014, section 5) level the brightness of the views' texture patches with an additive
correction per vertex and patch, solved as one sparse least-squares problem: corrected colours on
either side of a seam should agree, and the correction should change little between neighbouring
vertices of a patch. The photograph bake here blends the views that see a texel rather than
picking one, so every surface point where two views overlap is a "seam": the problem becomes

    min  sum_(o, k, l)  W_okl |g_k(o) - g_l(o) + D_okl|^2            (the views agree)
       + lambda  sum_(k, (o, p) edge)  |g_k(o) - g_k(p)|^2            (smooth per view)
       + sum_(k, o)  (mu + anchor w_k(o)) |g_k(o)|^2                  (the trusted views stay)

over a per-view log-colour correction ``g_k`` (3 channels) at the vertices ``o`` of a coarse proxy
of the surface, where ``D_okl`` is the weighted mean of ``log a_k - log a_l`` (view k's linear
albedo against view l's) over the surface samples nearest to ``o`` seen by both views, and
``w_k(o)`` view k's blending weight near ``o`` relative to the typical one (capped at 4): the views
a texel's colour mostly comes from keep theirs and the ones seen at a grazing angle, whose entry
into the blend makes the seam, come to them (without the anchor, levelling pulled the good views
towards the poor ones: the bunny's error per texel rose 1.5 %; with it, it stays). The
corrections are multiplicative (log domain): what differs between views is a scale (the
projector's irradiance model, the camera's response, light bounced from nearby), not an offset.
Waechter et al.'s local Poisson editing is not done: the bake blends views, so there is no hard
patch edge left for it to soften.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

log = logging.getLogger(__name__)

_LUMA = np.array([0.2126, 0.7152, 0.0722])


def proxy_surface(vertices: np.ndarray, faces: np.ndarray, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """A coarse proxy of a level's surface: (P, 3) float64 mm vertices and (E, 2) int64 unique edges.

    The level's vertices are split along its UV seams; they are welded by position first (the
    proxy must be one connected surface where the level is), then decimated to about
    ``target_faces`` faces (fast-simplification)."""
    import fast_simplification

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    scale = float(np.linalg.norm(np.ptp(v, axis=0))) or 1.0
    key = np.round(v / (scale * 1e-7)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    wv, wf = v[first], inverse.reshape(-1)[f]
    wf = wf[(wf[:, 0] != wf[:, 1]) & (wf[:, 1] != wf[:, 2]) & (wf[:, 0] != wf[:, 2])]
    if len(wf) > target_faces:
        pv, pf = fast_simplification.simplify(wv, wf.astype(np.int32), target_count=int(target_faces))
        if len(pf) > 0:
            wv, wf = np.asarray(pv, np.float64), np.asarray(pf, np.int64)
    e = np.sort(np.concatenate([wf[:, [0, 1]], wf[:, [1, 2]], wf[:, [2, 0]]]), axis=1)
    return wv, np.unique(e, axis=0)


def solve_corrections(alb: np.ndarray, wts: np.ndarray, owner: np.ndarray, edges: np.ndarray, n_proxy: int,
                      smoothness: float, max_factor: float, anchor: float = 0.0,
                      regulariser: float = 1e-3, max_iterations: int = 400) -> tuple[np.ndarray, dict]:
    """Per-view log-colour corrections at the proxy's vertices (the module docstring's problem).

    alb : (V, n, 3) linear albedo of n surface samples per view; wts : (V, n) their weights (0:
    the view does not see the sample, or left out as a highlight); owner : (n,) int the proxy vertex
    nearest each sample; edges : (E, 2) the proxy's edges. Returns (V, n_proxy, 3) float32
    corrections (multiply a view's albedo by their exponential), clipped to ``max_factor`` either
    way, and JSON-ready figures of the solve."""
    V, n = wts.shape
    la = np.log(np.maximum(alb, 1e-3)).astype(np.float32)
    # Dark samples carry noisy logarithms: their pairs count less.
    dark = np.clip((alb @ _LUMA.astype(np.float32)) / 0.05, 0.0, 1.0)
    keys, diffs, weights = [], [], []
    for k in range(V):
        for m in range(k + 1, V):
            both = np.flatnonzero((wts[k] > 0) & (wts[m] > 0))
            if len(both) == 0:
                continue
            w = np.minimum(wts[k, both], wts[m, both]) * np.minimum(dark[k, both], dark[m, both])
            d = np.clip(la[k, both] - la[m, both], -0.7, 0.7)  # a misplaced texture edge is not a seam
            keys.append((owner[both] * V + k) * V + m)
            diffs.append(d * w[:, None])
            weights.append(w)
    stats = {"pairs": 0, "unknowns": V * n_proxy}
    if not keys:
        return np.zeros((V, n_proxy, 3), np.float32), stats
    key = np.concatenate(keys)
    uk, inv = np.unique(key, return_inverse=True)
    W = np.bincount(inv, weights=np.concatenate(weights), minlength=len(uk))
    D = np.stack([np.bincount(inv, weights=c, minlength=len(uk)) for c in np.concatenate(diffs).T], 1)
    keep = W > 0
    uk, W, D = uk[keep], W[keep], D[keep] / W[keep, None]
    o, km = np.divmod(uk, V * V)
    k, m = np.divmod(km, V)
    # Data rows: a group's weight relative to the typical group's, capped (a vertex with many
    # samples should not drown its neighbours' smoothness).
    wd = np.sqrt(np.minimum(W / max(float(np.median(W)), 1e-12), 4.0))
    rows = np.arange(len(uk))
    A_data = sp.csr_matrix((np.concatenate([wd, -wd]), (np.concatenate([rows, rows]),
                                                        np.concatenate([k * n_proxy + o, m * n_proxy + o]))),
                           shape=(len(uk), V * n_proxy))
    b_data = -D * wd[:, None]
    # Smoothness: the proxy's graph Laplacian, once per view; the regulariser on the diagonal.
    E = np.asarray(edges, np.int64)
    adj = sp.coo_matrix((np.ones(2 * len(E)), (np.concatenate([E[:, 0], E[:, 1]]), np.concatenate([E[:, 1], E[:, 0]]))),
                        shape=(n_proxy, n_proxy)).tocsr()
    lap = sp.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj
    # Anchor: a view keeps its colour in proportion to how much it weighs near a vertex (the views
    # a texel's colour mostly comes from stay; the ones at a grazing angle come to them).
    wv = np.stack([np.bincount(owner, weights=wts[j], minlength=n_proxy) for j in range(V)])
    pos = wv[wv > 0]
    anchor_d = anchor * np.minimum(wv / max(float(np.median(pos)) if len(pos) else 1.0, 1e-12), 4.0)
    M = (A_data.T @ A_data + sp.kron(sp.identity(V), smoothness * lap)
         + sp.diags(regulariser + anchor_d.ravel())).tocsc()
    g, iterations = _pcg(M.tocsr(), np.asarray(A_data.T @ b_data), max_iterations)
    stats["iterations"] = iterations
    g = np.asarray(g, np.float64).reshape(V, n_proxy, 3)
    lim = float(np.log(max_factor))
    clipped = float((np.abs(g) > lim).mean())
    g = np.clip(g, -lim, lim)
    resid_before = float(np.sqrt(np.average((D ** 2).sum(1), weights=W)))
    after = D + g[k, o] - g[m, o]
    resid_after = float(np.sqrt(np.average((after ** 2).sum(1), weights=W)))
    stats.update({"pairs": int(len(uk)), "rms_log_disagreement": [round(resid_before, 4), round(resid_after, 4)],
                  "clipped_share": round(clipped, 5)})
    return g.astype(np.float32), stats


def _pcg(M: sp.csr_matrix, B: np.ndarray, max_iterations: int, rtol: float = 1e-5) -> tuple[np.ndarray, int]:
    """Solve M X = B (M symmetric positive definite, B (n, c)) by conjugate gradients with a diagonal
    preconditioner, all columns at once. A direct factorisation of the 65 k unknowns of an 8-view
    set took SuperLU 24 s; scipy's ``cg`` spent most of its time in multi-threaded BLAS dot
    products of short vectors on a loaded machine: the products here are numpy's own reductions."""
    dinv = (1.0 / M.diagonal())[:, None]
    X = np.zeros_like(B)
    R = B.copy()
    Z = dinv * R
    Pd = Z.copy()
    rz = np.einsum("ij,ij->j", R, Z)
    stop = rtol * np.sqrt(np.einsum("ij,ij->j", B, B)) + 1e-30
    k = 0
    while k < max_iterations:
        k += 1
        Q = M @ Pd
        alpha = rz / np.maximum(np.einsum("ij,ij->j", Pd, Q), 1e-300)
        X += alpha * Pd
        R -= alpha * Q
        if (np.sqrt(np.einsum("ij,ij->j", R, R)) <= stop).all():
            break
        Z = dinv * R
        rz_new = np.einsum("ij,ij->j", R, Z)
        Pd = Z + (rz_new / np.maximum(rz, 1e-300)) * Pd
        rz = rz_new
    return X, k
