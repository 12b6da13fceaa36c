"""Hierarchical interpolation of an error-bounded range band (private kernels of
:mod:`shared.compress._quadtree`).

A band coded in *interpolation* mode (the encoder's choice per band, bounded mode only) is
coded coarse to fine, as SZ3 codes its fields: first the samples on a grid of spacing
:data:`S0` (each predicted from its grid neighbours W, N, NW), then, for each spacing ``s``
from :data:`S0` down to 2 with ``h = s / 2``, pass A the samples at (multiple of s, odd multiple
of h) from their left and right neighbours at distance h, and pass B the rows at odd multiples
of h from the rows h above and below. Every prediction is the mean of two *reconstructed*
samples on either side (or the one of them that is valid; else the sample before it in its
pass), so a smooth, detailed surface is predicted from both sides, and the reconstruction
noise of an error bound (uniform, +-E) is halved in the prediction instead of tripled as by
the plane through W, N, NW of the raster order. Depth jumps and noise favour the raster order's
quadtree; the encoder codes both ways and keeps the smaller.

Residuals are quantised as in the raster order's bounded mode (``r = (t - p + half) >> F_SHIFT``,
reconstruction ``p + r * FINE``, within half a quantum of the target ``t``). The reconstructed
error of the sample before in its pass-row (``v - p0``, before its own feedback) is fed back
into the prediction with a weight in sixteenths per spacing and pass (eight per band): an
oversampling camera's sub-pixel errors run along its rows (the simulated spot at 4:1 and fandisk
at 2:1 show horizontal streaks of several pixels in their high-passed depth), so
pass B, predicting a row from the rows above and below, wants a weight of 8-14 where pass A,
whose sample before is two columns away, wants 0-3. The encoder's first pass runs weights
:data:`FB_CAND` beside the ones it codes with (every candidate following its own feedback along
the row) and counts their symbols, and its second pass codes with the weights of fewest
estimated bits; least squares over the first pass's errors had chosen 0-4, since most errors it
sees are rounded to 0.

Residuals are coded in level tables by the activity ``|left - right|`` (or ``|above - below|``)
plus twice the error of the sample before in its pass and the error of the sample a pass-row
above, in half-octaves (:func:`shared.compress._levels.context_choice` slides and merges them),
or, where the band's first pass estimates them smaller, in sign contexts (:func:`_table`: three
groups of those levels x the signs of the residual before in the pass-row and of the two samples
it is interpolated from x three classes of pass, 45 tables).

Measured (bits per valid sample within 0.1 mm, whole 2048x1536 bench images; ``quadtree-lp-4``,
one feedback weight per band -> weights per spacing and pass -> with sign contexts): the bunny
at 2:1 0.830 -> 0.774 -> 0.742, the spot at 4:1 0.907 -> 0.771 -> 0.738, the fandisk at 2:1
0.782 -> 0.757 -> 0.715, the relief at 4:1 0.476 -> 0.430 -> 0.416 (SZ3: 0.861, 0.911, 0.801,
0.548). Tried and dropped: a finer quantum on the coarse levels (QoZ's level-wise error bound:
+1 to +13 % on the bunny, -1.3 % at best for the coarsest grid alone), cubic interpolation
(2-5 % larger: it amplifies the reconstruction's noise), per-level weights found by search
instead of estimated (-1.5 % more for 70 passes), 24 sign tables by the sign before alone
(-3.7 % against -7.3 % on the fandisk, offline).
"""

from __future__ import annotations

import numpy as np

from shared.compress._check import add_row, scratch
from shared.compress._levels import pattern_bits
from shared.compress._lpred import (
    E_LIM,
    F_SHIFT,
    FINE,
    L_RES,
    LEVEL_LUT,
    M_RES,
    NCTX,
    NI_CLS,
    NI_GRP,
    NI_PAT,
    NLEVEL,
    _level_of,
)
from shared.compress._rans import at, put_value, read_value, set_at, symbol_of, unzigzag, zigzag
from shared.core.jit import helper, kernel, zeros

