"""The activity levels' rANS tables of a range band's residuals (private kernels of
:mod:`shared.compress._band`).

:func:`shared.compress._lpred.encode_residuals` and the interpolation order
(:mod:`shared.compress._interp`) give each residual an activity level (:data:`NLEVEL`
half-octaves); here the encoder chooses which levels share a table -- the raster order by the
partition of its levels into runs that codes the band in the fewest bits as the coder spends
them (:func:`level_partition`), the interpolation order by sliding and merging them
(:func:`context_choice`) -- estimates what sign contexts would save (:func:`pattern_bits`),
and turns levels into tables (:func:`apply_levels`); the decoder rebuilds a partition from its
flags (:func:`partition_tables`).
"""

from __future__ import annotations

import math

import numpy as np

from shared.compress._lpred import MAX_COFS, NCTX, NLEVEL, NRES, NSUB
from shared.compress._rans import NSYM
from shared.compress._tables import table_bits
from shared.core.jit import empty, full, helper, kernel, zeros


@helper(inline=False)
def _tables_bits(counts, nt):
    """Estimated bits of coding the symbols counted in ``counts`` (>= nt, symbols) int64, tables 0..nt-1,
    with static tables: their code lengths and the stored tables (:mod:`shared.compress._tables`:
    about 4 bits a symbol used, 2 a symbol absent, up to the last used)."""
    bits = 0.0
    for t in range(nt):
        tot = 0
        last = -1
        for s in range(counts.shape[1]):
            tot += counts[t, s]
            if counts[t, s] > 0:
                last = s
        for s in range(last + 1):
            c = counts[t, s]
            if c > 0:
                bits += c * math.log2(tot / c) + 4.0
            else:
                bits += 2.0
    return bits


@kernel
def context_choice(tab, val, nb, n0, n1, t0):
    """The residual tables of events n0..n1-1 (coded by :func:`encode_residuals` with their
    activity level as table ``t0 + level``): the offset ``cofs`` (0..:data:`MAX_COFS`) and the
    merging ``cshift`` (0..2) of the least estimated bits, the table of a level being
    ``t0 + (min(max(level - cofs, 0), NCTX - 1) >> cshift)``. Returns (bits, cofs, cshift). The
    bits: the static-table code length, the escapes' raw bits (``nb``) and the stored tables (:mod:`shared.compress._tables`:
    about 4 bits a symbol used, 2 a symbol absent, up to the last used; measured against 8 and
    16, the old byte-wise tables' cost, on the dragon scans 5.089 -> 5.068 and 4.892 -> 4.880
    bits per valid sample, lossless). Noisy depth fills the top levels (a fixed offset 0 put
    30 % of the bunny's samples at 1:1 in the last table); the offset follows the band's noise."""
    counts, raw = level_counts(tab, val, nb, n0, n1, t0)
    return choice_of(counts, raw)


@kernel
def level_counts(tab, val, nb, n0, n1, t0):
    """The symbol counts (NLEVEL, NSYM) int64 of the residual events n0..n1-1 by activity level
    (their tables ``t0 + level``), and the escapes' raw bits (the same whatever the tables)."""
    counts = zeros((NLEVEL, NSYM), np.int64)
    raw = 0.0
    for i in range(n0, n1):
        t = tab[i] - t0
        if 0 <= t < NLEVEL:
            counts[t, val[i]] += 1
        elif tab[i] < 0:
            raw += nb[i]
    return counts, raw


@kernel
def choice_of(counts, raw):
    """:func:`context_choice` of the residuals counted by :func:`level_counts`."""
    merged = zeros((NCTX, NSYM), np.int64)
    best = 1e300
    best_o = 0
    best_s = 0
    for cofs in range(MAX_COFS + 1):
        for shift in range(3):
            # scalar loops (slice arithmetic costs seconds of compilation)
            for t in range(NCTX):
                for s in range(NSYM):
                    merged[t, s] = 0
            for lev in range(NLEVEL):
                t = min(max(lev - cofs, 0), NCTX - 1) >> shift
                for s in range(NSYM):
                    merged[t, s] += counts[lev, s]
            bits = raw + _tables_bits(merged, NCTX >> shift)
            if bits < best:
                best = bits
                best_o = cofs
                best_s = shift
    return best, best_o, best_s


@kernel
def pattern_bits(alt, first, tab, nb, n0, n1, exact):
    """Estimated bits of a band's residuals (events n0..n1-1, coded without sign contexts) had
    they been coded in sign contexts: from the counts ``alt`` (NLEVEL * m, NSYM) of their
    symbols so coded by activity level and pattern (m patterns), each level's patterns in the
    tables from ``first`` (NLEVEL,) int64 on; as :func:`context_choice` counts bits, or with
    ``exact`` as the coder spends them (:func:`shared.compress._tables.table_bits`, as
    :func:`level_partition` counts them); the escapes' raw bits taken as they are (a residual's
    sign changes them by at most one bit)."""
    m = alt.shape[0] // NLEVEL
    counts = zeros((NRES, NSYM), np.int64)
    bits = 0.0
    for i in range(n0, n1):
        if tab[i] < 0:
            bits += nb[i]
    for lev in range(NLEVEL):
        for k in range(m):
            for s in range(alt.shape[1]):
                counts[first[lev] + k, s] += alt[lev * m + k, s]
    if not exact:
        return bits + _tables_bits(counts, NRES)
    for t in range(NRES):
        bits += table_bits(counts[t : t + 1])
    return bits


