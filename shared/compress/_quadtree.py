"""Quadtree range-image band codec kernels (private; the public API is :mod:`shared.compress.range`,
the band's encoder and decoder over these kernels :mod:`shared.compress._band`).

A band of rows is coded as one rANS stream (codec ``quadtree-lp-10``) of three parts:

1. the validity mask, exactly (:mod:`shared.compress._mask`): its coder, then per row where its
   alternating invalid/valid runs end, against the row above, or each sample in the context
   of its decoded neighbours (speckled holes), then the band's order: :data:`MODE_RASTER` (the
   rest of this list) or, in bounded mode, :data:`MODE_INTERP` (the residual tables' offset and
   merging, the flag of sign contexts, the error feedback's eight weights, then the residuals
   in hierarchical interpolation order, :mod:`shared.compress._interp`);
2. the quadtree: every 64x64 block holding a valid sample either splits into four (down
   to 4x4) or is a leaf with a surface model -- constant, plane, bilinear or quadratic in
   depth -- or with local prediction, whichever the estimated code length favours (Gaussian
   residual entropy plus the model's bits; local prediction by LOCO-I's median predictor's
   absolute errors as a Laplacian, :func:`_node`), so a block straddling a depth
   discontinuity splits because its residuals cost more than its children's, and smooth
   detailed surfaces stay in large blocks. Model coefficients are integers (fixed point, so
   encoder and decoder evaluate bit-identical predictions), coded as differences from the
   previous leaf's model extrapolated to the new block;
3. per band the flags of bias cancellation and of the weighted predictor, the context merging
   and the error-feedback weights, the flag of sign contexts, each leaf's predictor (its model, or one of the local
   predictors over the reconstructed neighbours, :mod:`shared.compress._lpred`), then the
   residuals in raster order, each in one of :data:`NCTX` tables chosen by the local
   activity (the neighbours' prediction errors and the curvature of the row above).

All values are integers in *fine units*: ``FINE = 2**F_SHIFT`` fine units per quantum, so
that predictions carry sub-quantum precision. Lossless mode codes ``Q = round(z / q)``
exactly (target ``Q * FINE``); bounded mode codes ``round((t - p) / FINE)`` for the fine
target ``t`` and prediction ``p`` (reconstruction within half a quantum of ``t``).
"""

from __future__ import annotations

import math

import numpy as np

from shared.compress import _lpred as lp
from shared.compress._mask import MASK_CTX, encode_mask, encode_mask_ctx
from shared.compress._rans import (
    NSYM,
    PROB_BITS,
    count_symbols,
    normalise,
    put,
    put_value,
    read_symbol,
    read_value,
    unzigzag,
    zigzag,
)
from shared.compress._rows import A_SHIFT, F_SHIFT, FINE, MINB, Q_SHIFT
from shared.compress._tables import pack_codes, quantise_tables
from shared.core.jit import empty, full, helper, kernel, zeros

TOP = 64  # top block size (a band's height is a multiple of it)
NCTX = lp.NCTX

T_SPLIT = 0  # 4 tables, one per splittable level (64, 32, 16, 8)
T_MODEL = 4
# T_RUN (8, 9): the mask's explicit run lengths by state (shared.compress._mask)
T_C0 = 5
T_C12 = 6
T_C345 = 7
T_PRED = 10  # the leaves' residual predictors
T_RES = 11
T_EDGE = T_RES + lp.NRES  # 2 tables: the mask's edges by state (shared.compress._mask)
NTABLES = T_EDGE + 2

#: A band's order (a symbol after its mask): the quadtree and raster-order prediction, or
#: hierarchical interpolation (:mod:`shared.compress._interp`; bounded mode).
MODE_RASTER = 0
MODE_INTERP = 1
#: The raster order's header after the tree: :data:`N_FLAGS` flags (bias cancellation, the sign
#: contexts' offset, the weighted predictor, the two feedback weights, the curvature in the
#: activity, sign contexts, the least-squares predictor), then the activity levels' tables as
#: NLEVEL - 1 flags (:func:`shared.compress._levels.partition_tables`), then, with the
#: least-squares predictor, its weights' bytes (from :data:`HEAD_N` on).
N_FLAGS = 8
HEAD_N = N_FLAGS + lp.NLEVEL - 1
F_SIGNS = 6  # the flag of sign contexts