#: Spacing of the coarsest grid.
S0 = 16
#: Clamp of the stored errors and residuals (int16).
I16 = 32767
#: Spacings S0, S0 / 2, ..., 2: level ``log2(s) - 1`` (3..0).
NLV = 4
#: Error feedback: the reconstructed error of the sample before in its pass weighs in
#: sixteenths, one weight per spacing and pass (a band's choice among FB_CAND).
FB_MAX = 15
FB_CAND = np.array([0, 3, 6, 9, 12, 15], np.int64)
NCAND = FB_CAND.shape[0]
#: The candidates' symbol counts (:func:`interp_events`) by activity group (level // 4) and
#: zigzagged residual u: bins 0..7 the values, bin 8 + j (j < 8) the values of about j + 3
#: bits beside their leading one (octaves; the last all larger ones), so that a noisy band's
#: large residuals weigh by their size.
HG = 6
HB = 16


@helper
def _two_sided(rec, valid, ym, xm, yp, xp, H, W):
    """Prediction from the reconstructed samples (ym, xm) and (yp, xp) (either may be outside or
    invalid): (prediction, activity, found)."""
    okm = ym >= 0 and xm >= 0 and valid[ym, xm]
    okp = yp < H and xp < W and valid[yp, xp]
    if okm and okp:
        a = rec[ym, xm]
        b = rec[yp, xp]
        return (a + b) >> 1, min(abs(a - b), E_LIM), True
    if okm:
        return rec[ym, xm], 4 * FINE, True
    if okp:
        return rec[yp, xp], 4 * FINE, True
    return 0, 8 * FINE, False


@helper
def _pass(s, k):
    """The samples of pass ``k`` at spacing ``s`` (h = s / 2) and their neighbours: (first row,
    row step, first column, column step, the two-sided offset (dy, dx), the fallback's offset
    (fy, fx)). Pass A (k 0): rows on the grid, odd multiples of h across, from left and right;
    pass B (k 1): the rows at odd multiples of h, every h across, from above and below."""
    h = s >> 1
    if k == 0:
        return 0, s, h, s, 0, h, s, 0
    return h, s, 0, h, h, 0, 0, h


@helper
def _coarse(rec, valid, y, x, last):
    """Prediction of a grid sample (y, x) of spacing S0 from its grid neighbours W, N, NW."""
    okw = x >= S0 and valid[y, x - S0]
    okn = y >= S0 and valid[y - S0, x]
    if okw and okn:
        w = rec[y, x - S0]
        n = rec[y - S0, x]
        if valid[y - S0, x - S0]:
            c = rec[y - S0, x - S0]
            return max(min(w, n), min(max(w, n), w + n - c)), min(abs(w - c) + abs(n - c), E_LIM)
        return (w + n) >> 1, min(abs(w - n), E_LIM)
    if okw:
        return rec[y, x - S0], 8 * FINE
    if okn:
        return rec[y - S0, x], 8 * FINE
    return last, 16 * FINE


@helper
def _table(t_res, act, sgn, cofs, rprev, rnb, cls):
    """(table, flip) of a residual of activity ``act``: in level mode (``sgn`` 0) the table
    ``t_res`` plus its level (made tables after the pass by
    :func:`shared.compress._levels.context_choice`), no flip; in sign mode the table of its
    group of levels from ``cofs`` (3), its pattern (5) and its class ``cls`` (3: the finest
    spacing's pass B, its pass A, the others). The pattern: the signs of the residual before in
    its pass-row ``rprev`` and of the sum ``rnb`` of the residuals of the two samples it is
    interpolated from, as the same or opposite signs where ``rprev`` is not 0, else whether
    ``rnb`` is; the residual is coded negated (flip -1) where the sign it is compared with (that
    of ``rprev``, else of ``rnb``) is negative, so each table sees the lean one way. Measured
    (offline, tables' cost included, bits of the interpolation order's residuals): -7.3 % on the
    fandisk at 2:1, -5.1 % on the bunny at 2:1 against the level tables; with the sign of
    ``rprev`` alone in 24 tables -3.7 and -2.8 %. Branch-free: the signs are coin flips."""
    lev = _level_of(act)
    pat, flip = _pattern(rprev, rnb)
    tb = t_res + (_group(lev, cofs) * NI_PAT + pat) * NI_CLS + cls
    return sgn * tb + (1 - sgn) * (t_res + lev), flip * sgn