def sign_bits(alt: np.ndarray, cofs: int, tab: np.ndarray, nb: np.ndarray, n0: int, n1: int) -> float:
    """:func:`pattern_bits` of the raster order's sign contexts (:func:`_sign_context`; ``alt``
    from :func:`encode_residuals`), the levels slid by ``cofs``, as the coder spends them (beside
    :func:`level_partition`'s bits)."""
    first = (np.minimum(np.maximum(np.arange(NLEVEL) - cofs, 0), NCTX - 1) >> 2) * NSUB
    return pattern_bits(alt[: NLEVEL * NSUB], first.astype(np.int64), tab, nb, np.int64(n0), np.int64(n1), True)


def grad_counts(alt: np.ndarray) -> np.ndarray:
    """The symbol counts (NLEVEL, NSYM) int64 of a band's residuals by their level without the
    curvature in the activity (``alt`` from :func:`encode_residuals`)."""
    return alt[NLEVEL * NSUB :].astype(np.int64)


@kernel
def apply_contexts(tab, n0, n1, t0, cofs, cshift):
    """Turn the levels of the residual events n0..n1-1 into their tables (:func:`context_choice`)."""
    apply_levels(tab, n0, n1, t0, level_tables(cofs, cshift))


@kernel
def apply_levels(tab, n0, n1, t0, lut):
    """Turn the levels of the residual events n0..n1-1 into their tables ``lut`` (NLEVEL,) int64."""
    for i in range(n0, n1):
        if tab[i] >= t0:
            tab[i] = t0 + lut[tab[i] - t0]


@kernel
def level_tables(cofs, cshift):
    """The table (NLEVEL,) int64 of each activity level: slid by ``cofs`` and merged by
    ``cshift`` (0..2, :func:`context_choice`)."""
    lut = empty(NLEVEL, np.int64)
    for lev in range(NLEVEL):
        lut[lev] = min(max(lev - cofs, 0), NCTX - 1) >> cshift
    return lut


@kernel
def partition_tables(starts):
    """The table (NLEVEL,) int64 of each level from the flags ``starts`` (NLEVEL - 1,) of 0 or 1
    (1: level k + 1 starts a new table; the decoder checks them, as it reads them)."""
    lut = zeros(NLEVEL, np.int64)
    for k in range(NLEVEL - 1):
        lut[k + 1] = lut[k] + starts[k]
    return lut


@kernel
def level_partition(counts, raw):
    """The partition of the activity levels into runs of neighbouring levels, one table a run,
    that codes the residuals counted by :func:`level_counts` (``counts``, escapes' ``raw`` bits)
    in the fewest bits as the coder would spend them (:func:`shared.compress._tables.table_bits`:
    code lengths and stored tables), by dynamic programming over the runs of the levels holding
    residuals (a level holding none joins the next). Returns (bits with the raw bits, not the
    header's flags, coded either way; lut (NLEVEL,) int64). Where the
    sliding and merging of :func:`context_choice` keeps tables of a few hundred samples (a real
    capture's quiet levels: each stored at some hundreds of bits), neighbouring levels share one."""
    used = zeros(NLEVEL, np.int64)  # the levels holding residuals
    nu = 0
    for lev in range(NLEVEL):
        for s in range(NSYM):
            if counts[lev, s] > 0:
                used[nu] = lev
                nu += 1
                break
    lut = zeros(NLEVEL, np.int64)
    if nu == 0:
        return raw, lut
    # cost[i, j]: the used levels i..j in one table
    cost = zeros((nu, nu), np.float64)
    acc = zeros((1, NSYM), np.int64)
    for i in range(nu):
        for s in range(NSYM):
            acc[0, s] = 0
        for j in range(i, nu):
            for s in range(NSYM):
                acc[0, s] += counts[used[j], s]
            cost[i, j] = table_bits(acc)
    best = full(nu + 1, 1e300, np.float64)
    first = zeros(nu + 1, np.int64)  # where the last run of used levels 0..j-1 starts
    best[0] = 0.0
    for j in range(1, nu + 1):
        for i in range(j):
            b = best[i] + cost[i, j - 1]
            if b < best[j]:
                best[j] = b
                first[j] = i
    # the runs from the top down, then each level's table counted from the bottom: a level
    # holding no residual takes the table of the next used level above it (the last, past them)
    run_of = zeros(nu, np.int64)
    j = nu
    runs = 0
    while j > 0:
        i = first[j]
        for k in range(i, j):
            run_of[k] = runs
        runs += 1
        j = i
    k = 0
    for lev in range(NLEVEL):
        while k < nu - 1 and used[k] < lev:
            k += 1
        lut[lev] = runs - 1 - run_of[k]
    return raw + best[nu], lut
