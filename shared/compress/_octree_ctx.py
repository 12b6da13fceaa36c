"""The octree cloud codec's neighbour map, contexts and adaptive models (private kernels of
:mod:`shared.compress._octree`, whose docstring describes what each context sees).

Split from :mod:`shared.compress._octree` (the chunk coder and decoder) by size only: every name
here is imported there too.
"""

from __future__ import annotations

import numpy as np

from shared.compress._octree_prior import PRIOR_BOUNDS, PRIOR_P12, PRIOR_SHIFTS
from shared.compress._rans import (
    BIN,
    P_ONE,
    adapt_state,
    at,
    model_p,
    model_update,
    set_at,
    state_next,
    state_p,
)
from shared.core.bits import popcount
from shared.core.jit import empty, helper, kernel
from shared.core.morton import compact21

#: Neighbour regions: 2**REGION_LOG nodes a side, mapped with an empty border (no bounds
#: checks): the map of (x, y, z) is at ORIGIN + (z * PAD + y) * PAD + x, in an array of PAD**3
#: (a border of one cell, and of a row more before the first slab, where the look-ups two back
#: along y one slab down land: the indices are unsigned, :func:`shared.compress._rans.at`); the
#: bit row of (y, z) is at ``map index // PAD`` (MAP_ROWS of them).
REGION_LOG = 6
REGION = 1 << REGION_LOG
REGION_SHIFT = 3 * REGION_LOG
PAD = REGION + 2
ORIGIN = PAD * PAD + 2 * PAD + 1
MAP_ROWS = PAD * PAD + 1
#: Occupancy contexts: child bits of nodes with two children or more, occupied nodes of the
#: slab on the child's side along z (2: :func:`_slab_z`) x bit (8) x occupied siblings (4) x past
#: faces (8) x two back (8) x occupied future faces (8); then the single-child flag (64) and the
#: single child's x, y and z bits. (The side of the node a child lies on along each axis, which
#: the future faces' contexts once also held, is the bit's position: those contexts were 8 of 64
#: used, in two cache lines of four, and the table 1 MB, larger than the L2 cache.)
C_BIT_SPAN = 8 * 4 * 8 * 8 * 8
C_BIT = 0
C_SINGLE = C_BIT + 2 * C_BIT_SPAN
C_X = C_SINGLE + 256
C_Y = C_X + 512
C_Z = C_Y + 1024
N_OCC_CTX = C_Z + 8192 * 16
#: The x and y bits of a single child in the last MIX_LEVELS levels (where most of the bits
#: go) are coded by three models, their probabilities mixed by secondary estimation: the
#: first (A) of the context above, a second (B) of the past neighbours' children projected
#: along z (footprints), a third (C) of the occupied nodes of the 26 around counted per slab.
MIX_LEVELS = 2
B_X = N_OCC_CTX
B_Y = B_X + 512
C3_X = B_Y + 1024
C3_Y = C3_X + 1000
#: The single-child flag of the FLAG_MIX_LEVELS levels above the last is mixed too, its second
#: model (B) the footprints at x - 1 and y - 1 and the occupied face neighbours, its third (C)
#: the occupied nodes of the 26 around counted per slab along z.
FLAG_MIX_LEVELS = 3
#: Whether the last level's x and y bits are mixed (a literal of the last level's decoder).
_LAST_MIXED = MIX_LEVELS >= 1
B_SINGLE = C3_Y + 2000
C3_SINGLE = B_SINGLE + 256 * 7
N_MODELS = C3_SINGLE + 900
#: Secondary estimation: each model's probability falls in one of SSE_N buckets (by its
#: log-odds, uniform over [-7, 7]; SSE_EDGES[k] is the first 12-bit probability of bucket k),
#: and the three buckets of an event pick an adaptive cell of its kind's SSE_N**3 table (x, y,
#: single-child flag), whose probability codes the event.
SSE_N = 16
SSE_EDGES = (0, 9, 21, 51, 120, 277, 606, 1205, 2048, 2891, 3490, 3819, 3976, 4045, 4075, 4087)
SSE_BUCKET = (np.searchsorted(np.array(SSE_EDGES), np.arange(4096), side="right") - 1).astype(np.uint8)  # 4 kB: stays in L1
#: A cell's first probability (16 bits): the logistic of 0.5 a + 0.3 b + 0.3 c, the buckets'
#: centres in log-odds a, b, c = 0.875 (k + 0.5) - 7, i.e. of 0.0875 m - 7.21875 with
#: m = 5 ka + 3 kb + 3 kc (tabled as integers: encoder and decoder agree on every machine).
SSE_INIT_M = np.array((
    47, 52, 57, 62, 68, 74, 81, 88, 96, 105, 114, 125, 136, 149, 163, 177, 194, 211, 231, 252, 275, 300, 327, 357,
    389, 425, 463, 505, 551, 601, 656, 715, 780, 850, 927, 1010, 1101, 1200, 1308, 1425, 1552, 1690, 1841, 2004,
    2181, 2373, 2582, 2808, 3053, 3318, 3604, 3914, 4249, 4610, 5000, 5419, 5870, 6355, 6875, 7433, 8029, 8666,
    9346, 10069, 10838, 11653, 12515, 13425, 14383, 15389, 16443, 17544, 18691, 19882, 21114, 22385, 23692, 25031,
    26398, 27789, 29198, 30620, 32051, 33484, 34915, 36337, 37746, 39137, 40504, 41843, 43150, 44421, 45653, 46844,
    47991, 49092, 50146, 51152, 52110, 53020, 53882, 54697, 55466, 56189, 56869, 57506, 58102, 58660, 59180, 59665,
    60116, 60535, 60925, 61286, 61621, 61931, 62217, 62482, 62727, 62953, 63162, 63354, 63531, 63694, 63845, 63983,
    64110, 64227, 64335, 64434, 64525, 64608, 64685, 64755, 64820, 64879, 64934, 64984, 65030, 65072, 65110, 65146,
    65178, 65208, 65235, 65260, 65283, 65304, 65324, 65341, 65358, 65372, 65386, 65399, 65410, 65421, 65430, 65439,
    65447, 65454, 65461, 65467, 65473, 65478, 65483, 65488), np.uint32)