@helper
def _group(lev, cofs):
    """The sign contexts' group (0..NI_GRP - 1) of activity level ``lev`` from offset ``cofs``."""
    return (min(max(lev - cofs, 0), NCTX - 1) * NI_GRP) >> 4


@helper
def _pattern(rprev, rnb):
    """The sign pattern (0..NI_PAT - 1) and flip (-1 or 0) of :func:`_table`."""
    sp = np.int64(rprev > 0) - np.int64(rprev < 0)
    sn = np.int64(rnb > 0) - np.int64(rnb < 0)
    nz = sp & 1  # sp != 0
    ref = sp + (1 - nz) * sn
    return nz * (1 + sp * sn) + (1 - nz) * (4 - (sn & 1)), ref >> 63


@helper
def _neighbour_residuals(rr, ym, xm, yp, xp, H, W):
    """The sum of the residuals at (ym, xm) and (yp, xp) (0 outside the band; ``rr`` is 0 where
    no residual was coded)."""
    a = np.int64(rr[ym, xm]) if ym >= 0 and xm >= 0 else 0
    b = np.int64(rr[yp, xp]) if yp < H and xp < W else 0
    return a + b


@helper
def _count_alt(alt, act, rprev, rnb, cls, r):
    """Count residual ``r``'s symbol in sign contexts (:func:`interp_events`' ``alt``)."""
    pat, flip = _pattern(rprev, rnb)
    alt[(_level_of(act) * NI_PAT + pat) * NI_CLS + cls, symbol_of(np.int64(zigzag((r ^ flip) - flip)), L_RES, M_RES)] += 1


def sign_estimate(alt: np.ndarray, cofs: int, tab: np.ndarray, nb: np.ndarray, n0: int, n1: int) -> float:
    """Estimated bits of a band's interpolation residuals (events n0..n1-1, coded in level
    tables) had they been coded in sign contexts from offset ``cofs``: from the counts ``alt``
    of :func:`interp_events` (:func:`shared.compress._levels.pattern_bits`)."""
    # the groups of :func:`_group`
    groups = (np.minimum(np.maximum(np.arange(NLEVEL, dtype=np.int64) - cofs, 0), NCTX - 1) * NI_GRP) >> 4
    first = groups * (NI_PAT * NI_CLS)
    return pattern_bits(alt, first, tab, nb, np.int64(n0), np.int64(n1), False)