L_SPLIT = 1
L_MODEL = 2
L_COEF = 4
L_RES = lp.L_RES

#: Parameters of the models 0..3 (constant, plane, bilinear, quadratic) and their estimated bits.
K_OF = np.array([1, 3, 4, 6], np.int64)
WS_SIZE = 96
MODEL_BITS = np.array([8.0, 24.0, 32.0, 48.0])
TWO_PI_E = 2.0 * math.pi * math.e

assert NSYM >= (1 << L_RES) + (64 << lp.M_RES) and NTABLES <= 64 and T_RES + lp.NLEVEL < 128 and lp.NK <= NSYM and 2 * lp.FB_MAX < NSYM


@helper
def model_eval(m, c, X, Y):
    """Prediction in fine units of model ``m`` with integer coefficients ``c`` at half-pixel
    offsets (X, Y) from the block's centre."""
    p = c[0]
    if m >= 1:
        p += (c[1] * X + c[2] * Y) >> A_SHIFT
    if m >= 2:
        q = c[3] * X * Y
        if m == 3:
            q += c[4] * X * X + c[5] * Y * Y
        p += q >> Q_SHIFT
    return p


@helper(inline=False)
def _cholesky(M, r, kmax, L, y):
    """Cholesky factor ``L`` of the leading kmax x kmax block of the normal equations ``M`` (a
    small ridge added) and the forward solve ``L y = r``; returns how many leading pivots are
    sound. The models are nested (1, X, Y, XY, XX, YY), so the first k rows of L and y are those
    of the k-parameter model: its residual is ``dd - sum(y[:k] ** 2)`` and only the chosen model
    needs a back substitution (:func:`_back`). ``L`` (6, 6) and ``y`` (6,) are scratch."""
    tr = 0.0
    for i in range(kmax):
        tr += M[i, i]
    ridge = 1e-12 * tr + 1e-300
    for i in range(kmax):
        for j in range(i + 1):
            s = M[i, j]
            if i == j:
                s += ridge
            for m in range(j):
                s -= L[i, m] * L[j, m]
            if i == j:
                if s <= 1e-9 * (M[i, i] + 1e-300):
                    return i
                L[i, i] = math.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
        s = r[i]
        for m in range(i):
            s -= L[i, m] * y[m]
        y[i] = s / L[i, i]
    return kmax


@helper(inline=False)
def _back(L, y, k, a):
    """The coefficients ``a`` (k,) of the k-parameter model from :func:`_cholesky`'s factors."""
    for i in range(k - 1, -1, -1):
        s = y[i]
        for m in range(i + 1, k):
            s -= L[m, i] * a[m]
        a[i] = s / L[i, i]