_ka, _kb, _kc = np.meshgrid(np.arange(SSE_N), np.arange(SSE_N), np.arange(SSE_N), indexing="ij")
#: A cell starts as if it had seen SSE_INIT_COUNT events (its first updates at rate 1/10, not
#: 1/2: the initial probability is a fair guess, not worth discarding at the first event; 0.004
#: bits a point fewer on the bench scan and the bunny's at 0.1 mm, counts of 6 to 14 alike).
SSE_INIT_COUNT = 8
#: Every cell's first state, (SSE_N**3,) uint32; the tables of x, y and the flag follow each other.
SSE_INIT = SSE_INIT_M[(5 * _ka + 3 * _kb + 3 * _kc).ravel()] | np.uint32(SSE_INIT_COUNT << 16)
N_SSE = 3 * SSE_N**3
#: A cell's slowest update, as a count (:func:`shared.compress._rans.adapt_state`): rate 1/128.
SSE_LIMIT = 128
_OCCUPIED = 256
_CODED = 512

#: 0 and 1 as int64 values a kernel loads (not literals: see :func:`_decode_level`).
_ZERO_ONE = np.array((0, 1), np.int64)
#: LOWEST[byte]: the index of the lowest set bit (byte > 0).
LOWEST = np.array([(i & -i).bit_length() - 1 for i in range(256)], np.int64)


# The scalar helpers below (contexts, cells, counter steps, the SSE cell, the map's marks, and
# the rANS coder's at/set_at/get_bit/state_* they call) are kernel helpers (shared.core.jit),
# inlined by LLVM when their callers are optimised; numba's own inlining (inline="always")
# re-reads the callee's bytecode and deep-copies its IR at every call site (hundreds of copies
# of ``at`` alone): dropping it took the cloud codec's compilation from 81 s to 28 s, for no
# speed (A/B in the commits). Inlined by numba still: _bit_context (the decoder's innermost
# loop), and _around, _learn, _emit_mixed, which LLVM leaves as calls in the encoder or the
# decoder: as LLVM-inlined helpers (shared.core.jit.helper), with the rANS renormalisation
# (shared.compress._rans._next), the cloud decoder ran 2.5-3.5 % slower.
@helper(inline=False)
def _cell(key):
    """Index of a node in its region's map."""
    c = key & ((1 << REGION_SHIFT) - 1)
    return ORIGIN + (compact21(c >> 2) * PAD + compact21(c >> 1)) * PAD + compact21(c)