@kernel
def interp_events(t, valid, tab, val, nb, n, t_res, fbw, sgn, cofs, hist, alt, scale, chk):
    """Append the residual events of a band in interpolation order (bounded mode: ``t`` (H, W)
    int64 fine-unit targets) after event ``n``, each in table ``t_res`` plus its activity level
    (:func:`shared.compress._levels.context_choice` then makes them tables), with the error
    feedback weights ``fbw`` (NLV, 2) int64 (sixteenths, by level and pass); with ``sgn`` 1, in
    the sign contexts of :func:`_table` (final tables, from offset ``cofs``). Unless ``hist`` is
    (1, 1, 1, 1, 1), adds to it (NLV, 2, NCAND, HG, HB) int64 the symbols each weight of
    :data:`FB_CAND` would have given, every candidate following its own feedback along the
    pass's row beside the weight used (the neighbours and the activity those of the weight
    used): the encoder's estimate of each weight's bits without coding the band again; and to
    ``alt`` (NLEVEL * NI_PAT * NI_CLS, NSYM) int32 the symbols the residuals would have in sign
    contexts, by level, pattern and class (:func:`sign_estimate`). Where ``chk`` (uint64) has an
    element (else empty), it receives the sum of :func:`shared.compress._check.add_row` over
    the reconstruction (``scale`` the fine unit), the band's check before it is folded.
    Returns the count (or -1 when the buffers are full)."""
    H, W = t.shape
    rec = zeros((H, W), np.int64)
    # the errors and residuals of the samples coded, int16 (clamped: a quarter of the memory
    # traffic; an error clamped at 32767 still puts its activity at the top level, and the
    # decoder clamps alike)
    err = zeros((H, W), np.int16)
    rr = zeros((H, W), np.int16)
    half = FINE >> 1
    last = 0
    count = hist.shape[0] > 1
    for y in range(0, H, S0):
        eprev = 0
        rprev = 0
        for x in range(0, W, S0):
            if not valid[y, x]:
                continue
            p, act = _coarse(rec, valid, y, x, last)
            r = (t[y, x] - p + half) >> F_SHIFT
            v = p + (r << F_SHIFT)
            tb, flip = _table(t_res, act + 2 * eprev, sgn, cofs, rprev, 0, 2)
            n = put_value(tab, val, nb, n, tb, zigzag((r ^ flip) - flip), L_RES, M_RES)
            if count:
                _count_alt(alt, act + 2 * eprev, rprev, 0, 2, r)
            rec[y, x] = v
            last = v
            eprev = min(abs(v - p), E_LIM)
            rprev = r
            rr[y, x] = min(max(r, -I16), I16)
    sc = zeros(NCAND, np.int64)  # each candidate weight's own feedback along the row
    s = S0
    lv = NLV - 1
    while s > 1:
        for k in range(2):
            w = fbw[lv, k]
            cls = 2 if lv > 0 else 1 - k  # the finest spacing's pass B, its pass A, the others
            ry, rs, cx, cs, dy, dx, fy, fx = _pass(s, k)
            for y in range(ry, H, rs):
                eprev = 0
                sprev = 0
                rprev = 0
                for c in range(NCAND):  # a loop: a slice assignment links numba's error formatting
                    sc[c] = 0
                for x in range(cx, W, cs):
                    if not valid[y, x]:
                        continue
                    p, act, ok = _two_sided(rec, valid, y - dy, x - dx, y + dy, x + dx, H, W)
                    if not ok:
                        p, act, ok = _two_sided(rec, valid, y - fy, x - fx, H, W, H, W)
                        if not ok:
                            p = last
                    act += 2 * eprev + (np.int64(err[y - s, x]) if y >= s else 0)
                    p0 = p
                    p += (w * sprev) >> 4
                    r = (t[y, x] - p + half) >> F_SHIFT
                    v = p + (r << F_SHIFT)
                    if count:
                        g = min(_level_of(act) >> 2, HG - 1)
                        for c in range(NCAND):
                            pc = p0 + ((FB_CAND[c] * sc[c]) >> 4)
                            rc = (t[y, x] - pc + half) >> F_SHIFT
                            sc[c] = min(max(pc + (rc << F_SHIFT) - p0, -E_LIM), E_LIM)
                            u = np.int64(zigzag(rc))
                            hb = u if u < 8 else 8 + min((np.int64(at(LEVEL_LUT, min(u, 4095))) - 6) >> 1, 7)
                            hist[lv, k, c, g, hb] += 1
                    rnb = _neighbour_residuals(rr, y - dy, x - dx, y + dy, x + dx, H, W)
                    tb, flip = _table(t_res, act, sgn, cofs, rprev, rnb, cls)
                    n = put_value(tab, val, nb, n, tb, zigzag((r ^ flip) - flip), L_RES, M_RES)
                    if count:
                        _count_alt(alt, act, rprev, rnb, cls, r)
                    rec[y, x] = v
                    last = v
                    eprev = min(abs(v - p), E_LIM)
                    sprev = min(max(v - p0, -E_LIM), E_LIM)
                    err[y, x] = min(eprev, I16)
                    rprev = r
                    rr[y, x] = min(max(r, -I16), I16)
        s >>= 1
        lv -= 1
    if chk.shape[0] > 0:
        f32, u32 = scratch(W)
        h = np.uint64(0)
        for y in range(H):
            h = add_row(h, rec[y], 0, 0, valid[y], y, W, scale, f32, u32)
        chk[0] = h
    return n


