"""The Gray-code decoder's numba kernels (:mod:`shared.scan.decode` drives them).

Bit planes classified in narrow integers, codes resolved level by level over a whole row, and
sub-pixel stripe edges placed; see :mod:`shared.scan.decode` for the method and the memory plan.
"""

from __future__ import annotations

import numba
import numpy as np

from shared.core.bits import popcount
from shared.core.jit import empty, helper, kernel, zeros
from shared.scan._bands import next_item, prefetch
from shared.scan._i32 import (
    LANES,
    add32,
    and32,
    compress_index,
    eq32,
    ge32,
    gt32,
    le32,
    lt32,
    ne32,
    shl32,
    shr32,
    sub32,
    xor32,
)


@kernel(error_model="numpy")
def _bit_planes(pats, refs, bits, thr, kq, signs, weak, q, store_q, m1, m2, counter):  # pragma: no cover
    """Classify a batch (tuple) of k flat bit planes: sign of ``pats[j] - refs[j]`` into ``signs``, and
    ``|pats[j] - refs[j]| < thr`` into ``weak``, at bit ``bits[j]``.

    ``refs`` holds inverse images or the white/black midpoint; with ``store_q`` the differences
    scaled by ``kq`` (127 / full swing) go to ``q[j]`` (int8), and ``m1``/``m2`` keep the smallest
    and second-smallest ``|q|`` seen so far (the confidence). One launch per batch, the bits of a
    batch: launches, not arithmetic, dominate on a busy machine. One thread's share
    (:func:`shared.scan._bands.run_bands`): chunks of pixels taken from ``counter``.
    """
    k = bits.size  # planes in this batch; the tuples are padded to _MAX_BATCH (one signature)
    n = pats[0].size
    chunk = 1 << 15
    zero = np.uint16(0)
    n_chunks = (n + chunk - 1) // chunk
    while True:
        c = next_item(counter)
        if c >= n_chunks:
            break
        lo = c * chunk
        hi = min(n, lo + chunk)
        sg = signs[lo:hi]
        wk = weak[lo:hi]
        t = thr[lo:hi]
        kk = kq[lo:hi]
        a1 = m1[lo:hi]
        a2 = m2[lo:hi]
        # Bit plane outer, pixel inner over slices indexed from 0: these loops vectorise.
        for j in range(k):
            one = np.uint16(1) << bits[j]
            p = pats[j][lo:hi]
            r = refs[j][lo:hi]
            for i in range(hi - lo):
                d = np.float32(p[i]) - np.float32(r[i])
                sg[i] |= one if d > 0 else zero
                wk[i] |= one if abs(d) < t[i] else zero
            if store_q:
                qq = q[j, lo:hi]
                for i in range(hi - lo):
                    d = np.float32(p[i]) - np.float32(r[i])
                    v = min(max(d * kk[i], np.float32(-127.0)), np.float32(127.0))
                    v += np.float32(0.5) if v >= 0 else np.float32(-0.5)
                    qi = np.int8(v)
                    qq[i] = qi
                    aq = np.uint8(abs(np.int16(qi)))
                    b1 = a1[i]
                    a2[i] = min(a2[i], max(b1, aq))
                    a1[i] = min(b1, aq)


@numba.njit(inline="always", error_model="numpy")
def _gray_to_binary(g):  # pragma: no cover
    # Prefix XOR from the top bit down (codes have at most 16 bits).
    g ^= g >> 1
    g ^= g >> 2
    g ^= g >> 4
    g ^= g >> 8
    return g


@numba.njit(inline="always", error_model="numpy")
def _quantise(d, kq):  # pragma: no cover
    """A pattern difference ``d`` scaled by ``kq`` (127 / full swing), rounded half away from zero
    into [-127, 127]: the int8 ``q`` of the streaming path, computed only where it is needed."""
    v = min(max(np.float32(d) * kq, np.float32(-127.0)), np.float32(127.0))
    v += np.float32(0.5) if v >= 0 else np.float32(-0.5)
    return np.int32(v)