@helper(inline=False)
def _child_cell(ci, b):
    """Map index of child ``b`` of the node at map index ``ci`` (in the child level's region)."""
    r = ci - ORIGIN
    z = r // (PAD * PAD)
    r -= z * (PAD * PAD)
    y = r // PAD
    x = r - y * PAD
    x = ((x << 1) | (b & 1)) & (REGION - 1)
    y = ((y << 1) | ((b >> 1) & 1)) & (REGION - 1)
    z = ((z << 1) | (b >> 2)) & (REGION - 1)
    return ORIGIN + (z * PAD + y) * PAD + x


@helper(inline=False)
def _neighbours(atlas, ci):
    """The region map's values of the node's face neighbours (0 outside the region) -x, -y,
    -z, +x, +y, +z, of the nodes two back along x and y, and the occupancy of the past x and y
    neighbours' neighbours above and below (4 bits: where the surface climbs or falls)."""
    return (np.int64(at(atlas, ci - 1)), np.int64(at(atlas, ci - PAD)), np.int64(at(atlas, ci - PAD * PAD)),
            np.int64(at(atlas, ci + 1)), np.int64(at(atlas, ci + PAD)), np.int64(at(atlas, ci + PAD * PAD)),
            np.int64(at(atlas, ci - 2)), np.int64(at(atlas, ci - 2 * PAD)),
            ((at(atlas, ci - 1 + PAD * PAD) >> 8) & 1) | (((at(atlas, ci - 1 - PAD * PAD) >> 8) & 1) << 1)
            | (((at(atlas, ci - PAD + PAD * PAD) >> 8) & 1) << 2) | (((at(atlas, ci - PAD - PAD * PAD) >> 8) & 1) << 3))


@kernel(inline="always")
def _bit_context(b, cur, ncur, xm, ym, zm, xp, yp, zp, slabs):
    """The context of child bit ``b`` of a node whose bits below ``b`` are ``cur`` (``ncur``
    of them set), from its neighbours' map values and ``slabs`` (:func:`_slab_z`; see the
    module docstring)."""
    bx = b & 1
    by = (b >> 1) & 1
    bz = b >> 2
    px = ((cur >> (b - 1)) & 1) if bx else ((xm >> (b | 1)) & 1)
    py = ((cur >> (b - 2)) & 1) if by else ((ym >> (b | 2)) & 1)
    pz = ((cur >> (b - 4)) & 1) if bz else ((zm >> (b | 4)) & 1)
    back = ((xm >> b) & 1) | (((ym >> b) & 1) << 1) | (((zm >> b) & 1) << 2)
    future = (((xp >> 8) & 1) << 2) | (((yp >> 8) & 1) << 1) | ((zp >> 8) & 1)
    return (((((((slabs >> bz) & 1) * 8 + b) * 4 + min(ncur, 3)) * 8 + (px | (py << 1) | (pz << 2))) * 8 + back) * 8
            + future)


@helper(inline=False)
def _slab_z(sz0, sz2):
    """Whether more than one of the nine nodes of the slab below a node are occupied (bit 0;
    ``sz0`` of :func:`_around`) and of the slab above (bit 1, ``sz2``): the side of the node the
    surface lies on, for its child bits (a noisy scan's surface crosses neighbours that the face
    and past-neighbour contexts do not see). (0, 1-2, 3-4, 5+ each: 0.0025 bits a point more on
    the bench scan at 0.1 mm, 0.008 fewer on the bunny's, for twice the contexts; more than two
    or three rather than one: 0.0007 and 0.004 more.)"""
    return (1 if sz0 > 1 else 0) | ((1 if sz2 > 1 else 0) << 1)


@helper(inline=False)
def _lean(sz0, sz2):
    """Which slab holds more of the 26 nodes around a node: 1 the one above (``sz2`` of
    :func:`_around`), 2 the one below (``sz0``), 0 neither; for the single child's z bit
    (:func:`_z_context`)."""
    return (1 if sz2 > sz0 else 0) | ((1 if sz0 > sz2 else 0) << 1)


