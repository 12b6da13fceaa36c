"""A least-squares predictor of a range band's samples (private kernels of
:mod:`shared.compress._lpred`; lossless mode).

An oversampling camera's sub-pixel depth is smooth and detailed at once: its samples are
correlated over more than the four neighbours the median and plane predictors see, in a way a
fixed predictor does not know (the decoder's errors run along the projector's stripes). The
encoder fits, per tile of a band's columns (:data:`TILE_SHIFT`), the linear prediction of each
sample from :data:`NLS` causal neighbours in the current row and the two above (as the
least-squares predictors of TMW and GLICBAWLS do per pixel; here once per tile, its weights in
the band's header), as differences from the N neighbour so that a constant depth is predicted
exactly whatever the weights. It is one more predictor a leaf may choose
(:data:`shared.compress._lpred.K_LS`), where its summed cost is the smallest.

A leaf's cost is not the code length (depth held constant over 2 x 2 pixels gives the local
predictors' errors of 0 at every other pixel, which code smaller than the fit's smaller
errors), so where the costs do not clearly favour it the encoder codes the band's residuals
both ways and keeps the smaller (:mod:`shared.compress._band`).

The fit is robust to the depth jumps at silhouettes, which would otherwise dominate the squares:
a first fit over every fifth row, then a second without the samples it predicts worse than
:data:`ROBUST` times its mean absolute error (clipped at :data:`ERR_CAP`).

Rows are the raster kernels' padded buffers (:mod:`shared.compress._rows`): ``rb`` the current
row (pixels before x decoded), ``ra`` the row above, ``rc`` the one above that; at a band's
first row both are its virtual row above, at its second ``rc`` is. Neighbours off the band's
sides take the nearest pixel of their row; off the current row's start, the W neighbour.
"""

from __future__ import annotations

import numpy as np

from shared.compress._rans import at
from shared.compress._rows import FINE, fill_row, target_row
from shared.core.jit import empty, helper, kernel, zeros

#: Neighbours of a sample (rows above, column offset): W, NW, NE, WW, NWW, NEE, NN, NNW, NNE,
#: WWW, NNWW, NNEE, then the row above out to 3 and 4 columns (N is the origin of the
#: differences). Measured, bits per valid sample with 12 / 14 / 16 of them: the relief at 1:1
#: 2.330 / 2.304 / 2.296, the bunny at 2:1 2.814 / 2.798 / 2.796, at 4:1 2.341 / 2.351 / 2.332,
#: the fandisk 2.737 / 2.726 / 2.724; 18 (two above, 3 columns out) within 0.5 % of 16 either way.
#: (The first six alone: the relief at 1:1 3.6 % larger than with 12, the bunny at 4:1 2.5 %.)
LS_DY = np.array([0, 1, 1, 0, 1, 1, 2, 2, 2, 0, 2, 2, 1, 1, 1, 1], np.int64)
LS_DX = np.array([-1, -1, 1, -2, -2, 2, 0, -1, 1, -3, -2, 2, -3, 3, -4, 4], np.int64)
NLS = 16
#: A band is fitted in tiles of 2**TILE_SHIFT columns, a set of weights each (local depth and
#: slopes), each tile's fit weighing the whole band's samples by TILE_PRIOR besides its own.
#: Measured on whole bench images, bits per valid sample, one set a band / tiles alone / tiles
#: with the prior: the relief at 1:1 2.337 / 2.325 / 2.330, the bunny at 2:1 2.824 / 2.797 /
#: 2.814, the fandisk 2.749 / 2.714 / 2.737, the bunny at 4:1 2.341 / 2.361 / 2.341, the spot
#: at 4:1 2.309 / 2.331 / 2.318 (tiles alone fit the 4:1 images' few samples a tile worse).
TILE_SHIFT = 9
TILE_PRIOR = 0.15
#: Weights in 2**-LS_SHIFT; |weight| <= LS_MAX (just under 8).
LS_SHIFT = 12
LS_MAX = (1 << 15) - 1
#: Differences from N are clamped to this many fine units (hostile inputs: the weighted sum stays
#: inside int64).
D_LIM = 1 << 30
#: The fit: every STEP-th row (coprime with the row periods of 2:1 and 4:1 sampling: every
#: fourth or eighth row coded the bunny at 4:1 0.8 and 1.6 % larger than every row, every second
#: or fifth within 0.2 %); a neighbour more than N_LIM fine units from N (a depth jump of
#: 256 quanta) leaves the sample out; the second fit leaves out the samples the first predicts
#: worse than ROBUST times its mean absolute error, itself clipped at ERR_CAP fine units.
STEP = 5
N_LIM = 256 * FINE
ROBUST = 4.0
ERR_CAP = 64.0 * FINE


# kernel helpers (shared.core.jit), inlined by LLVM (numba's IR inlining of their call sites cost seconds of compilation)
@helper(inline=False)
def _d(v, n):
    return min(max(v - n, -D_LIM), D_LIM)