@helper(inline=False, fastmath=True)  # encoder only: the decoder never fits
def fit_block(t, valid, y0, x0, B, coef, ws):
    """Choose and fit the model of one block: returns (model, estimated bits, valid count);
    ``coef`` receives the integer coefficients. Model -1 and count 0 for an empty block.
    ``ws`` is a float64 scratch array of :data:`WS_SIZE` (no allocation per block)."""
    H, W = t.shape
    # The normal equations of the quadratic basis (1, X, Y, XY, X^2, Y^2) in scalars: the
    # compiler keeps them in registers (an array accumulator costs about 3x).
    s1 = sx = sy = sxx = sxy = syy = sxxx = sxxy = sxyy = syyy = 0.0
    sxxxx = sxxxy = sxxyy = sxyyy = syyyy = 0.0
    r0 = r1 = r2 = r3 = r4 = r5 = 0.0
    dd = 0.0
    n = 0
    tref = 0.0
    inv = 1.0 / B
    found = False
    for y in range(y0, min(y0 + B, H)):
        for x in range(x0, min(x0 + B, W)):
            if valid[y, x]:
                tref = float(t[y, x])
                found = True
                break
        if found:
            break
    if not found:
        return -1, 0.0, 0
    sn = 0.0
    for y in range(y0, min(y0 + B, H)):
        Y = (2 * (y - y0) - (B - 1)) * inv
        YY = Y * Y
        # Branch-free (invalid samples weigh 0) so that the compiler vectorises the row.
        for x in range(x0, min(x0 + B, W)):
            wv = 1.0 if valid[y, x] else 0.0
            X = (2 * (x - x0) - (B - 1)) * inv
            d = (float(t[y, x]) - tref) * wv
            XX = X * X
            XY = X * Y
            wX = wv * X
            wXX = wv * XX
            wXY = wv * XY
            wYY = wv * YY
            sn += wv
            sx += wX
            sy += wv * Y
            sxx += wXX
            sxy += wXY
            syy += wYY
            sxxx += wXX * X
            sxxy += wXX * Y
            sxyy += wX * YY
            syyy += wYY * Y
            sxxxx += wXX * XX
            sxxxy += wXX * XY
            sxxyy += wXX * YY
            sxyyy += wXY * YY
            syyyy += wYY * YY
            r0 += d
            r1 += d * X
            r2 += d * Y
            r3 += d * XY
            r4 += d * XX
            r5 += d * YY
            dd += d * d
    n = int(sn + 0.5)
    s1 = sn
    if n == 0:
        return -1, 0.0, 0
    M = ws[0:36].reshape((6, 6))
    # rows: 1, X, Y, XY, XX, YY
    M[0, 0] = s1
    M[0, 1] = sx
    M[0, 2] = sy
    M[0, 3] = sxy
    M[0, 4] = sxx
    M[0, 5] = syy
    M[1, 1] = sxx
    M[1, 2] = sxy
    M[1, 3] = sxxy
    M[1, 4] = sxxx
    M[1, 5] = sxyy
    M[2, 2] = syy
    M[2, 3] = sxyy
    M[2, 4] = sxxy
    M[2, 5] = syyy
    M[3, 3] = sxxyy
    M[3, 4] = sxxxy
    M[3, 5] = sxyyy
    M[4, 4] = sxxxx
    M[4, 5] = sxxyy
    M[5, 5] = syyyy
    for i in range(6):
        for j in range(i):
            M[i, j] = M[j, i]
    r = ws[36:42]
    r[0] = r0
    r[1] = r1
    r[2] = r2
    r[3] = r3
    r[4] = r4
    r[5] = r5
    best_m = 0
    best_cost = 1e300
    best_a = ws[42:48]
    best_a[:] = 0.0
    L = ws[54:90].reshape((6, 6))
    yv = ws[90:96]
    mmax = 1 if B <= MINB else 3  # a 4x4 block: constant or plane (more never paid there)
    while mmax > 0 and n < 2 * K_OF[mmax]:
        mmax -= 1
    sound = _cholesky(M, r, K_OF[mmax], L, yv)
    yy = 0.0
    done = 0
    for m in range(mmax + 1):
        k = K_OF[m]
        if k > sound:
            break
        while done < k:
            yy += yv[done] * yv[done]
            done += 1
        dof = n - k if n > k else 1
        s2 = max(dd - yy, 0.0) / dof / (FINE * FINE)
        cost = 0.5 * n * math.log2(1.0 + TWO_PI_E * s2) + MODEL_BITS[m]
        if cost < best_cost:
            best_cost = cost
            best_m = m
    _back(L, yv, K_OF[best_m], best_a)
    coef[0] = np.int64(round(tref + best_a[0]))
    coef[1] = np.int64(round(best_a[1] * inv * (1 << A_SHIFT)))
    coef[2] = np.int64(round(best_a[2] * inv * (1 << A_SHIFT)))
    coef[3] = np.int64(round(best_a[3] * inv * inv * (1 << Q_SHIFT)))
    coef[4] = np.int64(round(best_a[4] * inv * inv * (1 << Q_SHIFT)))
    coef[5] = np.int64(round(best_a[5] * inv * inv * (1 << Q_SHIFT)))
    return best_m, best_cost, n