@helper
def _get(xa, xb, pos, words, nw, sym, fb, t_res, act, cofs, cshift, sgn, rprev, rnb, cls):
    """A residual coded by :func:`_table` (level mode: levels merged by ``cshift``)."""
    tb, flip = _table(t_res, act, sgn, cofs, rprev, rnb, cls)
    lt = t_res + (min(max(tb - t_res - cofs, 0), NCTX - 1) >> cshift)  # level mode's table
    u, xa, xb, pos = read_value(xa, xb, pos, words, nw, sym, fb, sgn * tb + (1 - sgn) * lt, L_RES, M_RES)
    r = unzigzag(u)
    return (r ^ flip) - flip, xa, xb, pos


@kernel
def interp_decode(xa, xb, pos, words, nw, sym, fb, valid, cofs, cshift, sgn, fbw, scale, t_res, out):
    """Inverse of :func:`interp_events` (feedback weights ``fbw`` (NLV, 2) int64, sign contexts
    ``sgn``; in level mode the tables merged by ``cshift``) into ``out``
    (H, W) float32 (depth ``rec * scale``, NaN where invalid); returns (xa, xb, pos)."""
    H, W = valid.shape
    rec = zeros((H, W), np.int64)
    err = zeros((H, W), np.int16)
    rr = zeros((H, W), np.int16)
    last = 0
    nan = np.float32(np.nan)
    for y in range(H):
        for x in range(W):
            if not valid[y, x]:
                set_at(out[y], x, nan)
    for y in range(0, H, S0):
        eprev = 0
        rprev = 0
        for x in range(0, W, S0):
            if not valid[y, x]:
                continue
            p, act = _coarse(rec, valid, y, x, last)
            r, xa, xb, pos = _get(xa, xb, pos, words, nw, sym, fb, t_res, act + 2 * eprev, cofs, cshift, sgn, rprev, 0, 2)
            v = p + (r << F_SHIFT)
            rec[y, x] = v
            out[y, x] = np.float32(v * scale)
            last = v
            eprev = min(abs(v - p), E_LIM)
            rprev = r
            rr[y, x] = min(max(r, -I16), I16)
    # The prediction below is written out as in interp_events, not shared through an inlined
    # helper: with the helper this decoder ran 1.5 times slower (measured, relief 2:1 band).
    s = S0
    lv = NLV - 1
    while s > 1:
        for k in range(2):
            w = fbw[lv, k]
            cls = 2 if lv > 0 else 1 - k
            ry, rs, cx, cs, dy, dx, fy, fx = _pass(s, k)
            for y in range(ry, H, rs):
                eprev = 0
                sprev = 0
                rprev = 0
                orow = out[y]
                for x in range(cx, W, cs):
                    if not valid[y, x]:
                        continue
                    p, act, ok = _two_sided(rec, valid, y - dy, x - dx, y + dy, x + dx, H, W)
                    if not ok:
                        p, act, ok = _two_sided(rec, valid, y - fy, x - fx, H, W, H, W)
                        if not ok:
                            p = last
                    act += 2 * eprev + (np.int64(err[y - s, x]) if y >= s else 0)
                    p0 = p
                    p += (w * sprev) >> 4
                    rnb = _neighbour_residuals(rr, y - dy, x - dx, y + dy, x + dx, H, W)
                    r, xa, xb, pos = _get(xa, xb, pos, words, nw, sym, fb, t_res, act, cofs, cshift, sgn, rprev, rnb,
                                          cls)
                    v = p + (r << F_SHIFT)
                    rec[y, x] = v
                    set_at(orow, x, np.float32(v * scale))
                    last = v
                    eprev = min(abs(v - p), E_LIM)
                    sprev = min(max(v - p0, -E_LIM), E_LIM)
                    err[y, x] = min(eprev, I16)
                    rprev = r
                    rr[y, x] = min(max(r, -I16), I16)
        s >>= 1
        lv -= 1
    return xa, xb, pos