@helper(inline=False)
def _neighbour(i, x, W, a, ra, rb, rc):
    """Neighbour i of :data:`LS_DY`, :data:`LS_DX` of pixel x (W ``a``), clamped to the band."""
    dy = LS_DY[i]
    xx = x + LS_DX[i]
    if dy == 0:
        return rb[xx + 1] if xx >= 0 else a
    j = min(max(xx, 0), W - 1) + 1
    return ra[j] if dy == 1 else rc[j]


@helper(inline=False)
def ls_predict(x, W, a, ra, rb, rc, w):
    """The prediction (fine units) of pixel x of width-W rows from its W neighbour ``a`` and the
    padded rows ``ra``, ``rb``, ``rc`` with the weights ``w`` (tiles * NLS,) int64, x's tile's
    from ``(x >> TILE_SHIFT) * NLS`` on."""
    n = at(ra, x + 1)
    o = (x >> TILE_SHIFT) * NLS
    acc = 0
    if x >= 3 and x + 3 < W:
        # unsigned indices (shared.compress._rans.at): no negative-index wraparound per load
        i = x + 1
        acc = (at(w, o) * _d(a, n) + at(w, o + 1) * _d(at(ra, i - 1), n) + at(w, o + 2) * _d(at(ra, i + 1), n)
               + at(w, o + 3) * _d(at(rb, i - 2), n) + at(w, o + 4) * _d(at(ra, i - 2), n)
               + at(w, o + 5) * _d(at(ra, i + 2), n) + at(w, o + 6) * _d(at(rc, i), n)
               + at(w, o + 7) * _d(at(rc, i - 1), n) + at(w, o + 8) * _d(at(rc, i + 1), n)
               + at(w, o + 9) * _d(at(rb, i - 3), n) + at(w, o + 10) * _d(at(rc, i - 2), n)
               + at(w, o + 11) * _d(at(rc, i + 2), n) + at(w, o + 12) * _d(at(ra, i - 3), n)
               + at(w, o + 13) * _d(at(ra, i + 3), n) + at(w, o + 14) * _d(at(ra, i - 4), n)
               + at(w, o + 15) * _d(at(ra, i + 4), n))
    else:
        for k in range(NLS):
            acc += at(w, o + k) * _d(_neighbour(k, x, W, a, ra, rb, rc), n)
    return n + ((acc + (1 << (LS_SHIFT - 1))) >> LS_SHIFT)


@kernel
def ls_rows(t, valid, cells, leaves, lcoef, w, pred, rows):
    """Every valid sample's prediction (fine units) into ``pred`` (H, W) int64 under the weights
    ``w`` (tiles * NLS,) int64 (:func:`ls_predict`), over a band's targets ``t`` (H, W) int64 (lossless:
    the reconstruction), the rows kept as the decoder keeps them; the first ``rows`` rows only."""
    H, W = t.shape
    H = min(H, rows)
    pf = zeros(W, np.int64)
    kr = zeros(W, np.int64)
    ra = zeros(W + 3, np.int64)
    rb = zeros(W + 3, np.int64)
    rc = zeros(W + 3, np.int64)
    for y in range(H):
        target_row(y, t, valid, cells, leaves, lcoef, pf, kr, ra, rb)
        if y == 0:
            for x in range(W + 3):  # scalar loops: slices cost seconds of compilation
                rc[x] = ra[x]
        for x in range(W):
            if valid[y, x]:
                pred[y, x] = ls_predict(x, W, rb[x] if x > 0 else ra[1], ra, rb, rc, w)
        rc, ra, rb = ra, rb, rc