#: Estimated bits of a leaf coded by local prediction (its constant and predictor).
LOCAL_BITS = 16.0
#: A block splits only where its children's estimated bits undercut its own by a margin: a
#: number of bits plus a share of its own. The estimates favour splitting: each child's Gaussian
#: or Laplacian fits its own samples, while the coder shares its context tables across the band,
#: and a child's model costs more than :data:`MODEL_BITS` on noisy depth. Lossless mode codes
#: a band with each margin of SPLIT_LOSSLESS and keeps the smaller stream: measured with one
#: margin for all (bits per valid sample at 0.02 mm, margins 0 / 200 / 1600 bits), the Cyberware
#: dragon scans 5.76 / 5.02 / 4.85 and 5.71 / 4.89 / 4.70 (noisy, holed: few leaves pay), the
#: relief at 1:1 2.59 / 2.53 / 2.59 and 2:1 2.23 / 2.14 / 2.20, the bunny at 4:1 2.70 / 2.61 /
#: 2.59. Bounded mode: 50 bits + 5 % (dragon 2.87 -> 2.74, relief 2:1 0.580 -> 0.579, bunny 1:1
#: 1.487 -> 1.494 from no margin).
SPLIT_LOSSLESS = (200.0, 1600.0)
SPLIT_BOUNDED = (50.0, 0.05)


@helper(inline=False)
def _node(t, valid, S, y0, x0, B, coef, ws, local):
    """:func:`fit_block`, then local prediction's estimated bits (:func:`lp.local_bits`) when
    ``local``: where they are fewer, the block becomes a constant (its model's value at the
    centre) for a local predictor. Returns (model, estimated bits, valid count)."""
    m, cost, cnt = fit_block(t, valid, y0, x0, B, coef, ws)
    if local and cnt > 0:
        lb = lp.local_bits(S, y0, x0, B, cnt) + MODEL_BITS[m]
        if lb < cost:
            return m, lb, cnt
    return m, cost, cnt


@helper
def _predict_coefs(pm, pc, px, py, pB, x0, y0, B, out):
    """The previous leaf's model carried to the centre of block (x0, y0, B)."""
    Xc = 2 * (x0 - px) + B - pB
    Yc = 2 * (y0 - py) + B - pB
    out[0] = model_eval(pm, pc, Xc, Yc)
    c3 = pc[3] if pm >= 2 else 0
    c4 = pc[4] if pm == 3 else 0
    c5 = pc[5] if pm == 3 else 0
    if pm >= 1:
        out[1] = pc[1] + ((c3 * Yc + 2 * c4 * Xc) >> (Q_SHIFT - A_SHIFT))
        out[2] = pc[2] + ((c3 * Xc + 2 * c5 * Yc) >> (Q_SHIFT - A_SHIFT))
    else:
        out[1] = 0
        out[2] = 0
    out[3] = c3
    out[4] = c4
    out[5] = c5


@helper(inline=False)
def _put_coef(tab, val, nb, n, t, u):
    # A leaf's coefficients, a few a leaf: called, not the coder's IR inlined at six sites of
    # the tree's kernel (numba copies an inlined function's IR at every call site).
    return put_value(tab, val, nb, n, t, u, L_COEF, 0)


#: Levels of the quadtree: blocks of TOP, TOP / 2, ... MINB samples.
NLEV = 5
assert TOP >> (NLEV - 1) == MINB


