"""A range band's encoder and decoder (private; the public API is :mod:`shared.compress.range`):
plain Python over the kernels of :mod:`shared.compress._quadtree` (the mask and the quadtree),
:mod:`shared.compress._lpred` (raster-order prediction and contexts) and
:mod:`shared.compress._interp` (the interpolation order), each kernel compiled once on its own
and releasing the GIL, so bands still code in parallel threads.

Per band the encoder codes the raster order with each tree margin of
:data:`shared.compress._quadtree.SPLIT_LOSSLESS` (lossless) and keeps the smaller stream (the
margins share the blocks' fits and the least-squares fit; a margin that builds a tree another
built is not coded again, nor the coarser ones where the first margin's leaves keep their
surface model: white noise, :data:`MARGIN_MODEL_MAX`), tries the weighted predictor (effort 2)
and bias cancellation (bounded; not in white noise, :data:`BIAS_MODEL_MAX`) both ways, codes
the residuals of the kept margin again with sign contexts where the first pass's counts say
they pay, and in bounded mode codes the interpolation order too (a
first pass, then, unless its estimate says the raster order's stream is smaller, a second with
the feedback weights and the tables the first pass's counts choose), keeping the smaller
stream.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from shared.compress import _levels as lv
from shared.compress import _lpred as lp
from shared.compress._check import fold, lossless_check
from shared.compress._interp import (
    FB_CAND,
    FB_MAX,
    HB,
    HG,
    NCAND,
    NLV,
    interp_decode,
    interp_events,
    sign_estimate,
)
from shared.compress._ls import NLS, ls_band, ls_weights, n_tiles
from shared.compress._mask import (
    MASK_CTX,
    MASK_RUNS,
    decode_mask,
    decode_mask_ctx,
)
from shared.compress._quadtree import (
    F_SHIFT,
    F_SIGNS,
    HEAD_N,
    MINB,
    MODE_INTERP,
    MODE_RASTER,
    N_FLAGS,
    NTABLES,
    SPLIT_BOUNDED,
    SPLIT_LOSSLESS,
    T_EDGE,
    T_PRED,
    T_RES,
    _decode_tree,
    _encode_tree,
    _leaf_cells,
    _put_predictors,
    _stream_bits,
    put_events,
    put_mask,
    tree_memo,
)
from shared.compress._rans import (
    NSYM,
    RANS_L,
    binary_bits,
    count_symbols,
    dec_init,
    decode_tables,
    encode_events,
    get_symbol,
    normalise,
)
from shared.compress._tables import pack_codes, quantise_tables, unpack_codes

#: Least share of a band's residual bits the weighted predictor must save to be used: it more
#: than halves the band's decoding speed (lossless relief 2:1 about 64 -> 29 MP per CPU second)
#: for 0.8-1.4 % on the simulated relief but 0.1-0.3 % on the bunny, fandisk and spot and 0.07 %
#: on white noise.
WP_MIN_GAIN = 0.005
#: Least share of a band's residual bits leaving the curvature of the row above out of the
#: activity must save to be taken (the residuals coded again): on a noisy real capture the
#: curvature is noise, and the neighbours' errors alone make the better context (the kamino410
#: captures 0 and 1, lossless: 0.56 and 0.64 % smaller), while the simulated relief's depth
#: codes 0.17 % larger without it.
GRAD_MIN_GAIN = 0.002
#: The least-squares predictor is not fitted in a lossless band whose leaves covering this share
#: of its area keep their surface model after the first choice (noise about a smooth surface,
#: where no leaf took it: the synthetic noise).
LS_MODEL_MAX = 0.8
#: The lossless tree margins after the first (:data:`SPLIT_LOSSLESS`) are not tried in a band
#: where leaves covering this share of its area keep their surface model at the first margin:
#: noise about a smooth surface, where a coarser tree only leaves the surface less well fitted.
#: Measured on the 75 lossless bands of the bench's table and its 15 MP image with both margins
#: coded: the 18 bands at 0.94-1.00 (the synthetic noise) all kept the first margin (the second
#: 0.02-0.8 % larger); every other band was at most 0.36 (the bunny at 1:1). Same bytes, and the
#: 15 MP image's lossless encoding about a third less work.
MARGIN_MODEL_MAX = 0.8
#: Bias cancellation (bounded mode) is not tried in a band where leaves covering this share of
#: its area keep their surface model: noise about a smooth surface, where the running means of
#: the errors are noise. Measured within 0.1 mm on every band of the bench's table and its 15 MP
#: image: the 20 such bands (0.95-1.00, the synthetic noise) coded 0.4-17 % larger with it; every
#: band it won was at most 0.10 (the simulated scenes). Same bytes, and one pass of the
#: residuals fewer a band.
BIAS_MODEL_MAX = 0.8
#: Least share of the leaves' summed costs (:func:`shared.compress._lpred.choose_predictors`) the
#: least-squares predictor must save to be tried: where it saves less, the stream hardly
#: shrinks and a band coded with it decodes at about 60 % of the speed (the bunny at 1:1, a real
#: capture and a Cyberware dragon coded the same tried at 0.2 % as at 1 %).
LS_MIN_GAIN = 0.01
#: Where the least-squares predictor lowers the leaves' summed costs below this share, the band
#: is not coded the other way too: in the bench's sixteen images and five test reliefs, 88 of
#: the 139 bands (and tree margins) it was tried in were such, and each coded smaller with it
#: (at most 0.990 of the stream without it); the 4 it coded larger had costs at 0.966-0.986.
LS_SURE = 0.95
#: About the bits of a tile's least-squares weights in a band's header: the stream without them
#: is kept unless the one with them is smaller by this much a tile.
LS_HEAD_BITS = 16.0 * NLS
#: A least-squares weight (:mod:`shared.compress._ls`) is coded as two bytes of itself plus this.
LS_BIAS = 1 << 15

#: int64 arguments of the kernels called from Python (one signature each, as from a kernel)
ZERO = np.int64(0)
ONE = np.int64(1)
TR = np.int64(T_RES)
#: No candidate counts (:func:`shared.compress._interp.interp_events`).
NO_HIST = np.zeros((1, 1, 1, 1, 1), np.int64)
NO_ALT = np.zeros((1, 1), np.int32)
#: No leaf's costs known (:func:`shared.compress._lpred.choose_predictors`).
NO_KNOWN = np.zeros(0, np.bool_)
#: No check wanted of a residual pass (lossless mode, or a way not kept).
NO_CHK = np.zeros(0, np.uint64)


def _save(tab: np.ndarray, val: np.ndarray, nb: np.ndarray, a: int, b: int) -> tuple[np.ndarray, ...]:
    """A copy of events a..b-1 (to put back with :func:`_restore` when another way codes larger)."""
    return tab[a:b].copy(), val[a:b].copy(), nb[a:b].copy()


def _restore(tab: np.ndarray, val: np.ndarray, nb: np.ndarray, a: int, saved: tuple[np.ndarray, ...]) -> None:
    """Put back events saved from event ``a`` on by :func:`_save`."""
    b = a + saved[0].shape[0]
    tab[a:b], val[a:b], nb[a:b] = saved


@dataclass
class _Margins:
    """What a band's tree margins share (:func:`_encode_events`): the mask's events, the blocks'
    fits, the least-squares weights once fitted (:func:`shared.compress._ls.ls_weights`: they do
    not depend on the tree) and their predictions, the first margin's leaves' costs and its
    choice of the activity, and the trees (leaves and models) already coded."""

    fitted: bool = False
    lsw: np.ndarray | None = None
    pls: np.ndarray | None = None
    trees: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    memo: tuple[np.ndarray, ...] = ()  # the blocks' fits (shared.compress._quadtree.tree_memo)
    grad: bool | None = None  # the curvature in the activity, once a margin chose (GRAD_MIN_GAIN)
    mask: tuple[np.ndarray, ...] = ()  # the mask's events (mask_events)
    costs: tuple[np.ndarray, np.ndarray] | None = None  # the first margin's leaves (keys), local predictors' costs

    def seen(self, leaves: np.ndarray, lcoef: np.ndarray) -> bool:
        """Whether this tree was coded already: then its stream would be the same."""
        return any(np.array_equal(lv, leaves) and np.array_equal(cf, lcoef) for lv, cf in self.trees)

    @staticmethod
    def _keys(leaves: np.ndarray, W: int) -> np.ndarray:
        # a block's place and size; a block's fit is the same in every margin (tree_memo)
        return (leaves[:, 1] * W + leaves[:, 0]) * 128 + leaves[:, 2]

    def keep_costs(self, leaves: np.ndarray, cost: np.ndarray, W: int) -> None:
        """Keep the leaves' local predictors' costs (the first margin's) for the next margin."""
        if self.costs is None:
            keys = self._keys(leaves, W)
            order = np.argsort(keys)
            self.costs = keys[order], cost[: leaves.shape[0], : lp.K_WP][order].copy()

    def known_costs(self, leaves: np.ndarray, cost: np.ndarray, valid: np.ndarray, W: int) -> np.ndarray:
        """Which leaves' local predictors' costs a previous margin counted (their rows of
        ``cost`` filled): the same blocks, below the rows whose neighbours depend on the tree
        (the first, and down to the first row that starts with a sample: holes at a row's
        start are filled from the row above, the first row's from the tree's virtual row)."""
        if self.costs is None or self.costs[0].size == 0:
            return NO_KNOWN
        keys, rows = self.costs
        mine = self._keys(leaves, W)
        at = np.minimum(np.searchsorted(keys, mine), keys.size - 1)
        starts = np.flatnonzero(valid[:, 0])
        free = (int(starts[0]) if starts.size else valid.shape[0]) + 1  # the first row not depending on the tree
        known = (keys[at] == mine) & (leaves[:, 1] >= free)
        cost[: leaves.shape[0], : lp.K_WP][known] = rows[at[known]]
        return known


#: :func:`_encode_events`' count where a band's tree margin built a tree another had built.
SAME_TREE = -2


def _encode_events(t: np.ndarray, valid: np.ndarray, lossless: bool, opts: int, margin: float, share: float,
                   tab: np.ndarray, val: np.ndarray, nb: np.ndarray,
                   shared: _Margins | None = None, scale: float = 1.0) -> tuple[int, _SignPass | None]:
    """Every event of one band, the residuals without sign contexts; returns the count (or -1
    when the event buffers are too small, :data:`SAME_TREE` when ``shared`` holds the tree
    already) and what coding them with sign contexts needs, with the band's check before it is
    folded (bounded mode, ``scale`` the fine unit; lossless bands' come from their targets).
    ``shared`` is what the band's tree margins share.

    Plain Python over the kernels (the tree's, the predictors', the residuals'), each compiled
    once on its own: as one kernel it spent 4.7 s of numba's time linking and optimising them
    all again."""
    H, W = t.shape
    lossless = bool(lossless)
    opts = np.int64(opts)
    shared = _Margins() if shared is None else shared
    nleaf_max = ((H + MINB - 1) // MINB) * ((W + MINB - 1) // MINB)
    leaves = np.zeros((nleaf_max, 5), np.int64)  # x0, y0, B, model, residual predictor
    lcoef = np.empty((nleaf_max, 6), np.int64)
    if not shared.memo:
        shared.memo = tree_memo(t, valid, lossless, int(opts))
    if not shared.mask:
        shared.mask = _mask_coded(valid)[1]
    n, nleaf = _encode_tree(t, valid, lossless, opts, float(margin), float(share), tab, val, nb, leaves, lcoef,
                            *shared.memo, *shared.mask)
    if n < 0:
        return -1, None
    if shared.seen(leaves[:nleaf, :4], lcoef[:nleaf]):
        # the same leaves make the same events (noise about smooth depth: both margins split
        # the first two of the 15 MP bench image's 14 bands alike)
        return SAME_TREE, None
    n = np.int64(n)
    nleaf = np.int64(nleaf)
    # 3. each leaf's residual predictor, then the residuals in raster order
    cells = _leaf_cells(np.int64(H), np.int64(W), leaves, nleaf)
    none = np.zeros((1, W), np.int64)  # the weighted predictor's arrays where it does not run
    pw = pe = none
    # the residuals' symbol counts with sign contexts, by level and pattern (lv.sign_bits), of
    # the way kept (alt) and of the way tried beside it (alt_b)
    count = (opts & lp.OPT_SIGN) != 0
    # the curvature in the activity: the first margin coded chooses, the others follow
    choose_grad = bool(opts & lp.OPT_GRAD) and shared.grad is None and count
    if shared.grad is False:
        opts = np.int64(opts & ~lp.OPT_GRAD)
    alt = np.zeros((lp.NLEVEL * (lp.NSUB + choose_grad), NSYM) if count else (1, 1), np.int32)
    alt_b = np.zeros_like(alt)
    # the reconstruction's check of the way kept (chk) and of the way tried beside it (chk_b)
    chk = NO_CHK if lossless else np.zeros(1, np.uint64)
    chk_b = NO_CHK if lossless else np.zeros(1, np.uint64)
    scale = float(scale)
    cost = np.empty((nleaf, lp.NK), np.int64)  # the leaves' summed costs by predictor
    known = shared.known_costs(leaves[:nleaf], cost, valid, W)
    lp.choose_predictors(t, valid, cells, leaves, lcoef, nleaf, lossless, opts, none, ZERO, none, ZERO, cost, ONE, known)
    shared.keep_costs(leaves[:nleaf], cost, W)
    # the least-squares predictor (lossless mode), where the leaves do not keep their fitted
    # surface (white noise): one more choice of every leaf, its weights in the header
    pls, lsw = none, None
    sure = False  # the least-squares predictor kept without coding the band the other way
    if lossless and (opts & lp.OPT_LS) and (opts & lp.OPT_PRED) and _model_share(leaves[:nleaf]) < LS_MODEL_MAX:
        if not shared.fitted:  # the fit does not depend on the tree: once for every margin
            shared.lsw = ls_weights(t, valid)
            shared.fitted = True
        lsw = shared.lsw
        if lsw is not None:
            # the predictions of the rows that do not depend on the tree are made once (ls_band)
            pls = ls_band(t, valid, cells, leaves, lcoef, lsw, shared.pls)
            shared.pls = pls
            lp.choose_predictors(t, valid, cells, leaves, lcoef, nleaf, lossless, opts, none, ZERO, pls, ONE, cost, ZERO,
                                 NO_KNOWN)
            # tried where the leaves' summed costs fall by LS_MIN_GAIN
            k = leaves[:nleaf, 4]
            with_ls = float(cost[np.arange(nleaf), k].sum())
            c0 = cost[:nleaf, : lp.K_WP]
            without = float(c0.min(axis=1).sum())
            if with_ls > (1.0 - LS_MIN_GAIN) * without:
                lp.choose_predictors(t, valid, cells, leaves, lcoef, nleaf, lossless, opts, none, ZERO, none, ZERO, cost,
                                     ZERO, NO_KNOWN)
                pls, lsw = none, None
            sure = with_ls < LS_SURE * without
    ls = ZERO if lsw is None else ONE
    # the flags of bias cancellation and the weighted predictor, the weights and each leaf's
    # predictor, then the residuals
    head_n = HEAD_N + (2 * NLS * n_tiles(W) if ls else 0)
    n_res = np.int64(n + head_n + nleaf)
    if n < 0 or n_res + 1 > tab.shape[0]:
        return -1, None
    bias = 0
    wp = 0
    if not lossless and (opts & lp.OPT_BIAS) and _model_share(leaves[:nleaf]) < BIAS_MODEL_MAX:
        # bias cancellation pays on smooth depth coarsely quantised (bounded mode), not on
        # noise: both ways, the smaller kept
        n1 = lp.encode_residuals(t, valid, cells, leaves, lcoef, lossless, opts, ONE, ZERO, ZERO, TR,
                                 tab, val, nb, n_res, none, none, ZERO, ZERO, ZERO, alt_b, pls, scale, chk_b)
        if n1 < 0:
            return -1, None
        with_bias = lv.context_choice(tab, val, nb, n_res, np.int64(n1), TR)[0]
        keep = _save(tab, val, nb, n_res, n1)
        n_end = lp.encode_residuals(t, valid, cells, leaves, lcoef, lossless, opts, ZERO, ZERO, ZERO,
                                    TR, tab, val, nb, n_res, none, none, ZERO, ZERO, ZERO, alt, pls, scale, chk)
        if n_end < 0 or with_bias < lv.context_choice(tab, val, nb, n_res, np.int64(n_end), TR)[0]:
            bias = 1
            _restore(tab, val, nb, n_res, keep)
            n_end = n1
            alt, alt_b = alt_b, alt
            chk, chk_b = chk_b, chk
    else:
        n_end = lp.encode_residuals(t, valid, cells, leaves, lcoef, lossless, opts, ZERO, ZERO, ZERO,
                                    TR, tab, val, nb, n_res, none, none, ZERO, ZERO, ZERO, alt, pls, scale, chk)
        if n_end < 0:
            return -1, None
        if ls and not sure:
            # the least-squares predictor both ways, the smaller kept: the leaves' costs are
            # not the code length (on depth held constant over 2 x 2 pixels, the local
            # predictors' errors are 0 at every other pixel, the fit's smaller but never 0:
            # with the leaves choosing by absolute error it coded 5 % larger)
            with_ls = lv.context_choice(tab, val, nb, n_res, np.int64(n_end), TR)[0]
            keep = _save(tab, val, nb, n_res, n_end)
            keep_k = leaves[:nleaf, 4].copy()
            lp.choose_predictors(t, valid, cells, leaves, lcoef, nleaf, lossless, opts, none, ZERO, none, ZERO, cost, ZERO,
                                 NO_KNOWN)
            n_res0 = np.int64(n + HEAD_N + nleaf)  # the header without the weights
            n0 = lp.encode_residuals(t, valid, cells, leaves, lcoef, lossless, opts, ZERO, ZERO, ZERO,
                                     TR, tab, val, nb, n_res0, none, none, ZERO, ZERO, ZERO, alt_b, none, scale, NO_CHK)
            if n0 < 0:
                return -1, None
            if lv.context_choice(tab, val, nb, n_res0, np.int64(n0), TR)[0] <= with_ls + LS_HEAD_BITS * n_tiles(W):
                ls, pls, head_n = ZERO, none, HEAD_N
                n_res, n_end = n_res0, n0
                alt, alt_b = alt_b, alt
            else:
                leaves[:nleaf, 4] = keep_k
                _restore(tab, val, nb, n_res, keep)
            alt_b[:] = 0
        if lossless and (opts & lp.OPT_WP):
            # the weighted predictor (a choice of every leaf, its error in the context): both
            # ways, kept where it saves WP_MIN_GAIN (it lost on the bunny at 4:1, where the
            # plane fits)
            without = lv.context_choice(tab, val, nb, n_res, np.int64(n_end), TR)[0]
            keep = _save(tab, val, nb, n_res, n_end)
            keep_k = leaves[:nleaf, 4].copy()
            pw, pe = lp.wp_band(t, valid, cells, leaves, lcoef)
            lp.choose_predictors(t, valid, cells, leaves, lcoef, nleaf, lossless, opts, pw, ONE, pls, ls, cost, ZERO,
                                 NO_KNOWN)
            n1 = lp.encode_residuals(t, valid, cells, leaves, lcoef, lossless, opts, ZERO, ZERO, ZERO,
                                     TR, tab, val, nb, n_res, pw, pe, ONE, ZERO, ZERO, alt_b, pls, scale, NO_CHK)
            if n1 < 0:
                return -1, None
            if lv.context_choice(tab, val, nb, n_res, np.int64(n1), TR)[0] < (1.0 - WP_MIN_GAIN) * without:
                wp = 1
                n_end = n1
                alt, alt_b = alt_b, alt
            else:
                _restore(tab, val, nb, n_res, keep)
                leaves[:nleaf, 4] = keep_k
    # error feedback (none until here: tried last, on the band's other choices)
    aw = an = ZERO
    if lossless and (opts & lp.OPT_FEEDBACK):
        # error feedback (lossless mode: in bounded mode the reconstruction's rounding noise in
        # the neighbours' errors made it cost more than it saved), on the band's other choices:
        # the weights feedback_weights finds, kept where the band codes smaller with them (their
        # log cost leaves out the activity contexts, which follow the neighbours' errors
        # already: the weights alone coded the Cyberware dragon 1.2 % larger than no feedback,
        # and a least-squares fit alone the bench's images up to 4.3 % larger)
        fw, fn = lp.feedback_weights(t, valid, cells, leaves, lcoef, pw, pls)
        if fw != 0 or fn != 0:
            without = lv.context_choice(tab, val, nb, n_res, np.int64(n_end), TR)[0]
            keep = _save(tab, val, nb, n_res, n_end)
            alt_b[:] = 0
            n1 = lp.encode_residuals(t, valid, cells, leaves, lcoef, lossless, opts, np.int64(bias), np.int64(fw),
                                     np.int64(fn), TR, tab, val, nb, n_res, pw, pe, np.int64(wp), ZERO, ZERO, alt_b,
                                     pls, scale, NO_CHK)  # fmt: skip
            if n1 < 0:
                return -1, None
            if lv.context_choice(tab, val, nb, n_res, np.int64(n1), TR)[0] < without:
                aw, an = np.int64(fw), np.int64(fn)
                n_end = n1
                alt, alt_b = alt_b, alt
            else:
                _restore(tab, val, nb, n_res, keep)
    # the residual tables, one a run of activity levels (level_partition), and the activity
    # without the curvature where the residuals' counts say it codes smaller
    counts, raw = lv.level_counts(tab, val, nb, n_res, np.int64(n_end), TR)
    bits, lut = lv.level_partition(counts, raw)  # the levels' tables: bits as the coder spends them
    if choose_grad and lv.level_partition(lv.grad_counts(alt), raw)[0] < (1.0 - GRAD_MIN_GAIN) * bits:
        opts = np.int64(opts & ~lp.OPT_GRAD)
        alt = np.zeros((lp.NLEVEL * lp.NSUB, NSYM), np.int32)
        n_end = lp.encode_residuals(t, valid, cells, leaves, lcoef, lossless, opts, np.int64(bias), aw, an, TR,
                                    tab, val, nb, n_res, pw, pe, np.int64(wp), ZERO, ZERO, alt, pls, scale, chk)
        if n_end < 0:
            return -1, None
        counts, raw = lv.level_counts(tab, val, nb, n_res, np.int64(n_end), TR)
        bits, lut = lv.level_partition(counts, raw)
    grad = int(bool(opts & lp.OPT_GRAD))
    # the sign contexts' offset (their groups of four levels; sign_bits counts their bits as
    # level_partition counts the levels')
    cofs = lv.choice_of(counts, raw)[1]
    lv.apply_levels(tab, n_res, np.int64(n_end), TR, lut)
    head = np.zeros(head_n, np.int64)
    head[:N_FLAGS] = bias, cofs, wp, aw + lp.FB_MAX, an + lp.FB_MAX, grad, 0, ls
    head[N_FLAGS:HEAD_N] = np.diff(lut)
    if ls:
        u = lsw + LS_BIAS  # each weight as two bytes
        head[HEAD_N::2], head[HEAD_N + 1 :: 2] = u >> 8, u & 255
    _put_predictors(tab, val, nb, n, head, leaves, nleaf)
    gain = 0.0
    if opts & lp.OPT_SIGN:
        gain = bits - lv.sign_bits(alt, np.int64(cofs), tab, nb, n_res, np.int64(n_end))
    signs = _SignPass(t, valid, cells, leaves, lcoef, lossless, opts, np.int64(bias), aw, an, pw, pe, np.int64(wp),
                      np.int64(cofs), alt, n + F_SIGNS, n_res, gain, pls, scale, int(chk[0]) if chk.size else 0)
    # kept once coded: a margin whose buffers were too small codes its tree again
    shared.trees.append((leaves[:nleaf, :4].copy(), lcoef[:nleaf].copy()))
    if choose_grad:
        shared.grad = bool(grad)
    return int(n_end), signs


@dataclass
class _SignPass:
    """What the residuals of a band coded without sign contexts need to be coded again with
    them (:func:`_with_signs`), and the bits that would save (estimated; <= 0: none)."""

    t: np.ndarray
    valid: np.ndarray
    cells: np.ndarray
    leaves: np.ndarray
    lcoef: np.ndarray
    lossless: bool
    opts: np.int64
    bias: np.int64
    aw: np.int64
    an: np.int64
    pw: np.ndarray
    pe: np.ndarray
    wp: np.int64
    cofs: np.int64
    alt: np.ndarray
    flag: int  # the event holding the band's sign-context flag
    n_res: np.int64
    gain: float
    pls: np.ndarray
    scale: float
    check: int  # the reconstruction's check before it is folded (bounded mode; else 0)


def _with_signs(p: _SignPass, tab: np.ndarray, val: np.ndarray, nb: np.ndarray, n_end: int) -> int:
    """Code the band's residuals again with sign contexts (from event ``p.n_res``; the flag set);
    returns the new count, or ``n_end`` with the events unchanged when the buffers are too small."""
    keep = _save(tab, val, nb, p.n_res, n_end)
    n1 = lp.encode_residuals(p.t, p.valid, p.cells, p.leaves, p.lcoef, p.lossless, p.opts, p.bias, p.aw, p.an, TR,
                             tab, val, nb, p.n_res, p.pw, p.pe, p.wp, ONE, p.cofs, p.alt, p.pls, p.scale, NO_CHK)
    if n1 < 0:
        _restore(tab, val, nb, p.n_res, keep)
        return n_end
    val[p.flag] = 1
    return int(n1)


def _coded(cap: int, code: Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[Any, ...]]
           ) -> tuple[int, tuple[np.ndarray, ...], tuple[Any, ...]]:
    """``code(tab, val, nb)`` into event buffers of ``cap`` events, four times larger until the
    count its answer starts with is not -1 (full buffers). Returns (the capacity used, the
    buffers, its answer)."""
    while True:
        bufs = (np.empty(cap, np.int8), np.empty(cap, np.int16), np.empty(cap, np.int8))  # val: a symbol or raw bits
        out = code(*bufs)
        if out[0] != -1:
            return cap, bufs, out
        cap *= 4


#: The interpolation order is not tried in a band where leaves covering this share of its area
#: predict their samples from their surface model alone: noise about a smooth surface, which a
#: fitted model predicts better than any mean of two noisy neighbours. Measured on every band of
#: the synthetic noise, the bunny at 1:1, the fandisk, the relief at 4:1 and a real capture within
#: 0.1 mm: the synthetic noise's bands 0.95-1.00 (interpolation lost by 6.5-8.5 %), every band
#: where interpolation won at most 0.43.
INTERP_MODEL_MAX = 0.8


def _model_share(leaves: np.ndarray) -> float:
    """The share of a band's leaf area (``leaves`` (n, 5) int64 of :func:`_encode_events`; unused
    rows zero) whose residual predictor is the leaf's model alone."""
    area = leaves[:, 2].astype(np.float64) ** 2
    total = area.sum()
    return float(area[leaves[:, 4] == 0].sum() / total) if total > 0 else 0.0


#: A band's mask is tried in context only where its runs cost at least this many bits a sample
#: of the band (one in a hundred): less is not worth the context coder's pass over every sample
#: (about 4 ms a band of 256 x 4480), and is what silhouettes cost (the simulated relief 0.001,
#: bunny 0.005 bits a sample, where the runs are smaller), not speckle (the real captures 0.16 -
#: 0.33 as runs).
MASK_CTX_MIN = 0.01


Events = tuple[np.ndarray, np.ndarray, np.ndarray]


def mask_events(valid: np.ndarray, coder: int) -> Events:
    """A band's mask ``valid`` (H, W) bool as events (tables, values, raw bit counts) by the
    coder ``coder`` (:func:`shared.compress._quadtree.put_mask`): coded once, copied into each
    way the band is coded. Sized to the mask: a sample a binary event in context; as runs, at
    most a few events a run's end."""
    if coder == MASK_CTX:
        cap = valid.size + 64
    else:
        cap = 3 * int(np.count_nonzero(valid[:, 1:] != valid[:, :-1])) + 3 * valid.shape[0] + 4096
    _, (tab, val, nb), (n,) = _coded(cap, lambda tb, vl, nbt: (put_mask(valid, tb, vl, nbt, ZERO, np.int64(coder)),))
    return tab[:n], val[:n], nb[:n]


def _mask_coded(valid: np.ndarray) -> tuple[int, Events]:
    """A band's mask ``valid`` (H, W) bool by the coder of fewer bits
    (:data:`shared.compress._mask.MASK_RUNS` or ``MASK_CTX``) and its events
    (:func:`mask_events`): the runs' bits as :func:`_stream_bits` counts them (their tables with
    them), the binary events' as the rANS coder spends them
    (:func:`shared.compress._rans.binary_bits`)."""
    H, W = valid.shape
    runs = mask_events(valid, MASK_RUNS)
    bits = _stream_bits(*(a[1:] for a in runs), np.int64(runs[0].size - 1))  # after the coder's symbol
    if bits < MASK_CTX_MIN * H * W:
        return MASK_RUNS, runs
    ctx = mask_events(valid, MASK_CTX)
    return (MASK_CTX, ctx) if binary_bits(ctx[0], ctx[1]) < bits else (MASK_RUNS, runs)


def encode_band(t: np.ndarray, valid: np.ndarray, lossless: bool, opts: int,
                scale: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Code one band: ``t`` (H, W) int64 fine-unit targets, ``valid`` (H, W) bool; ``opts`` the
    encoder's options (:data:`shared.compress._lpred.OPT_ALL` for a decodable stream; fewer for
    ablation); ``scale`` the quantum (lossless) or the fine unit (bounded), as the decoder is
    given it. Returns (packed tables uint8, rANS words uint16, the check of the samples they
    decode to: :func:`shared.compress._check.output_check`).

    Plain Python over the kernels (each releases the GIL, so bands still code in parallel
    threads): as a kernel of its own it cost numba 2.2 s to compile, its module linking and
    optimising again every kernel it calls, for a handful of calls a band."""
    H, W = t.shape
    margins = SPLIT_LOSSLESS if lossless else SPLIT_BOUNDED[:1]
    share = 0.0 if lossless else SPLIT_BOUNDED[1]
    best = np.inf
    tab = val = nb = None
    n = 0
    shared = _Margins(mask=_mask_coded(valid)[1])
    # about one event a valid sample, a few a leaf and a row, the mask's; rarely escapes
    # (retried when short)
    cap = H * W + (H * W >> 2) + 64 * (H + 1) + 4096 + shared.mask[0].size
    signs = None
    check = 0  # the interpolation order's sum, where it is kept
    interp = not lossless and bool(opts & lp.OPT_INTERP)
    compare = len(margins) > 1 or interp  # streams' bits wanted
    for margin in margins:
        cap, (tab_i, val_i, nb_i), (n_i, signs_i) = _coded(
            cap, lambda tb, vl, nbt, m=margin: _encode_events(t, valid, bool(lossless), np.int64(opts), float(m),
                                                             float(share), tb, vl, nbt, shared, scale))
        if n_i == SAME_TREE:
            continue
        # each margin's stream without sign contexts, less what they would save: the residuals
        # are coded again with them for the margin kept alone
        bits = _stream_bits(tab_i, val_i, nb_i, np.int64(n_i)) - max(signs_i.gain, 0.0) if compare else 0.0
        if bits < best:
            best = bits
            tab, val, nb, n, signs = tab_i, val_i, nb_i, n_i, signs_i
        if lossless and _model_share(signs_i.leaves) >= MARGIN_MODEL_MAX:
            break
    if interp and _model_share(signs.leaves) < INTERP_MODEL_MAX:
        # hierarchical interpolation (smooth detailed depth within a bound): both ways, the
        # smaller kept
        cap, (tab_i, val_i, nb_i), (n_i, bits_i, check_i) = _coded(
            cap, lambda tb, vl, nbt: _interp_band(t, valid, tb, vl, nbt, best, opts, mask=shared.mask, scale=scale))
        if n_i >= 0 and bits_i < best:
            tab, val, nb, n, signs = tab_i, val_i, nb_i, n_i, None
            check = check_i
    if signs is not None and signs.gain > 0:
        n = _with_signs(signs, tab, val, nb, n)
    if lossless:  # the samples are the targets
        check = lossless_check(t, valid, float(scale), np.int64(F_SHIFT))
    else:  # the sum of the way kept: the raster order's (sign contexts flip what is coded, not
        # what is decoded) or the interpolation order's
        check = fold(np.uint64(signs.check if signs is not None else check))
    return (*_pack(tab, val, nb, n), int(check))


def _pack(tab: np.ndarray, val: np.ndarray, nb: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A band's events 0..n-1 as (packed tables uint8, rANS words uint16)."""
    codes, freq = quantise_tables(normalise(count_symbols(tab, val, np.int64(n), np.int64(NTABLES))))
    words = encode_events(tab, val, nb, np.int64(n), freq)
    return pack_codes(codes), words


#: The interpolation order is given up, its second pass untried, where its first pass's
#: estimate of what the second would code (the mask's bits, then the residuals': the weights
#: chosen, in level or sign tables) is more than this many times the raster order's whole
#: stream. Measured on every band of the synthetic noise, the bunny at 1:1 and 2:1, the spot,
#: the fandisk, the relief at 4:1 and two real captures within 0.1 mm: the estimate was 0-5 %
#: below the stream coded or at most 0.9 % above it; every band where interpolation
#: won was estimated at most 0.995 times the raster order's stream, the synthetic noise's
#: 1.035-1.058 (it lost by 6.5-8.5 %).
INTERP_GIVE_UP = 1.01
#: The first pass's feedback weights (pass A, pass B at every spacing): the weights most bench
#: bands chose (an oversampling camera's sub-pixel errors run along its rows, so the error of
#: the sample before in a row predicts the next one; pass A's sample before is two apart).
FB_FIRST = (0, 9)


def feedback_choice(hist: np.ndarray) -> tuple[np.ndarray, float]:
    """The feedback weights (NLV, 2) int64 whose candidate symbol counts ``hist`` (from
    :func:`shared.compress._interp.interp_events`) code in the fewest bits, by level and pass:
    each activity group's bins in a table of their own, as the band's contexts do, plus the
    bits inside each octave bin; and the share of the first pass's bits (its weights
    :data:`FB_FIRST`) the estimate gives them."""
    h = hist.astype(np.float64)
    tot = h.sum(axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        ent = -np.where(h > 0, h * np.log2(h / np.where(tot > 0, tot, 1.0)), 0.0)
    bits = (ent + h * _OCTAVE_BITS).sum(axis=(-1, -2))  # (NLV, 2, NCAND)
    pick = np.argmin(bits, axis=-1)  # ties: the smallest weight
    first = np.searchsorted(FB_CAND, FB_FIRST)[None, :].repeat(NLV, 0)
    before = np.take_along_axis(bits, first[..., None], -1).sum()
    after = np.take_along_axis(bits, pick[..., None], -1).sum()
    return FB_CAND[pick].astype(np.int64), float(after / before) if before > 0 else 1.0


#: Bits inside each bin of the candidates' counts (:data:`shared.compress._interp.HB`).
_OCTAVE_BITS = np.array([0.0] * 8 + [3.0 + j for j in range(HB - 8)])


def _interp_band(t: np.ndarray, valid: np.ndarray, tab: np.ndarray, val: np.ndarray, nb: np.ndarray,
                 rival: float = np.inf, opts: int = lp.OPT_ALL, force: int | None = None,
                 mask: tuple[np.ndarray, ...] = (), scale: float = 1.0) -> tuple[int, float, int]:
    """Every event of one band in interpolation order (bounded mode): the mask (its events
    ``mask``, :func:`mask_events`; as runs where not given), the mode, the
    residual tables' offset and merging, whether they are sign contexts, the error feedback's
    weights, the residuals. ``opts``: without :data:`shared.compress._lpred.OPT_FEEDBACK` no
    feedback, without :data:`shared.compress._lpred.OPT_SIGN` level tables only (ablation);
    ``force`` (tests): the second pass's way kept whatever its size (1 sign contexts, 0 level
    tables). Returns (the count, the stream's bits as :func:`_stream_bits` counts them, the
    band's check before it is folded, ``scale`` the fine unit); the count -1 when the event
    buffers are too small, or -2 when the first pass's estimate of the stream is more than
    :data:`INTERP_GIVE_UP` times ``rival`` bits (the raster order's stream)."""
    n = put_events(tab, val, nb, ZERO, *(mask or mask_events(valid, MASK_RUNS)))
    no_leaves = np.zeros((0, 5), np.int64)
    head = np.zeros(3 + 2 * NLV, np.int64)
    n = _put_predictors(tab, val, nb, np.int64(n), np.array([MODE_INTERP], np.int64), no_leaves, ZERO)
    n_res = np.int64(n + head.shape[0])
    if n < 0 or n_res > tab.shape[0]:
        return -1, np.inf, 0

    def put_head(cofs: int, cshift: int, sgn: int, fbw: np.ndarray) -> None:
        """The header's events (in place before a stream's bits are counted)."""
        head[:3], head[3:] = (cofs, cshift, sgn), fbw.ravel()
        _put_predictors(tab, val, nb, np.int64(n), head, no_leaves, ZERO)

    # error feedback: one weight per spacing and pass, chosen from the first pass's counts of
    # what each candidate would have coded (least squares on the first pass's errors chose
    # weights 0-4 where 8-14 code smallest: in bounded mode most errors fed back are 0, the
    # residual rounded away)
    fbw = np.zeros((NLV, 2), np.int64)
    feedback = bool(opts & lp.OPT_FEEDBACK)
    if feedback:
        fbw[:, 0], fbw[:, 1] = FB_FIRST
    signs = bool(opts & lp.OPT_SIGN)
    hist = np.zeros((NLV, 2, NCAND, HG, HB), np.int64)
    alt = np.zeros((lp.NLEVEL * lp.NI_PAT * lp.NI_CLS, NSYM), np.int32)
    chk, chk_w = np.zeros(1, np.uint64), np.zeros(1, np.uint64)
    scale = float(scale)
    n_end = interp_events(t, valid, tab, val, nb, n_res, TR, fbw, ZERO, ZERO, hist, alt, scale, chk)
    if n_end < 0:
        return -1, np.inf, 0
    bits, cofs, cshift = lv.context_choice(tab, val, nb, n_res, np.int64(n_end), TR)
    # the second pass's estimate: the weights chosen (their share of the first pass's bits
    # from the candidates' counts) in level or in sign tables, whichever the first pass's
    # counts say is smaller
    chosen, share = feedback_choice(hist) if feedback else (fbw, 1.0)
    sign_bits = sign_estimate(alt, np.int64(cofs), tab, nb, n_res, np.int64(n_end)) if signs else np.inf
    way = int(sign_bits < bits)
    if force is None and rival < np.inf:
        # the mask's and the mode's bits (events before the header) beside the residuals'
        # estimate, against the raster order's stream
        estimate = _stream_bits(tab, val, nb, np.int64(n)) + min(bits, share * min(bits, sign_bits))
        if estimate > INTERP_GIVE_UP * rival:
            return -2, np.inf, 0
    lv.apply_contexts(tab, n_res, np.int64(n_end), TR, np.int64(cofs), np.int64(cshift))
    put_head(cofs, cshift, 0, fbw)
    stream = _stream_bits(tab, val, nb, np.int64(n_end))
    if force is not None or way or not np.array_equal(chosen, fbw):
        way = way if force is None else force
        # kept where the whole stream is smaller than the first pass's (the estimates leave out
        # how the tables quantise: 45 sign tables cost more than estimated where the residuals
        # are wide, the real captures)
        keep = _save(tab, val, nb, n_res, n_end)
        n_w = interp_events(t, valid, tab, val, nb, n_res, TR, chosen, np.int64(way), np.int64(cofs), NO_HIST,
                            NO_ALT, scale, chk_w)
        if n_w < 0:
            return -1, np.inf, 0
        cofs_w, cshift_w = cofs, 0
        if way == 0:
            cofs_w, cshift_w = lv.context_choice(tab, val, nb, n_res, np.int64(n_w), TR)[1:]
            lv.apply_contexts(tab, n_res, np.int64(n_w), TR, np.int64(cofs_w), np.int64(cshift_w))
        put_head(cofs_w, cshift_w, way, chosen)
        stream_w = _stream_bits(tab, val, nb, np.int64(n_w))
        if force is not None or stream_w < stream:
            n_end, stream, chk = n_w, stream_w, chk_w
        else:
            _restore(tab, val, nb, n_res, keep)
            put_head(cofs, cshift, 0, fbw)
    return int(n_end), float(stream), int(chk[0])


def decode_band(tables: np.ndarray, words: np.ndarray, H: int, W: int, lossless: bool, scale: float,
                out: np.ndarray) -> int:
    """Decode one band (``tables`` uint8, ``words`` uint16 from :func:`encode_band`) into ``out``
    (H, W) float32 (NaN where invalid). ``scale`` is the quantum (lossless) or the fine unit
    (bounded). Returns 0, or -1 for a corrupt stream. Plain Python over the kernels (each
    releases the GIL): as a kernel it cost numba 2.7 s more to compile, relinking them all."""
    freq, used = unpack_codes(tables, np.int64(NTABLES))  # int64: one signature
    if used < 0 or used != tables.shape[0]:
        return -1
    nw = words.shape[0]
    if nw < 4:
        return -1
    sym, fb = decode_tables(freq)
    xa, xb, pos = dec_init(words)
    valid = np.zeros((H, W), np.bool_)
    mask, xa, xb, pos = get_symbol(xa, xb, pos, words, nw, sym, fb, T_PRED)
    if mask == MASK_CTX:
        ok, xa, xb, pos = decode_mask_ctx(xa, xb, pos, words, nw, valid)
    elif mask == MASK_RUNS:
        ok, xa, xb, pos = decode_mask(xa, xb, pos, words, nw, sym, fb, valid, T_EDGE)
    else:
        return -1
    if not ok:
        return -1
    mode, xa, xb, pos = get_symbol(xa, xb, pos, words, nw, sym, fb, T_PRED)
    if mode == MODE_INTERP and not lossless:
        head = np.zeros(3 + 2 * NLV, np.int64)
        for i in range(head.shape[0]):
            head[i], xa, xb, pos = get_symbol(xa, xb, pos, words, nw, sym, fb, T_PRED)
        cofs, cshift, sgn = (np.int64(v) for v in head[:3])
        if cofs > lp.MAX_COFS or cshift > 2 or sgn > 1 or head[3:].max() > FB_MAX or pos > nw:
            return -1
        xa, xb, pos = interp_decode(xa, xb, pos, words, nw, sym, fb, valid, cofs, cshift, sgn,
                                    head[3:].reshape(NLV, 2), float(scale), TR, out)
        return 0 if pos == nw and xa == RANS_L and xb == RANS_L else -1
    if mode != MODE_RASTER:
        return -1
    nleaf_max = ((H + MINB - 1) // MINB) * ((W + MINB - 1) // MINB)
    leaves = np.zeros((nleaf_max, 5), np.int64)
    lcoef = np.zeros((nleaf_max, 6), np.int64)
    head = np.zeros(HEAD_N + 2 * NLS * n_tiles(W), np.int64)
    nleaf, xa, xb, pos = _decode_tree(xa, xb, pos, words, nw, sym, fb, valid, bool(lossless), leaves, lcoef, head)
    if nleaf < 0:
        return -1
    bias, cofs, wp, aw, an, grad, sc, _ = (np.int64(v) for v in head[:N_FLAGS])
    lut = lp.activity_tables(lv.partition_tables(head[N_FLAGS:HEAD_N]))
    lsw = (head[HEAD_N::2] << 8) + head[HEAD_N + 1 :: 2] - LS_BIAS
    cells = _leaf_cells(np.int64(H), np.int64(W), leaves, np.int64(nleaf))
    xa, xb, pos = lp.decode_residuals(xa, xb, pos, words, nw, sym, fb, valid, cells, leaves, lcoef, bool(lossless), bias,
                                      aw - lp.FB_MAX, an - lp.FB_MAX, cofs, lut, wp, sc, float(scale), TR, out, lsw,
                                      bool(grad))
    # A sound stream ends exactly at its last word, both states back where the encoder began.
    if pos != nw or xa != RANS_L or xb != RANS_L:
        return -1
    return 0