@helper(inline=False)
def _any(v, mask):
    # Callers pass the mask as np.int64(...), not a literal: numba compiles a copy of a kernel
    # per literal argument value (nine copies of this one before).
    return np.int64((v & mask) != 0)


@helper(inline=False)
def _single_context(xm, ym, zm, xp, yp, zp, xm2, ym2):
    """Context of "the node has exactly one child": occupied face neighbours (0-6) x the
    children of the past neighbours (0-7+) x whether the nodes two back along x and y are occupied."""
    occ = ((xm >> 8) & 1) + ((ym >> 8) & 1) + ((zm >> 8) & 1) + ((xp >> 8) & 1) + ((yp >> 8) & 1) + ((zp >> 8) & 1)
    kids = min(popcount((xm & 255) | ((ym & 255) << 8) | ((zm & 255) << 16)), 7)
    return C_SINGLE + ((occ * 8 + kids) * 2 + ((xm2 >> 8) & 1)) * 2 + ((ym2 >> 8) & 1)


@helper(inline=False)
def _x_context(xm, ym, zm, xp, xm2):
    """Context of a single child's x bit: where the past neighbours' children lie along x."""
    return C_X + (_any(xm, np.int64(0xAA)) | (_any(xm, np.int64(0x55)) << 1) | (((xp >> 8) & 1) << 2) | (_any(ym, np.int64(0xAA)) << 3)
                  | (_any(ym, np.int64(0x55)) << 4) | (_any(zm, np.int64(0xAA)) << 5) | (_any(zm, np.int64(0x55)) << 6)
                  | (_any(xm2, np.int64(0xAA)) << 7) | (_any(xm2, np.int64(0x55)) << 8))


@helper(inline=False)
def _y_context(bx, xm, ym, zm, yp, ym2):
    """Context of a single child's y bit (its x bit ``bx`` known)."""
    return C_Y + (_any(ym, 0x44 << bx) | (_any(ym, 0x11 << bx) << 1) | (((yp >> 8) & 1) << 2)
                  | (_any(xm, np.int64(0x22)) << 3) | (_any(xm, np.int64(0x88)) << 4) | (((zm >> (4 | bx)) & 1) << 5)
                  | (((zm >> (6 | bx)) & 1) << 6) | (bx << 7) | (_any(ym2, np.int64(0xCC)) << 8) | (_any(ym2, np.int64(0x33)) << 9))


@helper(inline=False)
def _z_context(bx, by, xm, ym, zm, zp, xm2, ym2, slope, lean):
    """Context of a single child's z bit (its x and y bits known): the past neighbours'
    children, the nodes two back, whether the past x neighbour's neighbours above and below are
    occupied (two of the four bits of ``slope``) and ``lean``: 1 when more of the 26 around are
    occupied above the node than below, 2 when fewer (in place of the past y neighbour's half of
    ``slope``: no more contexts; at 0.1 mm 0.008 bits a point fewer on the bench scan, about 0.03
    on the bunny's). The column (x and y bits) and the past z neighbour's two children in it are
    the lowest four bits: the decoder loads the four columns' models before it knows the column,
    and they lie within 2 kB, within 64 bytes when the past x and y neighbours' children do not
    tell the columns apart."""
    col = bx | (by << 1)
    return C_Z + (col | (((zm >> (col | 4)) & 1) << 2) | (((zm >> col) & 1) << 3) | (((zp >> 8) & 1) << 4)
                  | (((xm >> (1 | (by << 1))) & 1) << 5) | (((xm >> (5 | (by << 1))) & 1) << 6)
                  | (((ym >> (bx | 2)) & 1) << 7) | (((ym >> (bx | 6)) & 1) << 8)
                  | (_any(xm2, np.int64(0xF0)) << 9) | (_any(xm2, np.int64(0x0F)) << 10) | (_any(ym2, np.int64(0xF0)) << 11) | (_any(ym2, np.int64(0x0F)) << 12)
                  | ((slope & 3) << 13) | (lean << 15))


@helper(inline=False)
def _emit(tab, val, nb, n, models, ctx, bit, kind):
    """Append a binary event of context ``ctx``'s model and adapt it; -1 when the buffers are full.
    ``kind`` (kept in ``nb``, which binary events do not use) tells the bench's cost breakdown
    what the bit was: 0 single-child flag, 1-3 its x, y, z bits, 4 a child bit."""
    if n < 0 or n >= tab.shape[0]:
        return -1
    tab[n] = BIN
    val[n] = (model_p(models, ctx) << 1) | bit
    nb[n] = kind
    model_update(models, ctx, bit)
    return n + 1