@numba.njit(cache=True, error_model="numpy")
def _resolve_row(sg, wk, lit, full, lowest, max_level, n_proj, blk, lvl, val, sel, hist):  # pragma: no cover
    """Resolve one camera row of codes: ``blk`` (int32 code block, -1 invalid), ``lvl`` (int8 level,
    -1 invalid), ``val`` (float32 centre of the code's span, NaN invalid); the decoded pixels per
    level are added to ``hist``. ``sel`` is (W,) int32 scratch.

    A Gray code changes one bit between neighbouring columns, so a single weak bit whose finer
    bits read the pattern of that bit's stripe edge (bit k-1 on, the rest off: ``g & (w - 1) ==
    w >> 1``) means the pixel lies on that edge: either value gives an adjacent column. Level L
    (the finest L bits dropped) is acceptable when the weak bits at or above L are none or such
    an edge bit above L; at the finest captured level the finest bit itself may be weak too (it
    is weak on every one of its own edges, half of all stripe edges, and nowhere errs by more
    than one column: kept so that the sub-pixel step sees these edges). The finest acceptable
    level wins. Each level is tried on the whole row in a loop without branches, so that it
    vectorises: a real capture has a weak bit in up to half of its pixels.
    """
    W = sg.size
    top = np.float32(n_proj - 1)
    nan = np.float32(np.nan)
    low_bit = np.int32(1 << lowest)
    if max_level - lowest <= 3:
        # Every level (up to three coarser ones), the code and the level counts in one loop:
        # each pixel's bits are loaded once and nothing goes through memory between the steps
        # (four passes over the row, and four more to count the levels, took twice as long).
        n_more = max_level - lowest
        u1, u2, u3 = n_more >= 1, n_more >= 2, n_more >= 3
        f = np.int32(full)
        hi1 = f & ~np.int32((1 << (lowest + 1)) - 1)
        hi2 = f & ~np.int32((1 << (lowest + 2)) - 1)
        hi3 = f & ~np.int32((1 << (lowest + 3)) - 1)
        bt1 = np.int32(1 << (lowest + 1))
        bt2 = np.int32(1 << (lowest + 2))
        bt3 = np.int32(1 << (lowest + 3))
        L0 = np.int32(lowest)
        L1 = np.int32(lowest + 1)
        L2 = np.int32(lowest + 2)
        L3 = np.int32(lowest + 3)
        np_32 = np.int32(min(n_proj, 1 << 30))
        one = np.int32(1)
        zero = np.int32(0)
        neg = np.int32(-1)
        n0 = zero
        n1 = zero
        n2 = zero
        n3 = zero
        # In int32 throughout (see _i32: numba's int64 kept this loop at 8 pixels a vector);
        # exact, codes have at most 16 bits.
        for x in range(W):
            w = np.int32(wk[x])
            g = np.int32(sg[x])
            lx = lit[x]
            wf = and32(w, f)
            wf1 = sub32(wf, one)
            ok = eq32(and32(wf, wf1), zero) & (le32(wf, low_bit) | eq32(and32(g, wf1), shr32(wf, one)))
            s = L0 if ok else neg
            wm = and32(w, hi1)
            wm1 = sub32(wm, one)
            ok = eq32(and32(wm, wm1), zero) & (eq32(wm, zero) | (ne32(wm, bt1) & eq32(and32(and32(g, wm1), hi1), shr32(wm, one))))
            s = L1 if lt32(s, zero) & ok & u1 else s
            wm = and32(w, hi2)
            wm1 = sub32(wm, one)
            ok = eq32(and32(wm, wm1), zero) & (eq32(wm, zero) | (ne32(wm, bt2) & eq32(and32(and32(g, wm1), hi2), shr32(wm, one))))
            s = L2 if lt32(s, zero) & ok & u2 else s
            wm = and32(w, hi3)
            wm1 = sub32(wm, one)
            ok = eq32(and32(wm, wm1), zero) & (eq32(wm, zero) | (ne32(wm, bt3) & eq32(and32(and32(g, wm1), hi3), shr32(wm, one))))
            s = L3 if lt32(s, zero) & ok & u3 else s
            L = s if gt32(s, zero) else zero
            # Gray to binary commutes with dropping the finest bits: convert, then shift.
            gb = and32(g, f)
            gb = xor32(gb, shr32(gb, np.int32(1)))
            gb = xor32(gb, shr32(gb, np.int32(2)))
            gb = xor32(gb, shr32(gb, np.int32(4)))
            gb = xor32(gb, shr32(gb, np.int32(8)))
            b = shr32(gb, L)
            bl = shl32(b, L)
            good = lx & ge32(s, zero) & lt32(bl, np_32)
            blk[x] = b if good else neg
            lvl[x] = L if good else neg
            c = np.float32(bl) + np.float32(sub32(shl32(one, L), one)) * np.float32(0.5)
            val[x] = min(c, top) if good else nan
            n0 = add32(n0, np.int32(good & eq32(L, L0)))
            n1 = add32(n1, np.int32(good & eq32(L, L1)))
            n2 = add32(n2, np.int32(good & eq32(L, L2)))
            n3 = add32(n3, np.int32(good & eq32(L, L3)))
        hist[0] += n0
        if u1:
            hist[1] += n1
        if u2:
            hist[2] += n2
        if u3:
            hist[3] += n3
        return
    for x in range(W):
        w = np.int32(wk[x]) & full
        ok = ((w & (w - 1)) == 0) & ((w <= low_bit) | ((np.int32(sg[x]) & (w - 1)) == (w >> 1)))
        sel[x] = lowest if ok else -1
    for L in range(lowest + 1, max_level + 1):
        hi = np.int32(full & ~((1 << L) - 1))
        bit = np.int32(1 << L)
        for x in range(W):
            wm = np.int32(wk[x]) & hi
            ok = ((wm & (wm - 1)) == 0) & ((wm == 0) | ((wm != bit) & ((np.int32(sg[x]) & (wm - 1) & hi) == (wm >> 1))))
            s = sel[x]
            sel[x] = L if (s < 0) & ok else s
    for x in range(W):
        L = max(sel[x], np.int32(0))
        b = _gray_to_binary((np.int32(sg[x]) & full) >> L)
        good = lit[x] & (sel[x] >= 0) & ((b << L) < n_proj)
        blk[x] = b if good else -1
        lvl[x] = L if good else -1
        c = np.float32(b << L) + np.float32(((1 << L) - 1) * 0.5)
        val[x] = min(c, top) if good else nan
    for L in range(lowest, max_level + 1):
        n = 0
        for x in range(W):
            n += lvl[x] == L
        hist[L - lowest] += n


