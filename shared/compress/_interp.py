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
reconstruction ``p + r * FINE``, within half a quantum of the target ``t``). The error of the
sample before in its pass (before its own feedback) is fed back into the prediction with a
weight per band in sixteenths (the encoder's choice of none, the least-squares weight and a
quarter, by bits): an oversampling camera's sub-pixel errors are correlated over neighbouring
samples. Residuals are coded in the band's residual tables by the activity ``|left - right|``
(or ``|above - below|``) plus twice the error of the sample before in its pass and the error of
the sample a row of its pass above, in half-octaves
(:func:`shared.compress._lpred.context_choice` slides and merges them).

Measured (bits per valid sample within 0.1 mm, whole 2048x1536 bench images; raster order
alone -> interpolation -> with the error feedback): the simulated relief at 1:1 0.600 -> 0.420
-> 0.402, 2:1 0.573 -> 0.438 -> 0.404, 4:1 0.603 -> 0.572 -> 0.476, the bunny at 2:1 0.977 ->
0.871 -> 0.830 (SZ3: 0.524, 0.512, 0.548, 0.861), the Cyberware dragon scan 2.47 -> 1.99; white
noise keeps the raster order. Cubic interpolation (-1, 9, 9, -1) / 16 where the samples beyond
were valid cost 2-5 % more on each of these (it amplifies the reconstruction's noise), and was
dropped.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from shared.compress._lpred import E_LIM, F_SHIFT, FINE, L_RES, NCTX, _level_of
from shared.compress._rans import get_value, put_value, set_at, unzigzag, zigzag

#: Spacing of the coarsest grid.
S0 = 16
#: Error feedback: the error of the sample before in its pass (before its own feedback) weighs
#: in sixteenths, per band (the least-squares weight over the band, FB_MIN..FB_MAX).
FB_MIN = -8
FB_MAX = 15


@njit(cache=True, nogil=True, inline="always")
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


@njit(cache=True, nogil=True, inline="always")
def _pass(s, k):
    """The samples of pass ``k`` at spacing ``s`` (h = s / 2) and their neighbours: (first row,
    row step, first column, column step, the two-sided offset (dy, dx), the fallback's offset
    (fy, fx)). Pass A (k 0): rows on the grid, odd multiples of h across, from left and right;
    pass B (k 1): the rows at odd multiples of h, every h across, from above and below."""
    h = s >> 1
    if k == 0:
        return 0, s, h, s, 0, h, s, 0
    return h, s, 0, h, h, 0, 0, h


@njit(cache=True, nogil=True, inline="always")
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


@njit(cache=True, nogil=True)
def interp_events(t, valid, tab, val, nb, n, t_res, fbw, st):
    """Append the residual events of a band in interpolation order (bounded mode: ``t`` (H, W)
    int64 fine-unit targets) after event ``n``, each in table ``t_res`` plus its activity level
    (:func:`shared.compress._lpred.context_choice` then makes them tables), with error feedback
    weight ``fbw`` (sixteenths); without it (``fbw`` 0), adds to ``st`` (2,) float64 the sums of the products of each
    error (before feedback) and the one before in its pass, and of the squares of the latter
    (the least-squares weight is ``st[0] / st[1]``). Returns the count (or -1 when the buffers
    are full)."""
    H, W = t.shape
    rec = np.zeros((H, W), np.int64)
    err = np.zeros((H, W), np.int64)
    half = FINE >> 1
    last = 0
    for y in range(0, H, S0):
        eprev = 0
        for x in range(0, W, S0):
            if not valid[y, x]:
                continue
            p, act = _coarse(rec, valid, y, x, last)
            r = (t[y, x] - p + half) >> F_SHIFT
            v = p + (r << F_SHIFT)
            n = put_value(tab, val, nb, n, t_res + _level_of(act + 2 * eprev), zigzag(r), L_RES)
            rec[y, x] = v
            last = v
            eprev = min(abs(v - p), E_LIM)
    s = S0
    while s > 1:
        for k in range(2):
            ry, rs, cx, cs, dy, dx, fy, fx = _pass(s, k)
            for y in range(ry, H, rs):
                eprev = 0
                sprev = 0
                for x in range(cx, W, cs):
                    if not valid[y, x]:
                        continue
                    p, act, ok = _two_sided(rec, valid, y - dy, x - dx, y + dy, x + dx, H, W)
                    if not ok:
                        p, act, ok = _two_sided(rec, valid, y - fy, x - fx, H, W, H, W)
                        if not ok:
                            p = last
                    act += 2 * eprev + (err[y - s, x] if y >= s else 0)
                    p0 = p
                    p += (fbw * sprev) >> 4
                    r = (t[y, x] - p + half) >> F_SHIFT
                    v = p + (r << F_SHIFT)
                    if fbw == 0:  # the statistics of the least-squares weight (a first pass)
                        e0 = min(max(t[y, x] - p0, -E_LIM), E_LIM)
                        st[0] += float(sprev) * float(e0)
                        st[1] += float(sprev) * float(sprev)
                    n = put_value(tab, val, nb, n, t_res + _level_of(act), zigzag(r), L_RES)
                    rec[y, x] = v
                    last = v
                    eprev = min(abs(v - p), E_LIM)
                    sprev = min(max(v - p0, -E_LIM), E_LIM)
                    err[y, x] = eprev
        s >>= 1
    return n


@njit(cache=True, nogil=True, inline="always")
def _get(xa, xb, pos, words, nw, sym, fb, t_res, act, cofs, cshift):
    ctx = min(max(_level_of(act) - cofs, 0), NCTX - 1)
    u, xa, xb, pos = get_value(xa, xb, pos, words, nw, sym, fb, t_res + (ctx >> cshift), L_RES)
    return unzigzag(u), xa, xb, pos


@njit(cache=True, nogil=True)
def interp_decode(xa, xb, pos, words, nw, sym, fb, valid, cofs, cshift, fbw, scale, t_res, out):
    """Inverse of :func:`interp_events` (feedback weight ``fbw``) into ``out`` (H, W) float32 (depth ``rec * scale``, NaN
    where invalid); returns (xa, xb, pos)."""
    H, W = valid.shape
    rec = np.zeros((H, W), np.int64)
    err = np.zeros((H, W), np.int64)
    last = 0
    nan = np.float32(np.nan)
    for y in range(H):
        for x in range(W):
            if not valid[y, x]:
                set_at(out[y], x, nan)
    for y in range(0, H, S0):
        eprev = 0
        for x in range(0, W, S0):
            if not valid[y, x]:
                continue
            p, act = _coarse(rec, valid, y, x, last)
            r, xa, xb, pos = _get(xa, xb, pos, words, nw, sym, fb, t_res, act + 2 * eprev, cofs, cshift)
            v = p + (r << F_SHIFT)
            rec[y, x] = v
            out[y, x] = np.float32(v * scale)
            last = v
            eprev = min(abs(v - p), E_LIM)
    # The prediction below is written out as in interp_events, not shared through an inlined
    # helper: with the helper this decoder ran 1.5 times slower (measured, relief 2:1 band).
    s = S0
    while s > 1:
        for k in range(2):
            ry, rs, cx, cs, dy, dx, fy, fx = _pass(s, k)
            for y in range(ry, H, rs):
                eprev = 0
                sprev = 0
                orow = out[y]
                for x in range(cx, W, cs):
                    if not valid[y, x]:
                        continue
                    p, act, ok = _two_sided(rec, valid, y - dy, x - dx, y + dy, x + dx, H, W)
                    if not ok:
                        p, act, ok = _two_sided(rec, valid, y - fy, x - fx, H, W, H, W)
                        if not ok:
                            p = last
                    act += 2 * eprev + (err[y - s, x] if y >= s else 0)
                    p0 = p
                    p += (fbw * sprev) >> 4
                    r, xa, xb, pos = _get(xa, xb, pos, words, nw, sym, fb, t_res, act, cofs, cshift)
                    v = p + (r << F_SHIFT)
                    rec[y, x] = v
                    set_at(orow, x, np.float32(v * scale))
                    last = v
                    eprev = min(abs(v - p), E_LIM)
                    sprev = min(max(v - p0, -E_LIM), E_LIM)
                    err[y, x] = eprev
        s >>= 1
    return xa, xb, pos