@kernel
def ls_samples(t, valid, x0, x1):
    """The fit's samples of columns x0..x1-1 of a band's targets ``t`` (H, W) int64: from every
    :data:`STEP`-th row from the third on (the rows above the first two are the quadtree's, not
    yet known), each valid sample whose neighbours lie within :data:`N_LIM` of N, its
    neighbours' differences from N (cap, NLS) float64 and its own (cap,) float64, the first n
    of them filled, and n."""
    H, W = t.shape
    cap = ((H + STEP - 1) // STEP) * (x1 - x0)
    F = empty((cap, NLS), np.float64)
    e = empty(cap, np.float64)
    f = zeros(NLS, np.int64)
    ra = zeros(W + 3, np.int64)
    rb = zeros(W + 3, np.int64)
    rc = zeros(W + 3, np.int64)
    n = 0
    for y in range(H):
        for x in range(W):
            rb[x + 1] = t[y, x]
        fill_row(ra, rb, valid, y, W)
        if y >= 2 and y % STEP == 0:
            for x in range(x0, x1):
                if not valid[y, x]:
                    continue
                a = rb[x] if x > 0 else ra[1]
                c = ra[x + 1]
                if x >= 3 and x + 3 < W:
                    i = x + 1
                    f[0] = a - c
                    f[1] = ra[i - 1] - c
                    f[2] = ra[i + 1] - c
                    f[3] = rb[i - 2] - c
                    f[4] = ra[i - 2] - c
                    f[5] = ra[i + 2] - c
                    f[6] = rc[i] - c
                    f[7] = rc[i - 1] - c
                    f[8] = rc[i + 1] - c
                    f[9] = rb[i - 3] - c
                    f[10] = rc[i - 2] - c
                    f[11] = rc[i + 2] - c
                    f[12] = ra[i - 3] - c
                    f[13] = ra[i + 3] - c
                    f[14] = ra[i - 4] - c
                    f[15] = ra[i + 4] - c
                else:
                    for k in range(NLS):
                        f[k] = _neighbour(k, x, W, a, ra, rb, rc) - c
                near = 0
                for k in range(NLS):
                    near += abs(f[k]) <= N_LIM
                if near < NLS:
                    continue
                for k in range(NLS):
                    F[n, k] = f[k]
                e[n] = t[y, x] - c
                n += 1
        rc, ra, rb = ra, rb, rc
    return F, e, n


def _solve_normal(A: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """The weights of the normal equations ``A`` w = ``b``, a whisker of ridge for flat bands;
    None for a singular fit."""
    ridge = 1e-6 * max(float(np.trace(A)) / NLS, 1.0)
    try:
        w = np.linalg.solve(A + ridge * np.eye(NLS), b)
    except np.linalg.LinAlgError:
        return None
    return w if np.all(np.isfinite(w)) else None


def n_tiles(W: int) -> int:
    """The tiles of a band W columns wide (at least one)."""
    return max(1, -(-W >> TILE_SHIFT))


def ls_weights(t: np.ndarray, valid: np.ndarray) -> np.ndarray | None:
    """A band's least-squares weights (n_tiles * NLS,) int64 in 2**-LS_SHIFT, a tile's after the
    one before (lossless mode; ``t`` (H, W) int64 targets in fine units, ``valid`` (H, W) bool),
    or None where the band has too few samples (fewer than 8 a weight). A tile's weights fit
    its own samples and, weighed by :data:`TILE_PRIOR`, the band's: a tile of few samples takes
    the band's."""
    W = t.shape[1]
    nt = n_tiles(W)
    normal = [_tile_normal(t, valid, k << TILE_SHIFT, min((k + 1) << TILE_SHIFT, W)) for k in range(nt)]
    if sum(n for _, _, n in normal) < 8 * NLS:
        return None
    Ab = sum(A for A, _, _ in normal)
    bb = sum(b for _, b, _ in normal)
    if (wb := _solve_normal(Ab, bb)) is None:
        return None
    out = np.empty((nt, NLS))
    for k, (A, b, _) in enumerate(normal):
        w = _solve_normal(A + TILE_PRIOR * Ab, b + TILE_PRIOR * bb)
        out[k] = wb if w is None else w
    return np.clip(np.rint(out.ravel() * (1 << LS_SHIFT)), -LS_MAX, LS_MAX).astype(np.int64)


def _tile_normal(t: np.ndarray, valid: np.ndarray, x0: int, x1: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The normal equations (NLS, NLS), (NLS,) of the samples of columns x0..x1-1 of ``t``, those
    a first fit predicts worse than :data:`ROBUST` times its mean error left out, and their count."""
    F, e, n = ls_samples(t, valid, np.int64(x0), np.int64(x1))
    F, e = F[:n], e[:n]  # sliced here: in the kernel the slices cost a second of compilation
    A = F.T @ F
    b = F.T @ e
    if e.shape[0] < 8 * NLS or (w := _solve_normal(A, b)) is None:
        return A, b, e.shape[0]
    r = np.abs(e - F @ w)
    thr = ROBUST * max(float(np.minimum(r, ERR_CAP).mean()), float(FINE))
    out = r > thr  # a few: their products are taken out of the first fit's
    Fo = F[out]
    return A - Fo.T @ Fo, b - Fo.T @ e[out], e.shape[0] - int(out.sum())


def ls_band(t: np.ndarray, valid: np.ndarray, cells: np.ndarray, leaves: np.ndarray, lcoef: np.ndarray,
            w: np.ndarray, pred: np.ndarray | None = None) -> np.ndarray:
    """The predictions (H, W) int64 (fine units; 0 at holes) of the weights ``w`` over a band's
    targets, as the decoder makes them (lossless mode). Given ``pred``, the same band's
    predictions under another quadtree, only the rows that depend on the tree are made again:
    the first two, and where rows start with holes (filled from the row above, the first from
    the tree's virtual row), down to the second after the first row that starts with a sample."""
    if pred is None:
        pred = np.zeros(t.shape, np.int64)
        rows = t.shape[0]
    else:
        pred = pred.copy()
        starts = np.flatnonzero(valid[:, 0])
        rows = min(t.shape[0], (int(starts[0]) if starts.size else t.shape[0]) + 2)
    ls_rows(t, valid, cells, leaves, lcoef, w, pred, np.int64(rows))
    return pred