@numba.njit(cache=True, error_model="numpy")
def _edge_differences(sg, q, nbits, qa, qb):  # pragma: no cover
    """For each pair of neighbouring pixels (x, x + 1) of a camera row, the pattern differences of
    the bit plane whose sign flips between them: ``qa[x] = q[j, x]``, ``qb[x] = q[j, x + 1]``.

    sg: (W,) uint16 sign bits; q: (planes, W) differences of bits nbits-1, nbits-2, ... (the
    finest may be missing); qa, qb: (W,) of q's dtype. Across a stripe edge exactly one bit
    flips (neighbouring Gray codes), so the pair's plane follows from the flipped bits alone:
    bit p is ``popcount(flips - 1)`` when only p flips. Elsewhere (no bit or several flip) the
    values come from some plane, clamped into q; the sub-pixel step does not read them.
    One pass over the row, two loads a pair: a pass per plane with a select ran 10 times over
    the row and did not vectorise for AVX2 (13 of the 46 ms of CPU of the bench decode there).
    """
    W = sg.size
    top = nbits - 1
    last = q.shape[0] - 1
    for x in range(W - 1):
        p = popcount(np.int64(sg[x] ^ sg[x + 1]) - 1)
        # Indices as unsigned (never negative once clamped): numba adds no wraparound.
        j = np.uint64(min(max(top - p, 0), last))
        qa[x] = q[j, np.uint64(x)]
        qb[x] = q[j, np.uint64(x + 1)]


@numba.njit(inline="always")
def _edge_pick(dd, qa, qb):  # pragma: no cover
    """One bit plane's share of :func:`_edge_differences`, run right after the plane is
    classified: where the plane's sign flips between pixels x and x + 1 (``dd`` (W,), its
    differences, positive where the bit is set), ``qa[x] = dd[x]`` and ``qb[x] = dd[x + 1]``;
    other pairs keep what they hold. Across a stripe edge exactly one plane flips, so after
    every plane the edges hold that plane's differences, as :func:`_edge_differences` gives
    them; elsewhere the values are never read. ``dd`` is still in L1 and all three arrays share
    one narrow dtype, so the loop vectorises on AVX2 and AVX-512 alike, where the gather of
    :func:`_edge_differences` stays scalar (one pair at a time over the whole row)."""
    for x in range(dd.size - 1):
        # Loads before the choice: a load inside a conditional expression becomes a branch.
        a, b, oa, ob = dd[x], dd[x + 1], qa[x], qb[x]
        flip = (a > 0) != (b > 0)
        qa[x] = a if flip else oa
        qb[x] = b if flip else ob


#: Pairs searched each side of a pixel for its stripe's edges by the sub-pixel step's pass
#: without branches (more cost every pixel; fewer leave pixels to the general pass).
_NEAR = 3
#: A row's pass without branches runs only when its stripes are at most this many pixels wide
#: on average (pixels decoded at the finest level per edge); wider ones go to pass 3 whole.
_DENSE = 2.5