@helper(inline=False)
def _lat(v):
    """The footprint of a map value's children seen along z: 4 bits, bit ``x + 2 y``."""
    v = np.int64(v)
    return (v | (v >> 4)) & 15


@kernel(inline="always")
def _around(atlas, rows, ci):
    """What the 26 nodes around a node tell a single child's x and y bits and the single-child
    flag: the occupied ones
    counted per slab (sx0, sx1, sx2: the slabs at x - 1, x and x + 1, the node itself left out;
    then along y and z), from the occupancy bit rows of the region (``rows[ci // PAD]`` bit
    ``ci % PAD - 1``: one uint64 per row along x), and the footprints (:func:`_lat` of the
    nodes at z - 1, z and z + 1 together) of the columns at x - 1, y - 1, x - 2 and y - 2."""
    r0 = ci // PAD
    x = np.uint64(ci - r0 * PAD - 1)
    # The 27 nodes as 9 windows of 3 bits (x - 1, x, x + 1; bit x - 1 empty at x = 0), window
    # 3 (dz + 1) + dy + 1; each slab's count is then one popcount of a mask.
    w = np.int64(0)
    for k in range(9):
        r = at(rows, r0 + (k % 3 - 1) + (k // 3 - 1) * PAD)
        w |= np.int64((((r >> x) << np.uint64(1)) | ((r << np.uint64(1)) >> x)) & np.uint64(7)) << (3 * k)
    zz = PAD * PAD
    fx1 = _lat(at(atlas, ci - 1 - zz)) | _lat(at(atlas, ci - 1)) | _lat(at(atlas, ci - 1 + zz))
    fy1 = _lat(at(atlas, ci - PAD - zz)) | _lat(at(atlas, ci - PAD)) | _lat(at(atlas, ci - PAD + zz))
    fx2 = _lat(at(atlas, ci - 2 - zz)) | _lat(at(atlas, ci - 2)) | _lat(at(atlas, ci - 2 + zz))
    fy2 = _lat(at(atlas, ci - 2 * PAD - zz)) | _lat(at(atlas, ci - 2 * PAD)) | _lat(at(atlas, ci - 2 * PAD + zz))
    # the node itself (occupied) is counted in the middle slabs
    return (popcount(w & 0o111111111), popcount(w & 0o222222222) - 1, popcount(w & 0o444444444),
            popcount(w & 0o007007007), popcount(w & 0o070070070) - 1, popcount(w & 0o700700700),
            popcount(w & 0o777), popcount(w & 0o777000) - 1, popcount(w >> 18), fx1, fy1, fx2, fy2)


@helper(inline=False)
def _mark(atlas, rows, ci, on):
    """Mark the node at map index ``ci`` occupied (``on``) or empty, in the map and its bit rows."""
    r = ci // PAD
    # int64 and uint64 values, not literals: set_at is compiled once a type, not once a literal
    if on:
        set_at(atlas, ci, np.int64(_OCCUPIED))
        set_at(rows, r, at(rows, r) | (np.uint64(1) << np.uint64(ci - r * PAD - 1)))
    else:
        set_at(atlas, ci, np.int64(0))
        set_at(rows, r, np.uint64(0))


@helper(inline=False)
def _mixed_x(xm, ym, zm, xp, xm2, sx0, sx1, sx2, fx1, fx2):
    """The three models (A, B, C) of a single child's x bit."""
    return (_x_context(xm, ym, zm, xp, xm2), B_X + (fx1 | (fx2 << 4) | (((xp >> 8) & 1) << 8)),
            C3_X + (sx0 * 10 + sx2) * 10 + (sx1 >> 1))


@helper(inline=False)
def _mixed_y(bx, xm, ym, zm, yp, ym2, sy0, sy1, sy2, fy1, fy2):
    """The three models (A, B, C) of a single child's y bit (its x bit ``bx`` known)."""
    return (_y_context(bx, xm, ym, zm, yp, ym2), B_Y + (fy1 | (fy2 << 4) | (((yp >> 8) & 1) << 8) | (bx << 9)),
            C3_Y + ((sy0 * 10 + sy2) * 10 + (sy1 >> 1)) * 2 + bx)


@helper(inline=False)
def _mixed_single(xm, ym, zm, xp, yp, zp, xm2, ym2, sz0, sz1, sz2, fx1, fy1):
    """The three models (A, B, C) of the single-child flag (``sz*``, ``fx1``, ``fy1``: from :func:`_around`)."""
    occ = ((xm >> 8) & 1) + ((ym >> 8) & 1) + ((zm >> 8) & 1) + ((xp >> 8) & 1) + ((yp >> 8) & 1) + ((zp >> 8) & 1)
    return (_single_context(xm, ym, zm, xp, yp, zp, xm2, ym2), B_SINGLE + (fx1 * 16 + fy1) * 7 + occ,
            C3_SINGLE + (sz0 * 9 + sz1) * 10 + sz2)


@helper(inline=False)
def _sse_cell(models, axis, ca, cb, cc):
    """The secondary-estimation cell (axis 0: x, 1: y, 2: the single-child flag) of an event
    whose models are ``ca``, ``cb``, ``cc``."""
    return (((axis * SSE_N + np.int64(at(SSE_BUCKET, state_p(at(models, ca))))) * SSE_N
             + np.int64(at(SSE_BUCKET, state_p(at(models, cb))))) * SSE_N + np.int64(at(SSE_BUCKET, state_p(at(models, cc)))))


@helper(inline=False)
def _sse_next(s, bit):
    """A cell's state ``s`` adapted to ``bit``: as :func:`shared.compress._rans.state_next`,
    the rate slowing further, to 1/128 (a cell sees many events)."""
    return adapt_state(s, bit, np.int64(SSE_LIMIT))  # int64: one copy with state_next's


@helper(inline=False)
def _fixed_next(s, bit):
    """A B or C model's state (a 16-bit probability of a one) adapted to ``bit`` at the fixed
    rate 1/32 (these models only pick a bucket; the count-based rate of :func:`state_next` saves
    0.002 bits a point on the bench scan at 0.1 mm but decodes 8 % slower)."""
    p = np.int64(s)
    if bit:
        p += (P_ONE - p) >> 5
    else:
        p -= p >> 5
    return np.uint32(p)


@kernel(inline="always")
def _learn(models, sse, ca, cb, cc, cell, bit):
    """Adapt a mixed event's three models and its cell to ``bit``."""
    set_at(models, ca, state_next(at(models, ca), bit))
    set_at(models, cb, _fixed_next(at(models, cb), bit))
    set_at(models, cc, _fixed_next(at(models, cc), bit))
    set_at(sse, cell, _sse_next(at(sse, cell), bit))


@kernel(inline="always")
def _emit_mixed(tab, val, nb, n, models, sse, axis, ca, cb, cc, bit, kind):
    """Append a mixed binary event (``axis`` 0 the x bit, 1 the y bit, 2 the single-child flag)
    coded with its cell's probability and adapt; -1 when the buffers are full (``kind``: as
    :func:`_emit`)."""
    if n < 0 or n >= tab.shape[0]:
        return -1
    cell = _sse_cell(models, np.int64(axis), ca, cb, cc)
    tab[n] = BIN
    val[n] = (state_p(at(sse, cell)) << 1) | bit
    nb[n] = kind
    _learn(models, sse, ca, cb, cc, cell, bit)
    return n + 1


@kernel
def _prior_states():
    """Every model's first state, (N_MODELS,) uint32: the probability of a one of its group in
    :data:`shared.compress._octree_prior.PRIOR_P12` (16 bits), a count of zero. Built once a chunk
    (a few hundred microseconds: the table in the source is 13 k groups, not 400 k models)."""
    out = empty(N_MODELS, np.uint32)
    g = 0
    for r in range(PRIOR_SHIFTS.shape[0]):
        a = PRIOR_BOUNDS[r]
        s = PRIOR_SHIFTS[r]
        for i in range(PRIOR_BOUNDS[r + 1] - a):
            out[a + i] = np.uint32(PRIOR_P12[g + (i >> s)]) << 4
        g += ((PRIOR_BOUNDS[r + 1] - a - 1) >> s) + 1
    return out
