"""Local prediction of a range band's residuals (private kernels of :mod:`shared.compress._quadtree`).

Every valid sample is predicted either by its quadtree leaf's surface model or, as the lossless
image codecs do, from its already decoded neighbours W, N, NW, NE (reconstructed values in fine
units; a hole takes the value before it in its row, a band's first row sees its own model
predictions above it):

- each leaf picks one of :data:`NK` predictors (:func:`local_pred`: the model, LOCO-I's median
  edge detector, the plane through W, N, NW, means, blends of the model with the median or
  the plane, the N or the W neighbour alone; in a band that runs them, :data:`K_WP` the self-correcting weighted predictor of
  :mod:`shared.compress._wp` and :data:`K_LS` the band's least-squares predictor over 16
  neighbours in three rows, :mod:`shared.compress._ls`), chosen by the encoder per leaf by the
  summed cost of its errors (:func:`choose_predictors`) and coded as a symbol after the tree: smooth, detailed depth (an
  oversampling camera's sub-pixel depth) takes a neighbour predictor, white noise keeps the model;
- the weighted and least-squares predictors (lossless mode) run over a band where the encoder
  finds they pay (both ways tried): both are functions of the reconstruction alone, so the
  encoder computes them once over the targets (:func:`wp_band`,
  :func:`shared.compress._ls.ls_band`) and the decoder alongside its samples (the least-squares
  one in the leaves that take it, from a third row buffer);
- error feedback (lossless mode): the W and N neighbours' prediction errors, weighted by the
  band's weights (:func:`feedback_weights`: least-squares fits with the errors clipped at four
  sizes, the one of least log cost where it saves :data:`FB_MIN_GAIN` of no feedback's; coded
  in sixteenths), are added to the prediction where the band codes smaller with them (the
  encoder tries them last, both ways);
- the coding context is the local activity: the sizes of the W, N, NW, NE prediction errors
  and the curvature of the row above, in :data:`NLEVEL` half-octave levels; in a band running
  the weighted predictor, half that plus twice the predictor's largest neighbour error
  (:func:`_wp_activity`); in raster order each band partitions its levels into runs, one rANS
  table a run, that code its residuals in the fewest bits, stored tables counted
  (:func:`shared.compress._levels.level_partition`: quiet levels of a few dozen residuals share a table); the
  interpolation order slides and merges its tables (:func:`shared.compress._levels.context_choice`);
- bias cancellation (LOCO-I/CALIC), per band where it pays (bounded mode): per context of
  gradient signs and activity, the running mean of the prediction's error is added.

In the error-bounded mode every prediction is made from *reconstructed* values, so the
encoder and the decoder run the same integers and errors do not drift. What each piece buys
is measured by the encoder's options (:data:`OPT_ALL`; the bench's ablation).
"""

from __future__ import annotations

import math

import numpy as np
from numba.cpython.unsafe.numbers import leading_zeros

from shared.compress._check import add_row, scratch
from shared.compress._ls import ls_predict
from shared.compress._rans import at, put_value, read_value, set_at, symbol_of, unzigzag, zigzag
from shared.compress._rows import F_SHIFT, FINE, MINB, fill_row, first_row, row_prediction, target_row
from shared.compress._wp import wp_hole, wp_predict, wp_update
from shared.core.jit import helper, kernel, zeros

#: Residual predictors a leaf may choose (see :func:`local_pred`; :data:`K_WP` is the weighted
#: predictor of :mod:`shared.compress._wp` and :data:`K_LS` the least-squares predictor of
#: :mod:`shared.compress._ls`, each only in a band that runs it).
NK = 12
#: The N and the W neighbour alone (:func:`local_pred`).
K_N = 8
K_W = 9
K_WP = 10
K_LS = 11
#: Coding contexts of the residuals (activity levels).
NCTX = 16
L_RES = 8
#: The bits below a large residual's top bit coded in its escape symbol, not raw (the symbol
#: the bit length and these): a noisy real capture's residuals spread over hundreds of quanta,
#: and a bit length's lower values are the likelier ones. Measured (lossless at 0.02 mm): the
#: kamino410 captures 0.15-0.3 % smaller with 2 bits (1 bit: 0.1-0.2 %), the Cyberware dragons
#: 0.05-0.09 % larger (their tables hold more symbols), the simulated scenes within 0.05 %.
M_RES = 2
#: Sign contexts (a band's choice, :func:`_sign_context`): the residual tables are then
#: :data:`NGRP` groups of four activity levels times :data:`NSUB` patterns of the rounding
#: offset and the N neighbour's residual sign.
NGRP = 4
NSUB = 6
#: Sign contexts of the interpolation order (:func:`shared.compress._interp._table`):
#: :data:`NI_GRP` groups of activity levels x :data:`NI_PAT` patterns of the signs of the residual
#: before in the pass-row and of the two neighbours it is interpolated from x :data:`NI_CLS` classes of
#: pass.
NI_GRP = 3
NI_PAT = 5
NI_CLS = 3
#: Residual tables of a band (any way).
NRES = max(NCTX, NGRP * NSUB, NI_GRP * NI_PAT * NI_CLS)
#: Bias contexts: 27 patterns of gradient signs x 4 activity groups.
NBIAS = 27 * 4
BIAS_RESET = 64
#: Reconstructed residuals, errors and their sizes are clamped to this many fine units in the
#: predictors and contexts (hostile inputs: sums of them stay inside int64).
E_LIM = 1 << 40
#: Options of the encoder (ablation; the decoder always runs with :data:`OPT_ALL`).
OPT_PRED = 1  # local residual predictors (else every leaf keeps its model alone)
OPT_GRAD = 2  # gradients of the residual field in the context
OPT_ERR = 4  # previous prediction errors in the context
OPT_BIAS = 8  # bias cancellation (bounded mode: per band, where it pays)
OPT_FEEDBACK = 16  # the W and N neighbours' prediction errors fed back into the prediction
OPT_WP = 32  # the weighted predictor (lossless mode: per band, where it pays)
OPT_SIGN = 64  # sign contexts (per band, where they pay)
OPT_INTERP = 128  # hierarchical interpolation (bounded mode: per band, where it pays)
OPT_LS = 256  # the least-squares predictor (lossless mode: per band, where leaves take it)
OPT_ALL = 511