@numba.njit(cache=True, error_model="numpy")
def _subpixel_row(blk, lvl, qa, qb, kq, quantise, lowest, eidx, mk, blocks, frac, ep, ek, slow, out):  # pragma: no cover
    """Interpolate projector columns between stripe edges along one camera row.

    blk, lvl: (W,) code block and level; qa, qb: (W,) the differences of the flipping bit plane
    at each pair's two pixels (:func:`_edge_differences`), already scaled to int8 (streaming) or
    raw, then scaled by ``kq`` (W,) float32 here (``quantise``); eidx, mk: (W,) int32 (the
    row's edges, its marked pixels), blocks: (2, W // LANES + 1) int64 (edge masks and counts
    by block), frac: (W,) float64, ep: (W + 2 _NEAR,) float64, ek: (W + 2 _NEAR,) int32 and slow:
    (W,) bool scratch; out: (W,) float32 holding the integer decode, overwritten where
    interpolated. Returns the number of interpolated pixels. Divisions follow numpy's error
    model: two edges at one position give an infinite slope, clamped to the stripe, or NaN,
    left uninterpolated (Python's model raised ZeroDivisionError there).

    A pixel takes the column between the edges either side of it (the nearest edge at or left
    of it and the next one) when both bound its stripe; otherwise one edge and the slope of the
    neighbouring stripe. Most pixels lie within a few pairs of both edges: a pass without
    branches (it vectorises) finds them among the ``_NEAR`` pairs each side and interpolates.
    The other pixels (edges farther away, or a stripe bounded on one side only), and every
    pixel of a row whose stripes are wider than ``_DENSE`` pixels on average, are marked and
    decoded as before: the row's edges and marked pixels compacted (eidx, mk), each marked
    pixel's edge count from the blocks' counts, then the three cases in order. Either way the
    same arithmetic on the same values.
    """
    W = blk.size
    step = 1 << lowest
    # Column values from int32 through float64 (exact: they stay below 2**31): the vector
    # loops below then convert with AVX2's int32 instructions; an int64 conversion has none
    # before AVX-512 and was done lane by lane.
    fstep = np.float64(step)
    K = _NEAR
    nan = np.nan
    # Pass 1: per pair, the edge fraction (frac, -1 for no edge), position (ep, NaN for no
    # edge) and the lower of its two code blocks (ek, -2 for no edge: never a pixel's block
    # or the one below it), at index pair + K of ep/ek, whose first K and last K + 1 entries
    # are NaN and -2. An edge's projector column (its value) is (ek + 1) step - 0.5: the passes
    # below compare blocks in int32 lanes and compute the value only where they use it.
    nek = np.int32(-2)
    for i in range(K):
        ep[i] = nan
        ek[i] = nek
    # The last pixel's own (absent) pair and the K after it: pass 2 reads up to ep[W - 1 + 2 K]
    # there. (Only K were written: the buffer's last entry, left over from earlier use, could
    # make up an edge beyond the row for the last pixel, whose decode then depended on memory
    # contents: 88 pixels of a real capture's last column with lit_threshold 40.)
    for i in range(K + 1):
        ep[W - 1 + K + i] = nan
        ek[W - 1 + K + i] = nek
    n_edges = 0
    n_here = 0  # pixels of pairs 0..W-2 decoded at the finest level
    for x in range(W - 1):
        a = np.int32(blk[x])
        b = np.int32(blk[x + 1])
        edge = (a >= 0) & (b >= 0) & (lvl[x] == lowest) & (lvl[x + 1] == lowest) & (abs(a - b) == 1)
        da, db, ka, kb = qa[x], qb[x], kq[x], kq[x + 1]
        fa = np.float64(_quantise(da, ka)) if quantise else np.float64(da)
        fb = np.float64(_quantise(db, kb)) if quantise else np.float64(db)
        den = fa - fb
        t = min(max(fa / den if den != 0.0 else 0.5, 0.0), 1.0)
        frac[x] = t if edge else -1.0
        ep[x + K] = np.float64(np.int32(x)) + t if edge else nan
        ek[x + K] = min(a, b) if edge else nek
        n_edges += edge
        n_here += (a >= 0) & (lvl[x] == lowest)
    frac[W - 1] = -1.0
    n_sub = 0
    n_slow = 0
    if n_here > _DENSE * n_edges:
        # Stripes wider than _DENSE pixels on average: many pixels lie farther than K pairs from
        # an edge, and the pass below would only add its cost to theirs. All go to pass 3.
        for x in range(W):
            s = (blk[x] >= 0) & (lvl[x] == lowest)
            slow[x] = s
            n_slow += s
    # Pass 2: the nearest edge each side within K pairs. An edge at fraction 0 lies on pixel x
    # and counts as left of it. Loads come before every choice (a load inside a conditional
    # expression becomes a branch and keeps the loop scalar).
    # The two edges bound the pixel's stripe (block Bi) when each lies between Bi - 1 and Bi
    # (value lo) or between Bi and Bi + 1 (value hi), and they differ: their blocks tell, in
    # int32 lanes (a missing edge's -2 matches neither for a decoded pixel), and the values
    # are then lo and hi themselves (equal as doubles: the same integers times step).
    one = np.int32(1)
    zero = np.int32(0)
    for x in range(W if n_slow == 0 else 0):
        Bi = np.int32(blk[x])
        B = np.float64(Bi)
        c = x + K
        lo = B * fstep - 0.5
        hi = (B + 1.0) * fstep - 0.5
        t0 = frac[x]
        p0, pm1, pm2, pm3 = ep[c], ep[c - 1], ep[c - 2], ep[c - 3]
        pp1, pp2, pp3 = ep[c + 1], ep[c + 2], ep[c + 3]
        k0, km1, km2, km3 = ek[c], ek[c - 1], ek[c - 2], ek[c - 3]
        kp1, kp2, kp3 = ek[c + 1], ek[c + 2], ek[c + 3]
        o = out[x]
        at0 = t0 == 0.0
        r0 = t0 > 0.0
        e1 = ge32(km1, zero)
        e2 = ge32(km2, zero)
        f1 = ge32(kp1, zero)
        f2 = ge32(kp2, zero)
        pl = p0 if at0 else (pm1 if e1 else (pm2 if e2 else pm3))
        kl = k0 if at0 else (km1 if e1 else (km2 if e2 else km3))
        pr = p0 if r0 else (pp1 if f1 else (pp2 if f2 else pp3))
        kr = k0 if r0 else (kp1 if f1 else (kp2 if f2 else kp3))
        Bm = sub32(Bi, one)
        c1 = (eq32(kl, Bm) | eq32(kl, Bi)) & (eq32(kr, Bm) | eq32(kr, Bi)) & ne32(kl, kr)
        vl = hi if eq32(kl, Bi) else lo
        vr = hi if eq32(kr, Bi) else lo
        v = vl + (np.float64(np.int32(x)) - pl) * (vr - vl) / (pr - pl)
        want = ge32(Bi, zero) & (lvl[x] == lowest)
        ok = want & c1 & (v == v)
        v = min(max(v, lo), hi)
        out[x] = np.float32(v) if ok else o
        n_sub += ok
        s = want & ~c1
        slow[x] = s
        n_slow += s
    if n_slow == 0:
        return n_sub
    # Pass 3, for the marked pixels: the row's edges in order, as their pairs' indices in eidx
    # (their positions and blocks are read from ep/ek through them), and the marked pixels in
    # order in mk, both compacted LANES pairs at a time (compress_index: the scalar loop that
    # did this over every pair of the row cost more than the rest of the pass). A marked
    # pixel's count of edges at or left of it (earlier pairs, and its own pair at fraction 0)
    # comes from its block's count before it (eb) and the edge mask of the block (em).
    em = blocks[0]
    eb = blocks[1]
    nb = W // LANES
    ne = 0
    ns = 0
    for bi in range(nb):
        m = compress_index(frac, bi * LANES, eidx, ne)
        em[bi] = m
        eb[bi] = ne
        ne += popcount(m)
        ns += popcount(compress_index(slow, bi * LANES, mk, ns))
    # The last W % LANES pixels one at a time (frac[W - 1] is -1: no pair, no edge); a pair
    # that is not an edge is overwritten by the next edge or lies at index ne, never read.
    eb[nb] = ne
    tail = np.int64(0)
    for x in range(nb * LANES, W):
        edge = frac[x] >= 0.0
        eidx[ne] = x
        tail |= np.int64(edge) << (x - nb * LANES)
        ne += edge
        mk[ns] = x
        ns += slow[x]
    em[nb] = tail
    eidx[ne] = 0  # read (not used) when j == ne: any pair, but one of this row
    # Without branches: the three cases computed, one kept (they were mispredicted often
    # enough to cost ~40 cycles a marked pixel); loads before every choice.
    for i in range(ns):
        # Indices as unsigned (they are never negative): numba then adds no wraparound.
        x = np.int64(mk[i])
        ux = np.uint64(x)
        bi = np.uint64(x // LANES)
        j = eb[bi] + popcount(em[bi] & ((np.int64(1) << (x & (LANES - 1))) - 1)) + (frac[ux] == 0.0)
        B = blk[ux]
        lo = B * step - 0.5
        hi = (B + 1) * step - 0.5
        # Edge k of the row sits at ep/ek[eidx[k] + K]; indices clamped where there is none.
        im2 = np.uint64(eidx[np.uint64(max(j - 2, 0))] + K)
        im1 = np.uint64(eidx[np.uint64(max(j - 1, 0))] + K)
        i0 = np.uint64(eidx[np.uint64(min(j, ne))] + K)
        ip1 = np.uint64(eidx[np.uint64(min(j + 1, ne))] + K)
        km2, km1, k0, kp1 = ek[im2], ek[im1], ek[i0], ek[ip1]
        pm2, pm1, p0, pp1 = ep[im2], ep[im1], ep[i0], ep[ip1]
        o = out[ux]
        # The edges' values, (ek + 1) step - 0.5 (unused where an index was clamped).
        vm2 = (np.float64(km2) + 1.0) * fstep - 0.5
        vm1 = (np.float64(km1) + 1.0) * fstep - 0.5
        v0 = (np.float64(k0) + 1.0) * fstep - 0.5
        vp1 = (np.float64(kp1) + 1.0) * fstep - 0.5
        left_ok = (j > 0) & ((vm1 == lo) | (vm1 == hi))
        right_ok = (j < ne) & ((v0 == lo) | (v0 == hi))
        c1 = left_ok & right_ok & (vm1 != v0)
        # Only the left edge bounds this stripe: carry on the slope of the stripe before (c2),
        # or only the right one, with the slope of the stripe after (c3).
        c2 = ~c1 & left_ok & (j > 1) & (abs(vm1 - vm2) == step)
        c3 = ~c1 & ~c2 & right_ok & (j + 1 < ne) & (abs(vp1 - v0) == step)
        v1 = vm1 + (x - pm1) * (v0 - vm1) / (p0 - pm1)
        # Cases 2 and 3 share one form, base + (x - at) * (a - b) / (c - d): operands chosen,
        # then one division.
        a = vm1 if c2 else vp1
        b = vm2 if c2 else v0
        c = pm1 if c2 else pp1
        d = pm2 if c2 else p0
        base = vm1 if c2 else v0
        at = pm1 if c2 else p0
        sl = (a - b) / (c - d)
        v23 = base + (x - at) * sl
        v = v1 if c1 else (v23 if c2 | c3 else nan)
        ok = v == v
        v = min(max(v, lo), hi)
        out[ux] = np.float32(v) if ok else o
        n_sub += ok
    return n_sub


@numba.njit(inline="always")
def _row_scratch(W, q, levels):  # pragma: no cover
    """Row buffers of the code resolution and the sub-pixel step, once per band: blk, sel
    (int32; sel is also the sub-pixel step's eidx), qa, qb (q's dtype), mk (int32), frac
    (float64), slow (bool), all (W,), blocks (2, W // LANES + 1) int64, ep (W + 2 _NEAR,)
    float64, ek (W + 2 _NEAR,) int32, and the level histogram (levels,) int64."""
    return (empty(W, np.int32), empty(W, np.int32), empty(W, q.dtype), empty(W, q.dtype),
            empty(W, np.int32), empty((2, W // LANES + 1), np.int64), empty(W, np.float64),
            empty(W + 2 * _NEAR, np.float64), empty(W + 2 * _NEAR, np.int32), empty(W, np.bool_),
            zeros(levels, np.int64))  # fmt: skip


@numba.njit(inline="always", error_model="numpy")
def _classify(di, x, one, ithr, sg, wk, a1, a2, with_q=True):  # pragma: no cover
    """Pixel ``x``'s difference ``di`` of one bit plane: its sign bit ``one`` into ``sg``, its
    weakness (``|di| < ithr[x]``) into ``wk``, and, ``with_q``, ``|di|`` into the smallest and
    second-smallest so far (``a1``, ``a2``: the confidence)."""
    zero = np.uint16(0)
    sg[x] |= one if di > 0 else zero
    wk[x] |= one if abs(di) < ithr[x] else zero
    if with_q:
        aq = abs(di)
        b1 = a1[x]
        a2[x] = min(a2[x], max(b1, aq))
        a1[x] = min(b1, aq)


#: Camera rows per parallel work item: few enough items to keep launches cheap, enough to
#: balance two threads; row buffers are allocated once per item.
_BAND = 16


@kernel(error_model="numpy")
def _decode_rows(pats, refs, with_inverse, bits, white, black, mid2, lit_thr, noise, ratio, nbits, lowest, max_level,
                 n_proj, want_q, subpixel, diff, lit, value, level, conf, counts, counter):  # pragma: no cover
    """Decode one axis from all of its bit planes in one pass, a band of camera rows at a time.

    Per row: references (white/black contrast, integer weak bounds, q scales), every bit plane's
    sign, weakness and raw difference into row buffers that stay in cache, then the code
    resolution, the confidence and the sub-pixel step. Each image is read once; nothing per
    pixel but the outputs goes back to memory.

    The per-plane loop runs in narrow integers: ``d = pattern - inverse`` (or ``2 * pattern -
    white - black`` without inverses, an integer too) in the dtype of ``diff`` (a (0,) array:
    int16 for 8-bit images, int32 for 16-bit), so that a vector register holds as many pixels
    as it can. The scaled, rounded ``q`` that the confidence and the sub-pixel step read is a
    monotone function of ``d``: the confidence takes it of the second-smallest ``|d|`` and the
    sub-pixel step of the two differences at an edge, with the same result as scaling every
    difference.

    pats, refs: tuples of (H, W) pattern and inverse images (``refs`` is ignored without
    inverses); bits: bit of each plane, most significant first. mid2: (H, W) int32, twice the
    stored value of the white/black midpoint in linear light, used without inverses; a (0, 0)
    array means ``white + black`` (a linear camera). Outputs (H, W): lit (bool),
    value (float32), level (int8), conf (float32, written when ``want_q``); counts (H, 2 +
    levels) int64: lit pixels, interpolated pixels, decoded pixels per level. One thread's share
    (:func:`shared.scan._bands.run_bands`): bands of rows taken from ``counter``.
    """
    H, W = white.shape
    k = bits.size  # planes of this axis; the tuples are padded to _MAX_PLANES (one signature)
    full = (1 << nbits) - 1
    dmax = np.iinfo(diff.dtype).max
    half = np.float32(dmax // 2)  # weak bounds are capped here (they fit diff's dtype)
    n_bands = (H + _BAND - 1) // _BAND
    line = 64 // white.itemsize  # image elements per cache line
    sg = empty(W, np.uint16)
    wk = empty(W, np.uint16)
    ithr = empty(W, diff.dtype)
    wb = empty(W, diff.dtype)
    kq = empty(W, np.float32)
    dd = empty(W, diff.dtype)  # one plane's differences at a time
    a1 = empty(W, diff.dtype)
    a2 = empty(W, diff.dtype)
    blk, sel, qa, qb, mk, blocks, frac, ep, ek, slow, hist = _row_scratch(W, dd, max_level - lowest + 1)
    while True:
        band = next_item(counter)
        if band >= n_bands:
            break
        for y in range(band * _BAND, min(H, band * _BAND + _BAND)):
            # The next row of each image is asked for just before this row of it is read
            # (see prefetch): spread out so, the requests keep the memory busy.
            ahead = min(y + 1, H - 1)
            for x in range(0, W, line):
                prefetch(white[ahead], x)
                prefetch(black[ahead], x)
            wr = white[y]
            br = black[y]
            lr = lit[y]
            # One loop per case, the choices hoisted and the lit count in int32 (a loop
            # with them inside, and an int64 sum, ran 8 pixels a vector, spilling).
            n_lit = np.int32(0)
            if with_inverse:
                for x in range(W):
                    c = np.float32(wr[x]) - np.float32(br[x])
                    lx = c > lit_thr
                    lr[x] = lx
                    n_lit = add32(n_lit, np.int32(lx))
                    # The swing of a bit's difference: the contrast against an inverse.
                    thr = max(noise, ratio * c)
                    # d is an integer: |d| < thr exactly when |d| < ceil(thr).
                    ithr[x] = min(np.ceil(thr), half)
                    wb[x] = np.int32(wr[x]) + np.int32(br[x])
                if want_q:  # the q scale: only the confidence and the sub-pixel step read it
                    for x in range(W):
                        c = np.float32(wr[x]) - np.float32(br[x])
                        kq[x] = np.float32(127.0) / c if c > 0 else np.float32(0.0)
            else:
                for x in range(W):
                    c = np.float32(wr[x]) - np.float32(br[x])
                    lx = c > lit_thr
                    lr[x] = lx
                    n_lit = add32(n_lit, np.int32(lx))
                    # Against the white/black midpoint the swing is half the contrast (the
                    # stored difference is then doubled).
                    thr = max(noise, ratio * (c * np.float32(0.5)))
                    ithr[x] = min(np.ceil(thr * np.float32(2.0)), half)
                    wb[x] = np.int32(wr[x]) + np.int32(br[x])
                if mid2.shape[0] > 0:  # a non-linear camera: the midpoint in linear light
                    mr = mid2[y]
                    for x in range(W):
                        wb[x] = mr[x]
                if want_q:
                    for x in range(W):
                        sw = (np.float32(wr[x]) - np.float32(br[x])) * np.float32(0.5)
                        g = np.float32(127.0) / sw if sw > 0 else np.float32(0.0)
                        kq[x] = g * np.float32(0.5)
            for x in range(W):
                sg[x] = 0
                wk[x] = 0
                a1[x] = dmax
                a2[x] = dmax
            # Bit plane outer, pixel inner: these loops vectorise.
            for j in range(k):
                one = np.uint16(1) << bits[j]
                p = pats[j][y]
                pn = pats[j][ahead]
                rn = refs[j][ahead]
                for x in range(0, W, line):
                    prefetch(pn, x)
                    if with_inverse:
                        prefetch(rn, x)
                # One pass a plane: the difference, stored for the sub-pixel step's edge pick,
                # is read back at once (a register, not memory) for the sign, weakness and
                # confidence.
                if with_inverse:
                    r = refs[j][y]
                    if want_q:
                        for x in range(W):
                            dd[x] = np.int32(p[x]) - np.int32(r[x])
                            _classify(dd[x], x, one, ithr, sg, wk, a1, a2)
                    else:
                        for x in range(W):
                            dd[x] = np.int32(p[x]) - np.int32(r[x])
                            _classify(dd[x], x, one, ithr, sg, wk, a1, a2, False)
                elif want_q:
                    for x in range(W):
                        dd[x] = 2 * np.int32(p[x]) - wb[x]
                        _classify(dd[x], x, one, ithr, sg, wk, a1, a2)
                else:
                    for x in range(W):
                        dd[x] = 2 * np.int32(p[x]) - wb[x]
                        _classify(dd[x], x, one, ithr, sg, wk, a1, a2, False)
                if want_q and subpixel:
                    _edge_pick(dd, qa, qb)
            hist[:] = 0
            lv = level[y]
            _resolve_row(sg, wk, lr, full, lowest, max_level, n_proj, blk, lv, value[y], sel, hist)
            n_sub = 0
            if want_q:
                cr = conf[y]
                for x in range(W):
                    m = a2[x]
                    # A single plane has no second-smallest difference: full confidence.
                    qm = np.int32(127) if m == dmax else _quantise(m, kq[x])
                    cr[x] = min(np.float32(qm) / np.float32(127.0), np.float32(1.0)) if blk[x] >= 0 else np.float32(0.0)
                if subpixel:
                    n_sub = _subpixel_row(blk, lv, qa, qb, kq, True, lowest, sel, mk, blocks, frac, ep, ek, slow, value[y])
            counts[y, 0] = n_lit
            counts[y, 1] = n_sub
            for L in range(hist.size):
                counts[y, 2 + L] = hist[L]


@kernel(error_model="numpy")
def _finish_rows(signs, weak, lit, m2, has_q, q, nbits, lowest, max_level, n_proj, subpixel, value, level, conf,
                 counts, counter):  # pragma: no cover
    """Resolve codes classified batch by batch (:func:`_bit_planes`) and run the sub-pixel step,
    a band of camera rows at a time. signs, weak, lit, m2: (H, W); q: (planes, H, W) int8 when
    ``has_q``; outputs as in :func:`_decode_rows` (``counts[:, 0]`` is left alone). One thread's
    share, as there."""
    H, W = lit.shape
    full = (1 << nbits) - 1
    kq = zeros(W, np.float32)  # unread: q is already scaled
    n_bands = (H + _BAND - 1) // _BAND
    blk, sel, qa, qb, mk, blocks, frac, ep, ek, slow, hist = _row_scratch(W, q, max_level - lowest + 1)
    while True:
        band = next_item(counter)
        if band >= n_bands:
            break
        for y in range(band * _BAND, min(H, band * _BAND + _BAND)):
            hist[:] = 0
            _resolve_row(signs[y], weak[y], lit[y], full, lowest, max_level, n_proj, blk, level[y], value[y], sel,
                         hist)
            n_sub = 0
            if has_q:
                cr = conf[y]
                mr = m2[y]
                for x in range(W):
                    cr[x] = (min(np.float32(mr[x]) / np.float32(127.0), np.float32(1.0)) if blk[x] >= 0
                             else np.float32(0.0))
                if subpixel:
                    _edge_differences(signs[y], q[:, y, :], nbits, qa, qb)
                    n_sub = _subpixel_row(blk, level[y], qa, qb, kq, False, lowest, sel, mk, blocks, frac, ep, ek, slow,
                                           value[y])
            counts[y, 1] = n_sub
            for L in range(hist.size):
                counts[y, 2 + L] = hist[L]


@kernel(error_model="numpy")
def _grey_rgb(grey, shift, out, counter):  # pragma: no cover
    """(H, W) uint8/uint16 grey -> (H, W, 3) uint8 grey RGB in ``out`` (C order; top 8 bits);
    several times faster than ``np.repeat`` on a new axis, which was a tenth of a whole
    in-memory decode. Each row is written as a flat (3 W,) array: LLVM vectorises the
    interleaved stores there, not through the three-index form (0.54 -> 0.13 ms a 1.3 MP
    frame on one thread). One thread's share (:func:`shared.scan._bands.run_bands`): bands of
    rows taken from ``counter``."""
    H, W = grey.shape
    n_bands = (H + _BAND - 1) // _BAND
    while True:
        band = next_item(counter)
        if band >= n_bands:
            break
        for y in range(band * _BAND, min(H, band * _BAND + _BAND)):
            _grey_row(grey[y], shift, out[y], W)


@helper
def _grey_row(g, shift, row, W):  # pragma: no cover
    """One row of :func:`_grey_rgb`: ``g`` (W,) grey into ``row`` (W, 3)."""
    o = row.reshape(3 * W)
    for x in range(W):
        v = np.uint8(g[x] >> shift)
        o[3 * x] = v
        o[3 * x + 1] = v
        o[3 * x + 2] = v