def tree_memo(t: np.ndarray, valid: np.ndarray, lossless: bool, opts: int) -> tuple[np.ndarray, ...]:
    """What a band's trees share whatever their margin (:func:`_encode_tree`): the integral of
    local prediction's errors (:func:`shared.compress._lpred.local_cost_integral`) and, empty,
    every block's fitted model (int64 (cells, 8): model, valid count + 1 (0: not yet fitted),
    six coefficients) and its estimated bits (float64 (cells,)), the blocks of each level in
    raster order (zeros: only the pages of the blocks fitted are ever touched). A block's fit
    does not depend on the margin; a larger margin splits fewer blocks, so its tree fits none
    the smaller margin's did not."""
    H, W = t.shape
    local = (opts & lp.OPT_PRED) != 0
    S = lp.local_cost_integral(t, valid, lossless) if local else np.zeros((1, 1), np.int64)
    cells = sum(-(-H // (TOP >> lev)) * -(-W // (TOP >> lev)) for lev in range(NLEV))
    return S, np.zeros((cells, 8), np.int64), np.zeros(cells)


@helper(inline=False)
def _memo_node(t, valid, S, y0, x0, B, lev, coef, ws, local, memo, memo_c):
    """:func:`_node` of block (y0, x0, B) at level ``lev``, fitted once (:func:`tree_memo`; an
    empty ``memo``: fitted every time). A block at the band's edge has children past it: they
    are empty, and have no cell (their index would be another block's)."""
    H, W = t.shape
    if y0 >= H or x0 >= W or memo.shape[0] == 0:
        return _node(t, valid, S, y0, x0, B, coef, ws, local)
    off = 0
    for j in range(lev):
        b = TOP >> j
        off += ((H + b - 1) // b) * ((W + b - 1) // b)
    i = off + (y0 // B) * ((W + B - 1) // B) + x0 // B
    if memo[i, 1] == 0:
        m, cost, cnt = _node(t, valid, S, y0, x0, B, coef, ws, local)
        memo[i, 0] = m
        memo[i, 1] = cnt + 1
        memo_c[i] = cost
        for k in range(6):
            memo[i, 2 + k] = coef[k]
        return m, cost, cnt
    for k in range(6):
        coef[k] = memo[i, 2 + k]
    return memo[i, 0], memo_c[i], memo[i, 1] - 1


@kernel
def put_mask(valid, tab, val, nb, n, mask):
    """A band's mask coder ``mask`` (:data:`shared.compress._mask.MASK_RUNS` or ``MASK_CTX``) and
    its mask ``valid`` (H, W) bool so coded, from event ``n``; returns the count (-1: full)."""
    n = put(tab, val, nb, n, T_PRED, mask, 0)
    if mask == MASK_CTX:
        return encode_mask_ctx(valid, tab, val, nb, n)
    return encode_mask(valid, tab, val, nb, n, T_EDGE)


@kernel
def put_events(tab, val, nb, n, stab, sval, snb):
    """Append the events ``stab``, ``sval``, ``snb`` after event ``n``; returns the count (-1:
    the buffers are full)."""
    m = stab.shape[0]
    if n < 0 or n + m > tab.shape[0]:
        return -1
    for i in range(m):
        tab[n + i] = stab[i]
        val[n + i] = sval[i]
        nb[n + i] = snb[i]
    return n + m


@kernel
def _encode_tree(t, valid, lossless, opts, margin, share, tab, val, nb, leaves, lcoef, S, memo, memo_c, mtab, mval,
                 mnb):
    """The mask's and the quadtree's events of one band (its leaves into ``leaves`` (n, 5) and
    ``lcoef`` (n, 6) int64); returns (events, leaves), events -1 when the buffers are too small.
    ``S``, ``memo`` and ``memo_c`` from :func:`tree_memo`, and the mask's events ``mtab``,
    ``mval``, ``mnb`` (:func:`put_mask`), shared by the band's margins.
    (Arrays copied by loops, not ``a[:] = b``: numba links a shape mismatch's error message into
    every kernel holding one, 0.2 s more compilation each, 2.4 s once a process.)"""
    H, W = t.shape
    # 1. the mask (n an int64 value, not the literal 0: put_events compiles once, as Python calls it)
    n = put_events(tab, val, nb, np.int64(0), mtab, mval, mnb)
    n = put(tab, val, nb, n, T_PRED, MODE_RASTER, 0)
    # 2. the quadtree with its leaves' models
    local = (opts & lp.OPT_PRED) != 0
    nleaf = 0
    st_xyb = empty((64, 4), np.int64)  # x0, y0, B, level
    st_fit = empty((64, 6), np.int64)
    st_m = empty(64, np.int64)
    st_cost = empty(64, np.float64)
    pm = 0
    pc = zeros(6, np.int64)
    px = 0
    py = 0
    pB = TOP
    pred = zeros(6, np.int64)
    coef = zeros(6, np.int64)
    kids = zeros((4, 6), np.int64)
    kid_m = zeros(4, np.int64)
    kid_cost = zeros(4, np.float64)
    ws = empty(WS_SIZE, np.float64)
    for ty in range(0, H, TOP):
        for tx in range(0, W, TOP):
            m, cost, cnt = _memo_node(t, valid, S, np.int64(ty), np.int64(tx), np.int64(TOP), np.int64(0), coef, ws, local,
                                      memo, memo_c)
            if cnt == 0:
                continue
            sp = 0
            st_xyb[0, 0] = tx
            st_xyb[0, 1] = ty
            st_xyb[0, 2] = TOP
            st_xyb[0, 3] = 0
            for i in range(6):
                st_fit[0, i] = coef[i]
            st_m[0] = m
            st_cost[0] = cost
            sp = 1
            while sp > 0:
                sp -= 1
                x0 = st_xyb[sp, 0]
                y0 = st_xyb[sp, 1]
                B = st_xyb[sp, 2]
                lev = st_xyb[sp, 3]
                m = st_m[sp]
                cost = st_cost[sp]
                for i in range(6):
                    coef[i] = st_fit[sp, i]
                if B > MINB:
                    h = B // 2
                    split_cost = 4.0
                    for k in range(4):
                        kx = x0 + (k & 1) * h
                        ky = y0 + (k >> 1) * h
                        kid_m[k], kid_cost[k], kc = _memo_node(t, valid, S, np.int64(ky), np.int64(kx), np.int64(h),
                                                               np.int64(lev + 1), kids[k], ws, local, memo, memo_c)
                        if kc > 0:
                            split_cost += kid_cost[k]
                    split = split_cost + margin + share * cost < cost
                    n = put(tab, val, nb, n, T_SPLIT + lev, 1 if split else 0, 0)
                    if split:
                        for k in range(3, -1, -1):  # pushed in reverse: popped in Z order
                            if kid_m[k] < 0:
                                continue
                            st_xyb[sp, 0] = x0 + (k & 1) * h
                            st_xyb[sp, 1] = y0 + (k >> 1) * h
                            st_xyb[sp, 2] = h
                            st_xyb[sp, 3] = lev + 1
                            for i in range(6):
                                st_fit[sp, i] = kids[k, i]
                            st_m[sp] = kid_m[k]
                            st_cost[sp] = kid_cost[k]
                            sp += 1
                        continue
                # a leaf
                n = put(tab, val, nb, n, T_MODEL, m, 0)
                _predict_coefs(pm, pc, px, py, pB, x0, y0, B, pred)
                # the tables as int64 values, not literals: _put_coef is compiled once, not once a table
                n = _put_coef(tab, val, nb, n, np.int64(T_C0), zigzag(coef[0] - pred[0]))
                if m >= 1:
                    n = _put_coef(tab, val, nb, n, np.int64(T_C12), zigzag(coef[1] - pred[1]))
                    n = _put_coef(tab, val, nb, n, np.int64(T_C12), zigzag(coef[2] - pred[2]))
                if m >= 2:
                    n = _put_coef(tab, val, nb, n, np.int64(T_C345), zigzag(coef[3] - pred[3]))
                if m == 3:
                    n = _put_coef(tab, val, nb, n, np.int64(T_C345), zigzag(coef[4] - pred[4]))
                    n = _put_coef(tab, val, nb, n, np.int64(T_C345), zigzag(coef[5] - pred[5]))
                for i in range(6):
                    if (i >= 1 and m == 0) or (i >= 3 and m == 1) or (i >= 4 and m == 2):
                        coef[i] = 0
                leaves[nleaf, 0] = x0
                leaves[nleaf, 1] = y0
                leaves[nleaf, 2] = B
                leaves[nleaf, 3] = m
                for i in range(6):
                    lcoef[nleaf, i] = coef[i]
                    pc[i] = coef[i]
                nleaf += 1
                pm = m
                px = x0
                py = y0
                pB = B
    return (n if n >= 0 else -1), nleaf


@kernel
def _put_predictors(tab, val, nb, n, head, leaves, nleaf):
    """The band's flags and weights ``head`` (n,) int64 and each leaf's predictor, from event ``n``."""
    for i in range(head.shape[0]):
        n = put(tab, val, nb, n, T_PRED, head[i], 0)
    for i in range(nleaf):
        n = put(tab, val, nb, n, T_PRED, leaves[i, 4], 0)
    return n


@kernel
def finite_abs_max(z):
    """Largest ``|z|`` over the valid (non-NaN) samples of ``z`` (H, W) float32, as a float, and
    their count; (0.0, 0) when every sample is a hole. One pass, no temporaries."""
    H, W = z.shape
    m = np.float32(0.0)
    n = 0
    for y in range(H):
        for x in range(W):
            v = z[y, x]
            if v == v:
                a = abs(v)
                if a > m:
                    m = a
                n += 1
    return float(m), n


@kernel
def quantise(z, scale, lossless):
    """Fine-unit targets of a band of depth ``z`` (float32, NaN holes) and its mask: lossless,
    ``round(z / scale) * FINE``; bounded, ``round(z / scale)`` (scale is then the fine unit)."""
    H, W = z.shape
    t = zeros((H, W), np.int64)
    valid = zeros((H, W), np.bool_)
    for y in range(H):
        for x in range(W):
            v = z[y, x]
            if v == v:
                valid[y, x] = True
                # divide (not multiply by 1/scale): the same rounding as numpy's z / q
                q = np.int64(np.rint(np.float64(v) / scale))
                t[y, x] = q << F_SHIFT if lossless else q
    return t, valid


@kernel
def _stream_bits(tab, val, nb, n):
    """The coded size in bits of events 0..n-1: their tables' code lengths, raw bits and stored
    tables; not their binary events (a mask in context, :func:`put_mask`: the same in every way
    a band is coded, so they do not change which way is smaller)."""
    counts = count_symbols(tab, val, n, np.int64(NTABLES))  # int64: one signature with encode_band's
    codes, freq = quantise_tables(normalise(counts))
    bits = 8.0 * pack_codes(codes).size
    for i in range(n):
        if tab[i] < 0:
            bits += nb[i]  # raw
    for k in range(NTABLES):
        for s in range(NSYM):
            if counts[k, s] > 0:
                bits += counts[k, s] * (PROB_BITS - math.log2(freq[k, s]))
    return bits


@helper(inline=False)
def _count(ii, y0, x0, B, H, W):
    """Valid MINB x MINB cells in block (y0, x0, B) (clipped to H x W) from the cell-level
    integral image ``ii`` (see :func:`_cell_integral`); blocks are aligned to cells."""
    if y0 >= H or x0 >= W:
        return 0
    c0y = y0 // MINB
    c0x = x0 // MINB
    c1y = (min(y0 + B, H) + MINB - 1) // MINB
    c1x = (min(x0 + B, W) + MINB - 1) // MINB
    return ii[c1y, c1x] - ii[c0y, c1x] - ii[c1y, c0x] + ii[c0y, c0x]


@helper(inline=False)
def _cell_integral(valid):
    """Integral image over MINB x MINB cells of "the cell holds a valid sample":
    (ceil(H / MINB) + 1, ceil(W / MINB) + 1) int32 (a band's mask is 16x larger)."""
    H, W = valid.shape
    ch = (H + MINB - 1) // MINB
    cw = (W + MINB - 1) // MINB
    occ = zeros(cw, np.int32)
    ii = zeros((ch + 1, cw + 1), np.int32)
    for cy in range(ch):
        occ[:] = 0
        for y in range(cy * MINB, min(cy * MINB + MINB, H)):
            for x in range(W):
                if valid[y, x]:
                    occ[x // MINB] = 1
        acc = 0
        for cx in range(cw):
            acc += occ[cx]
            ii[cy + 1, cx + 1] = ii[cy, cx + 1] + acc
    return ii


@kernel
def _decode_tree(xa, xb, pos, words, nw, sym, fb, valid, lossless, leaves, lcoef, head):
    """A band's quadtree, its mask ``valid`` decoded: the leaves into ``leaves`` (n, 5) (x0, y0,
    B, model, predictor) and ``lcoef`` (n, 6) int64, then the header (:data:`HEAD_N`) into
    ``head`` (HEAD_N + 2 NLS tiles,) int64 (:mod:`shared.compress._ls`) and, where its last flag
    says the least-squares predictor runs, its weights' bytes after it (as
    :func:`_put_predictors` put them). Returns (leaves, xa, xb, pos), -1 leaves for a corrupt
    stream."""
    H, W = valid.shape
    ii = _cell_integral(valid)
    nleaf = 0
    stack = empty((64, 4), np.int64)
    pm = 0
    pc = zeros(6, np.int64)
    px = 0
    py = 0
    pB = TOP
    pred = zeros(6, np.int64)
    for ty in range(0, H, TOP):
        for tx in range(0, W, TOP):
            if _count(ii, ty, tx, np.int64(TOP), H, W) == 0:
                continue
            stack[0, 0] = tx
            stack[0, 1] = ty
            stack[0, 2] = TOP
            stack[0, 3] = 0
            sp = 1
            while sp > 0:
                sp -= 1
                x0 = stack[sp, 0]
                y0 = stack[sp, 1]
                B = stack[sp, 2]
                lev = stack[sp, 3]
                if pos > nw:
                    return -1, xa, xb, pos
                if B > MINB:
                    split, xa, xb, pos = read_symbol(xa, xb, pos, words, nw, sym, fb, T_SPLIT + lev)
                    if split > 1:
                        return -1, xa, xb, pos
                    if split == 1:
                        h = B // 2
                        for k in range(3, -1, -1):
                            kx = x0 + (k & 1) * h
                            ky = y0 + (k >> 1) * h
                            if _count(ii, ky, kx, h, H, W) == 0:
                                continue
                            stack[sp, 0] = kx
                            stack[sp, 1] = ky
                            stack[sp, 2] = h
                            stack[sp, 3] = lev + 1
                            sp += 1
                        continue
                m, xa, xb, pos = read_symbol(xa, xb, pos, words, nw, sym, fb, T_MODEL)
                if m > 3:
                    return -1, xa, xb, pos
                _predict_coefs(pm, pc, px, py, pB, x0, y0, B, pred)
                c = lcoef[nleaf]
                # the K_OF[m] coefficients: one inlined value decoder, not six (numba copies its IR per site)
                for i in range(K_OF[m]):
                    tc = T_C0 if i == 0 else (T_C12 if i < 3 else T_C345)
                    u, xa, xb, pos = read_value(xa, xb, pos, words, nw, sym, fb, tc, L_COEF, 0)
                    c[i] = pred[i] + unzigzag(u)
                leaves[nleaf, 0] = x0
                leaves[nleaf, 1] = y0
                leaves[nleaf, 2] = B
                leaves[nleaf, 3] = m
                nleaf += 1
                pm = m
                for i in range(6):
                    pc[i] = c[i]
                px = x0
                py = y0
                pB = B
    if pos > nw:
        return -1, xa, xb, pos
    # the flags and the levels' tables (HEAD_N symbols), then with the least-squares predictor
    # its weights' bytes
    nh = HEAD_N
    i = 0
    while i < nh:
        v, xa, xb, pos = read_symbol(xa, xb, pos, words, nw, sym, fb, T_PRED)
        head[i] = v
        if i == N_FLAGS - 1 and v == 1:
            nh = head.shape[0]
        i += 1
    bias, cofs, wp, aw, an, grad, sc, ls = head[0], head[1], head[2], head[3], head[4], head[5], head[6], head[7]
    # the weighted and least-squares predictors run in lossless bands only (the encoder's choice)
    if (bias > 1 or cofs > lp.MAX_COFS or wp > (1 if lossless else 0) or aw > 2 * lp.FB_MAX
            or an > 2 * lp.FB_MAX or grad > 1 or sc > 1 or ls > (1 if lossless else 0)):
        return -1, xa, xb, pos
    for i in range(N_FLAGS, HEAD_N):
        if head[i] > 1:
            return -1, xa, xb, pos
    for i in range(HEAD_N, nh):
        if head[i] > 255:
            return -1, xa, xb, pos
    for i in range(nleaf):
        k, xa, xb, pos = read_symbol(xa, xb, pos, words, nw, sym, fb, T_PRED)
        if k >= lp.NK or (k == lp.K_WP and not wp) or (k == lp.K_LS and not ls):
            return -1, xa, xb, pos
        leaves[i, 4] = k
    if pos > nw:
        return -1, xa, xb, pos
    return nleaf, xa, xb, pos


@kernel
def _leaf_cells(H, W, leaves, nleaf):
    """Which leaf covers each MINB x MINB cell: (ceil(H / MINB), ceil(W / MINB)) int32, -1 for none."""
    ch = (H + MINB - 1) // MINB
    cw = (W + MINB - 1) // MINB
    cells = full((ch, cw), -1, np.int32)
    for i in range(nleaf):
        cx0 = leaves[i, 0] // MINB
        cy0 = leaves[i, 1] // MINB
        n = leaves[i, 2] // MINB
        cells[cy0 : min(cy0 + n, ch), cx0 : min(cx0 + n, cw)] = i
    return cells