#: Activity levels (half octaves) of the residuals: a band's NCTX tables take the levels from
#: its offset (:func:`shared.compress._levels.context_choice`) on, the ones below and above joining the ends.
NLEVEL = 24
MAX_COFS = NLEVEL - NCTX
#: Level of an activity a (fine units): min(NLEVEL - 1, floor(2 log2(a / 4 + 1))).
LEVEL_LUT = np.array([min(NLEVEL - 1, int(2 * math.log2(v + 1))) for v in range(1 << 12)], np.int8)
#: 2**16 / n for the bias means (n < BIAS_RESET + 1).
RECIP = np.array([0] + [(1 << 16) // n for n in range(1, BIAS_RESET + 1)], np.int64)


@helper
def _level_of(act):
    v = act >> 2
    return np.int64(at(LEVEL_LUT, v)) if v < 4096 else NLEVEL - 1


@helper
def local_pred(k, a, b, c, d, m):
    """Predictor ``k`` of a sample from its reconstructed neighbours W ``a``, N ``b``, NW ``c``, NE
    ``d`` and its leaf's model ``m`` (fine units): 0 the model, 1 LOCO-I's median edge detector,
    2 the mean of W and N, 3 the plane through W, N, NW, 4 the mean with the NE slope, 5 and 6
    the model averaged with the median and with the plane (noisy or coarsely quantised
    neighbours), 7 between the mean and the plane, 8 N, 9 W. N alone: where a 1:1 camera's
    decoder misreads a dim backdrop's finest stripes, whole runs of a column are one projector
    column off, and only the sample above shares the offset (the bunny at 1:1 codes 1.3 %
    smaller with 8 and 9, the real captures 0.03-0.2 %, the others within 0.05 %)."""
    if k == 0:
        return m
    if k == 2:
        return (a + b) >> 1
    if k == 3:
        return a + b - c
    if k == 4:
        return ((a + b) * 2 + d - c) >> 2
    if k == 6:
        return (m + a + b - c) >> 1
    if k == 7:
        return (3 * (a + b) - 2 * c) >> 2
    if k == K_N:
        return b
    if k == K_W:
        return a
    # the median of W, N and the plane (LOCO-I's edge detector), branch-free
    med = max(min(a, b), min(max(a, b), a + b - c))
    return med if k == 1 else (m + med) >> 1


@helper(inline=False)
def _log_cost(e):
    """A leaf's cost of a prediction error ``e`` (fine units) when it chooses its predictor:
    floor(log2(2 m + 1)) for m = |e| in quarters of a quantum, about the bits a residual costs
    beyond its table's peak. The absolute error weighs a leaf's few large errors (at an edge) as
    heavily as its many small ones, which cost most of its bits. Measured against the absolute
    error (bits per valid sample, lossless at 0.02 mm): the relief at 1:1, 2:1, 4:1 2.296 /
    1.983 / 1.791 -> 2.275 / 1.977 / 1.747, the bunny at 2:1 and 4:1 2.796 / 2.332 -> 2.746 /
    2.286, the fandisk 2.724 -> 2.690, the spot 2.316 -> 2.267, the Cyberware dragons 4.859 /
    4.810 -> 4.860 / 4.555, the real captures within 0.3 % (9.351 -> 9.363 the worst), the
    synthetic noise 5.512 -> 5.509; m in eighths or halves of a quantum: up to 1.5 % larger on the
    relief at 2:1 and 4:1 or on a dragon; in sixteenths 4 % larger on the relief."""
    # floor(log2(2 m + 1)) is the bit length of m: 64 less its leading zeros (|e| < 2**63)
    return 64 - np.int64(leading_zeros(np.uint64(abs(e) >> (F_SHIFT - 2))))


@helper(inline=False)
def _err_cost(e, lossless):
    return _log_cost(e) if lossless else min(abs(e), E_LIM)


@helper
def _sign3(g):
    return 0 if g < -(FINE >> 2) else (2 if g > (FINE >> 2) else 1)


@kernel
def local_cost_integral(t, valid, lossless):
    """Integral image (H + 1, W + 1) int64 of every valid sample's absolute error (fine units,
    clamped) under LOCO-I's median predictor over the targets ``t``: the quadtree's estimate of
    what local prediction would cost in a block (:func:`local_bits`)."""
    H, W = t.shape
    S = zeros((H + 1, W + 1), np.int64)
    ra = zeros(W + 3, np.int64)
    rb = zeros(W + 3, np.int64)
    # open loop: the targets themselves (measured better than rounding them in bounded mode),
    # the first row its own row above
    first_row(ra, t[0], valid, W)
    for y in range(H):
        acc = 0
        for x in range(W):
            rb[x + 1] = t[y, x]
        fill_row(ra, rb, valid, y, W)
        for x in range(W):
            if valid[y, x]:
                acc += min(abs(t[y, x] - local_pred(1, rb[x], ra[x + 1], ra[x], ra[x + 2], 0)), E_LIM)
            S[y + 1, x + 1] = S[y, x + 1] + acc
        ra, rb = rb, ra
    return S


@helper(inline=False)
def local_bits(S, y0, x0, B, n):
    """Estimated bits of the n valid samples of block (y0, x0, B) under local prediction: a
    Laplacian's n log2(1 + 2e m) for their mean absolute error m (quanta) from ``S``."""
    H = S.shape[0] - 1
    W = S.shape[1] - 1
    y1 = min(y0 + B, H)
    x1 = min(x0 + B, W)
    s = S[y1, x1] - S[y0, x1] - S[y1, x0] + S[y0, x0]
    m = s / max(n, 1) / FINE
    return n * math.log2(1.0 + 2.0 * math.e * m)


@kernel
def choose_predictors(t, valid, cells, leaves, lcoef, nleaf, lossless, opts, pw, wp, pls, ls, cost, local, known):
    """Each leaf's predictor (``leaves[:, 4]``: 0 its model, else :func:`local_pred`'s): the one
    of least summed cost over the leaf, predicted from the targets ``t`` (exact in lossless mode,
    within half a quantum of the reconstruction in bounded mode): in lossless mode
    :func:`_log_cost`, in bounded mode the absolute error (there the log cost coded the raster
    order of test reliefs 16 % smaller to 8 % larger, whole bench images within 1.3 %). With ``wp``
    the weighted predictor's predictions ``pw`` (H, W) int64 (:func:`wp_band`) are a choice too,
    with ``ls`` the least-squares predictor's ``pls`` (H, W) int64
    (:func:`shared.compress._ls.ls_band`). ``cost`` (>= nleaf, NK) int64 holds the leaves'
    summed costs: with ``local`` they are counted for the local predictors, but for the leaves
    ``known`` (nleaf,) bool (empty: none) marks, whose rows the caller filled (the same leaf's
    under another tree margin: leaves below the rows that depend on the tree, whose neighbours
    are targets); without ``local`` they are a previous call's (another predictor tried beside
    them)."""
    H, W = t.shape
    leaves[:nleaf, 4] = 0
    if not (opts & OPT_PRED):
        return
    cost[:nleaf, K_WP] = 0
    cost[:nleaf, K_LS] = 0
    if local:
        some = known.shape[0] > 0
        for i in range(nleaf):
            if not (some and known[i]):
                for k in range(K_WP):
                    cost[i, k] = 0
        pf = zeros(W, np.int64)
        kr = zeros(W, np.int64)
        ra = zeros(W + 3, np.int64)
        rb = zeros(W + 3, np.int64)
        for y in range(H):
            target_row(y, t, valid, cells, leaves, lcoef, pf, kr, ra, rb)
            cy = y // MINB
            for x in range(W):
                if not valid[y, x]:
                    continue
                v = t[y, x]
                a = rb[x]
                b = ra[x + 1]
                c = ra[x]
                d = ra[x + 2]
                i = cells[cy, x // MINB]
                if some and known[i]:
                    continue
                for k in range(K_WP):
                    cost[i, k] += _err_cost(v - local_pred(k, a, b, c, d, pf[x]), lossless)
            ra, rb = rb, ra
    if wp or ls:
        for y in range(H):
            cy = y // MINB
            for x in range(W):
                if not valid[y, x]:
                    continue
                v = t[y, x]
                i = cells[cy, x // MINB]
                if wp:
                    cost[i, K_WP] += _err_cost(v - pw[y, x], lossless)
                if ls:
                    cost[i, K_LS] += _err_cost(v - pls[y, x], lossless)
    for i in range(nleaf):
        best = 0
        for k in range(1, NK):
            if (k != K_WP or wp) and (k != K_LS or ls) and cost[i, k] < cost[i, best]:
                best = k
        leaves[i, 4] = best


#: Error feedback: the W and N neighbours' prediction errors weigh in sixteenths, |weight| <= 16.
FB_SHIFT = 4
FB_MAX = 16


#: The clips (quanta) of the error-feedback fits: the W and N neighbours' errors and the
#: sample's, clipped at each, give a least-squares fit each (:func:`feedback_weights`).
FB_CLIPS = (1, 2, 8, 64)
#: Every FB_STRIDE-th row of a band (of 2 FB_STRIDE rows or more) is sampled for the fits and costs.
FB_STRIDE = 8
#: The least share of its log cost a fit must save against no feedback to be tried.
FB_MIN_GAIN = 0.02


@helper(inline=False)
def _fit(sww, swn, snn, swe, sne):
    """The least-squares weights (aw, an) in sixteenths, clamped to |w| <= :data:`FB_MAX`, from
    the sums of products of the W, N and own errors; (0, 0) when W and N are collinear."""
    det = sww * snn - swn * swn
    if det <= 1e-9 * (sww * snn + 1e-300):
        return 0, 0
    aw = (swe * snn - sne * swn) / det
    an = (sne * sww - swe * swn) / det
    qw = min(max(int(round(aw * (1 << FB_SHIFT))), -FB_MAX), FB_MAX)
    qn = min(max(int(round(an * (1 << FB_SHIFT))), -FB_MAX), FB_MAX)
    return qw, qn


@helper(inline=False)
def _row_sums(e, ea, v, c, sums):
    """Add a row's sums of products of the W, N and own errors, each clipped at ``c``, to
    ``sums`` (5,) int64 (sww, swn, snn, swe, sne): ``e``, ``ea`` (W + 1,) int64 the row's and the
    row above's errors after a 0, ``v`` (W,) bool the row's valid samples. Integers: clipped
    errors below 2**11, products below 2**22, no overflow below 2**41 samples."""
    sww = swn = snn = swe = sne = 0
    for x in range(v.shape[0]):
        m = np.int64(v[x])
        fe = min(max(e[x + 1], -c), c)
        fw = min(max(e[x], -c), c) * m
        fn = min(max(ea[x + 1], -c), c) * m
        sww += fw * fw
        swn += fw * fn
        snn += fn * fn
        swe += fw * fe
        sne += fn * fe
    sums[0] += sww
    sums[1] += swn
    sums[2] += snn
    sums[3] += swe
    sums[4] += sne


@helper(inline=False)
def _row_cost(e, ea, v, aw, an):
    """The summed :func:`_log_cost` of a row's errors less the feedback ``aw``, ``an`` of their W
    and N neighbours' (arrays as :func:`_row_sums`)."""
    cost = 0
    for x in range(v.shape[0]):
        r = e[x + 1] - ((aw * e[x] + an * ea[x + 1]) >> FB_SHIFT)
        cost += _log_cost(r) * np.int64(v[x])
    return cost


@kernel
def feedback_weights(t, valid, cells, leaves, lcoef, pw, pls):
    """The band's error-feedback weights (aw, an), in sixteenths, added to each sample's
    prediction as ``(aw * eW + an * eN) >> FB_SHIFT`` of its W and N neighbours' prediction
    errors (each leaf's predictor over the targets). The errors of an oversampling camera's
    sub-pixel depth are correlated along the stripes; white noise gives weights near 0.

    Candidates: no feedback and one least-squares fit of each sample's error to its neighbours'
    per clip of :data:`FB_CLIPS` (errors clipped there), over every :data:`FB_STRIDE`-th row;
    the fit of least summed :func:`_log_cost` of the errors it leaves, where that is below
    ``1 - FB_MIN_GAIN`` of no feedback's, else (0, 0). The encoder then keeps the weights only
    where the band codes smaller with them. One fit alone (clipped at 64 quanta) made the
    bunny at 1:1 sampling code 1.6 % larger than with no feedback: on a far backdrop the
    decoder's one-column misreads are errors of +-100 quanta, which a least-squares fit follows.
    The errors do not depend on the weights: they are computed once, and every candidate is
    costed on the rows kept.
    ``pw``, ``pls`` (H, W) int64: the weighted and least-squares predictors' predictions where a
    leaf takes them (:func:`wp_band`, :func:`shared.compress._ls.ls_band`)."""
    H, W = t.shape
    nc = len(FB_CLIPS)
    stride = FB_STRIDE if H >= 2 * FB_STRIDE else 1
    ns = H // stride
    pf = zeros(W, np.int64)
    kr = zeros(W, np.int64)
    ra = zeros(W + 3, np.int64)
    rb = zeros(W + 3, np.int64)
    ea = zeros(W + 1, np.int64)  # the row above's errors (0 where invalid) after a 0
    eb = zeros(W + 1, np.int64)  # this row's
    kept = zeros((ns, 2, W + 1), np.int64)  # the sampled rows' errors and the rows' above
    for y in range(H):
        target_row(y, t, valid, cells, leaves, lcoef, pf, kr, ra, rb)
        for x in range(W):
            if not valid[y, x]:
                eb[x + 1] = 0
                continue
            k = kr[x]
            if k == K_WP:
                pl = pw[y, x]
            elif k == K_LS:
                pl = pls[y, x]
            else:
                pl = local_pred(k, rb[x], ra[x + 1], ra[x], ra[x + 2], pf[x])
            eb[x + 1] = min(max(t[y, x] - pl, -E_LIM), E_LIM)
        if y % stride == stride - 1:
            # element by element: an array assigned to a slice has numba compile its shape
            # mismatch's message (1.75 s of string formatting)
            for x in range(W + 1):
                kept[y // stride, 0, x] = ea[x]
                kept[y // stride, 1, x] = eb[x]
        ra, rb = rb, ra
        ea, eb = eb, ea
    # one fit per clip, then each fit's cost and no feedback's, a sampled row at a time
    cw = zeros(nc + 1, np.int64)
    cn = zeros(nc + 1, np.int64)
    for j in range(nc):
        sums = zeros(5, np.int64)
        for i in range(ns):
            _row_sums(kept[i, 1], kept[i, 0], valid[i * stride + stride - 1], FB_CLIPS[j] * FINE, sums)
        cw[j + 1], cn[j + 1] = _fit(float(sums[0]), float(sums[1]), float(sums[2]), float(sums[3]), float(sums[4]))
    best = 0
    best_cost = 0.0
    for j in range(nc + 1):
        if j > 0 and cw[j] == 0 and cn[j] == 0:
            continue
        cost = 0
        for i in range(ns):
            cost += _row_cost(kept[i, 1], kept[i, 0], valid[i * stride + stride - 1], cw[j], cn[j])
        if j == 0:
            best_cost = (1.0 - FB_MIN_GAIN) * cost
        elif cost < best_cost:
            best = j
            best_cost = float(cost)
    return cw[best], cn[best]


@helper
def _activity(a, b, c, d, ew, en, enw, ene, grad, errs, wp, me):
    """A sample's activity (fine units): the curvature of the row above and its neighbours'
    prediction errors ``ew``, ``en``, ``enw``, ``ene``; with ``wp`` :func:`_wp_activity`."""
    act = 0
    if grad:
        act += min(abs(d - 2 * b + c), E_LIM)
    if errs:
        act += 2 * ew + en + ((enw + ene) >> 1)
    if wp:
        act = _wp_activity(act, me)
    return act


def activity_tables(lut: np.ndarray) -> np.ndarray:
    """The table (4097,) uint8 of each activity (fine units) >> 2, the last for all above, from
    the levels' tables ``lut`` (NLEVEL,): where the level itself is not wanted (no bias
    cancellation, no sign contexts) the decoder finds a residual's table in one look-up, not
    two, on its critical path (the 15 MP bench image decoded 8 % slower with two). uint8 (a
    table index is at most NLEVEL - 1, the decoder checks the flags): 4 kB beside the rANS
    tables in the core's cache, not 32 kB as int64 (the 15 MP image's lossless decode, A/B in
    alternating processes, CPU ms: median of medians 342 -> 289, of minima 281 -> 264)."""
    return np.append(lut[LEVEL_LUT], lut[NLEVEL - 1]).astype(np.uint8)


@helper
def _bias_context(a, b, c, d, lev):
    """Bias cancellation's context (< NBIAS): the signs of the gradients W-NW, N-NW, NE-N and the
    activity level in four groups."""
    return (_sign3(a - c) * 9 + _sign3(b - c) * 3 + _sign3(d - b)) * 4 + (min(lev, NCTX - 1) >> 2)


@helper
def _sign_context(p, rn, lossless):
    """A band's sign context of a sample predicted ``p`` (fine units) whose N neighbour's residual
    was ``rn`` (quanta): (pattern < :data:`NSUB`, flip -1 or 0; a residual r is coded as
    ``(r ^ flip) - flip``). In lossless mode ``p`` rounds to the nearest quantum, so its offset f
    from it says which sign the residual leans to: with ``flip`` (f < 0) the residual is coded
    negated, so every table sees the lean one way, and |f| >= a quarter quantum is a pattern of
    its own; the N neighbour's residual sign (as flipped) joins it. An oversampling camera's
    sub-pixel depth leaves residuals of the same sign along a stripe, which the error feedback's
    linear weights do not take. Branch-free: the signs are as likely one way as the other (with
    branches the decoder ran 22 % slower than without sign contexts, with these 10 %)."""
    f = ((p + (FINE >> 1)) & (FINE - 1)) - (FINE >> 1) if lossless else 0
    flip = f >> 63
    far = 3 * (((FINE >> 2) - 1 - abs(f)) >> 63)
    sgn = np.int64(rn > 0) - np.int64(rn < 0)
    return 1 - far + ((sgn ^ flip) - flip), flip


@helper
def _wp_activity(act, me):
    """The activity of a band running the weighted predictor: half the usual one plus twice the
    weighted predictor's largest neighbour error ``me`` (fine units). Measured against the usual
    activity alone with the predictor on (bits per valid sample, lossless at 0.02 mm): dragon
    scans 5.364 -> 5.374 and 5.287 -> 5.248, relief 1:1 2.546 -> 2.538 and 2:1 2.163 -> 2.155;
    its error alone (4 me) cost 1-2 % more."""
    return (act >> 1) + 2 * me


@kernel
def wp_band(t, valid, cells, leaves, lcoef):
    """The weighted predictor over a band's targets (lossless mode: they are the reconstruction):
    its prediction (H, W) int64 and its largest neighbour error (H, W) int64, fine units."""
    H, W = t.shape
    pw = zeros((H, W), np.int64)
    pe = zeros((H, W), np.int64)
    pf = zeros(W, np.int64)
    kr = zeros(W, np.int64)
    ra = zeros(W + 3, np.int64)
    rb = zeros(W + 3, np.int64)
    err_a = zeros((4, W + 4), np.int64)
    err_b = zeros((4, W + 4), np.int64)
    te_a = zeros(W + 4, np.int64)
    te_b = zeros(W + 4, np.int64)
    sub = zeros(4, np.int64)
    for y in range(H):
        if y == 0:
            row_prediction(y, W, cells, leaves, lcoef, pf, kr)
            first_row(ra, pf, valid, W)
        for x in range(W):
            rb[x + 1] = t[y, x]
        fill_row(ra, rb, valid, y, W)
        for x in range(W):
            if not valid[y, x]:
                wp_hole(x, err_b, te_b)
                continue
            a = rb[x] if x > 0 else ra[1]
            p, m = wp_predict(x, a, ra[x + 1], ra[x], ra[x + 2], err_a, err_b, te_a, te_b, sub)
            pw[y, x] = p
            pe[y, x] = m
            wp_update(x, t[y, x], p, sub, err_b, te_b)
        ra, rb = rb, ra
        err_a, err_b = err_b, err_a
        te_a, te_b = te_b, te_a
    return pw, pe


@kernel
def encode_residuals(t, valid, cells, leaves, lcoef, lossless, opts, bias, aw, an, t_res, tab, val, nb, n, pw, pe, wp,
                     sc, cofs, alt, pls, scale, chk):
    """Append the residual events of a band (raster order) after event ``n``, with bias
    cancellation when ``bias`` and error feedback ``aw``, ``an`` (:func:`feedback_weights`);
    with ``wp`` (lossless mode), ``pw`` and ``pe`` (H, W) are the weighted predictor's
    predictions and errors (:func:`wp_band`), else unused; ``pls`` (H, W) the least-squares
    predictor's predictions where a leaf takes it (lossless mode). Without sign contexts (``sc`` 0)
    each event's table is ``t_res`` plus its activity level (:func:`shared.compress._levels.context_choice` then
    :func:`shared.compress._levels.apply_contexts` make them tables); with them (``sc`` 1) it is its final table, the
    levels slid by ``cofs`` (:func:`_sign_context`); without them, ``alt`` (NLEVEL * (NSUB + 1),
    NSYM) int32, zero on entry (a (1, 1) array where the caller does not count), receives the
    symbol counts the residuals would have with them, by level and pattern (:func:`shared.compress._levels.sign_bits`:
    the encoder runs the second way only where it pays), and in NLEVEL rows more where it has
    them, with the curvature in the activity (``opts`` :data:`OPT_GRAD`), their counts by the
    level without it (:func:`shared.compress._levels.grad_counts`: a noisy band's curvature is noise). Where ``chk``
    (uint64) has an element (bounded mode; else empty), it receives the sum of
    :func:`shared.compress._check.add_row` over the reconstruction, which ``scale`` (the fine
    unit) makes the decoder's samples: the band's check before it is folded.
    Returns the count (or -1 when the buffers are full)."""
    H, W = t.shape
    pf = zeros(W, np.int64)
    kr = zeros(W, np.int64)
    ra = zeros(W + 3, np.int64)  # reconstructed samples (fine units) of the row above, padded
    rb = zeros(W + 3, np.int64)
    ea = zeros(W + 3, np.int64)  # |prediction error| (fine units) of the row above
    eb = zeros(W + 3, np.int64)
    sa = zeros(W + 3, np.int64)  # signed errors of the local predictors (feedback), row above
    sb = zeros(W + 3, np.int64)
    qa = zeros(W + 3, np.int64)  # residuals (quanta) of the row above (sign contexts)
    qb = zeros(W + 3, np.int64)
    bsum = zeros(NBIAS, np.int64)
    bcnt = zeros(NBIAS, np.int64)
    bcor = zeros(NBIAS, np.int64)
    grad = (opts & OPT_GRAD) != 0
    errs = (opts & OPT_ERR) != 0
    count_alt = sc == 0 and alt.shape[0] > 1
    count_g = count_alt and grad and alt.shape[0] > NLEVEL * NSUB
    half = FINE >> 1
    check = chk.shape[0] > 0
    f32, u32 = scratch(W)
    h = np.uint64(0)
    for y in range(H):
        row_prediction(y, W, cells, leaves, lcoef, pf, kr)
        pw_row = pw[y] if wp else pw[0]
        pe_row = pe[y] if wp else pe[0]
        if y == 0:
            first_row(ra, pf, valid, W)
        if not valid[y, 0]:
            rb[1] = ra[1]
        for x in range(W):
            if not valid[y, x]:
                if x > 0:
                    rb[x + 1] = rb[x]
                eb[x + 1] = 0
                sb[x + 1] = 0
                qb[x + 1] = 0
                continue
            a = rb[x] if x > 0 else ra[1]
            b = ra[x + 1]
            c = ra[x]
            d = ra[x + 2]
            # the activity of the neighbours' errors, then with the curvature (one level each)
            act_e = _activity(a, b, c, d, eb[x], ea[x + 1], ea[x], ea[x + 2], False, errs, False, 0)
            act = act_e + min(abs(d - 2 * b + c), E_LIM) if grad else act_e
            if wp:
                lev = _level_of(_wp_activity(act, at(pe_row, x)))
            else:
                lev = _level_of(act)
            lev_g = 0
            if count_g:
                lev_g = _level_of(_wp_activity(act_e, at(pe_row, x)) if wp else act_e)
            k = kr[x]
            if k == K_WP:
                pl = at(pw_row, x)
            elif k == K_LS:
                pl = pls[y, x]
            else:
                pl = local_pred(k, a, b, c, d, pf[x])
            p0 = pl + ((aw * sb[x] + an * sa[x + 1]) >> FB_SHIFT)
            q = 0
            p = p0
            if bias:
                q = _bias_context(a, b, c, d, lev)
                p += bcor[q]
            if lossless:
                r = (t[y, x] >> F_SHIFT) - ((p + half) >> F_SHIFT)
                rec = t[y, x]
            else:
                r = (t[y, x] - p + half) >> F_SHIFT
                rec = p + (r << F_SHIFT)
            if sc:
                pat, flip = _sign_context(p, qa[x + 1], lossless)
                g = min(max(lev - cofs, 0), NCTX - 1) >> 2
                n = put_value(tab, val, nb, n, t_res + g * NSUB + pat, zigzag((r ^ flip) - flip), L_RES, M_RES)
            else:
                n = put_value(tab, val, nb, n, t_res + lev, zigzag(r), L_RES, M_RES)  # a level: see context_choice
                if count_alt:
                    pat, flip = _sign_context(p, qa[x + 1], lossless)
                    alt[lev * NSUB + pat, symbol_of(np.int64(zigzag((r ^ flip) - flip)), L_RES, M_RES)] += 1
                    if count_g:
                        alt[NLEVEL * NSUB + lev_g, symbol_of(np.int64(zigzag(r)), L_RES, M_RES)] += 1
            qb[x + 1] = r
            rb[x + 1] = rec
            eb[x + 1] = min(abs(rec - p), E_LIM)
            sb[x + 1] = min(max(rec - pl, -E_LIM), E_LIM)
            if bias:
                _bias_update(bsum, bcnt, bcor, q, rec - p0)
        if check:
            h = add_row(h, rb, 1, 0, valid[y], y, W, scale, f32, u32)
        rb[0] = rb[1]
        rb[W + 1] = rb[W]
        rb[W + 2] = rb[W]
        ra, rb = rb, ra
        ea, eb = eb, ea
        sa, sb = sb, sa
        qa, qb = qb, qa
        sb[0] = 0
    if check:
        chk[0] = h
    return n


@helper
def _bias_update(bsum, bcnt, bcor, q, err):
    s = at(bsum, q) + min(max(err, -E_LIM), E_LIM)
    m = at(bcnt, q) + 1
    if m >= BIAS_RESET:
        s >>= 1
        m >>= 1
    set_at(bsum, q, s)
    set_at(bcnt, q, m)
    set_at(bcor, q, (s * at(RECIP, m)) >> 16)


@kernel
def decode_residuals(xa, xb, pos, words, nw, sym, fb, valid, cells, leaves, lcoef, lossless, bias, aw, an, cofs, lut,
                     wp, sc, scale, t_res, out, lsw, grad):
    """Inverse of :func:`encode_residuals` (with every option on) into ``out`` (H, W) float32,
    NaN where invalid, running the weighted predictor along when ``wp``, with sign contexts
    when ``sc`` (their groups of levels slid by ``cofs``), else the tables ``lut`` (4097,) uint8
    of the activities (:func:`activity_tables` of :func:`shared.compress._levels.partition_tables`), the least-squares
    weights ``lsw`` (NLS,) int64 for the leaves that take them, the curvature in the activity
    when ``grad``; returns (xa, xb, pos)."""
    H, W = valid.shape
    pf = zeros(W, np.int64)
    kr = zeros(W, np.int64)
    ra = zeros(W + 3, np.int64)
    rb = zeros(W + 3, np.int64)
    rc = zeros(W + 3, np.int64)  # the row two above (the least-squares predictor)
    ea = zeros(W + 3, np.int64)
    eb = zeros(W + 3, np.int64)
    sa = zeros(W + 3, np.int64)
    sb = zeros(W + 3, np.int64)
    qa = zeros(W + 3, np.int64)
    qb = zeros(W + 3, np.int64)
    bsum = zeros(NBIAS, np.int64)
    bcnt = zeros(NBIAS, np.int64)
    bcor = zeros(NBIAS, np.int64)
    err_a = zeros((4, W + 4), np.int64)  # the weighted predictor's state (shared.compress._wp)
    err_b = zeros((4, W + 4), np.int64)
    te_a = zeros(W + 4, np.int64)
    te_b = zeros(W + 4, np.int64)
    sub = zeros(4, np.int64)
    half = FINE >> 1
    nan = np.float32(np.nan)
    sh = F_SHIFT if lossless else 0
    for y in range(H):
        row_prediction(y, W, cells, leaves, lcoef, pf, kr)
        if y == 0:
            first_row(ra, pf, valid, W)
            for x in range(W + 3):  # scalar loops: slices cost seconds of compilation
                rc[x] = ra[x]
        vrow = valid[y]
        orow = out[y]
        if not vrow[0]:
            rb[1] = ra[1]
        for x in range(W):
            if not at(vrow, x):
                if x > 0:
                    set_at(rb, x + 1, at(rb, x))
                set_at(eb, x + 1, 0)
                set_at(sb, x + 1, 0)
                set_at(qb, x + 1, 0)
                set_at(orow, x, nan)
                if wp:
                    wp_hole(x, err_b, te_b)
                continue
            a = at(rb, x) if x > 0 else at(ra, 1)
            b = at(ra, x + 1)
            c = at(ra, x)
            d = at(ra, x + 2)
            k = at(kr, x)
            pw = 0
            me = 0
            if wp:
                pw, me = wp_predict(x, a, b, c, d, err_a, err_b, te_a, te_b, sub)
            act = _activity(a, b, c, d, at(eb, x), at(ea, x + 1), at(ea, x), at(ea, x + 2), grad, True, wp, me)
            lev = _level_of(act) if bias or sc else 0
            if k == K_WP:
                pl = pw
            elif k == K_LS:
                pl = ls_predict(x, W, a, ra, rb, rc, lsw)
            else:
                pl = local_pred(k, a, b, c, d, at(pf, x))
            p0 = pl + ((aw * at(sb, x) + an * at(sa, x + 1)) >> FB_SHIFT)
            q = 0
            p = p0
            if bias:
                q = _bias_context(a, b, c, d, lev)
                p += at(bcor, q)
            flip = 0
            if sc:
                pat, flip = _sign_context(p, at(qa, x + 1), lossless)
                tb = (min(max(lev - cofs, 0), NCTX - 1) >> 2) * NSUB + pat
            else:
                tb = at(lut, min(act >> 2, 4096))
            u, xa, xb, pos = read_value(xa, xb, pos, words, nw, sym, fb, t_res + tb, L_RES, M_RES)
            r = unzigzag(u)
            r = (r ^ flip) - flip
            set_at(qb, x + 1, r)
            if lossless:
                rec = (((p + half) >> F_SHIFT) + r) << F_SHIFT
            else:
                rec = p + (r << F_SHIFT)
            set_at(orow, x, np.float32((rec >> sh) * scale))
            set_at(rb, x + 1, rec)
            set_at(eb, x + 1, min(abs(rec - p), E_LIM))
            set_at(sb, x + 1, min(max(rec - pl, -E_LIM), E_LIM))
            if bias:
                _bias_update(bsum, bcnt, bcor, q, rec - p0)
            if wp:
                wp_update(x, rec, pw, sub, err_b, te_b)
        rb[0] = rb[1]
        rb[W + 1] = rb[W]
        rb[W + 2] = rb[W]
        rc, ra, rb = ra, rb, rc
        ea, eb = eb, ea
        sa, sb = sb, sa
        qa, qb = qb, qa
        sb[0] = 0
        err_a, err_b = err_b, err_a
        te_a, te_b = te_b, te_a
    return xa, xb, pos
