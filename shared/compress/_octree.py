"""Octree point-cloud chunk codec kernels (private; the public API is :mod:`shared.compress.cloud`).

Geometry: integer voxel coordinates (the cloud quantised to its precision grid, offset to
the chunk's minimum) become Morton codes; the octree is coded breadth-first, as in MPEG
G-PCC, every decision a binary event of an adaptive model (:func:`shared.compress._rans.state_next`)
chosen by what the decoder already knows around the node. Per occupied node:

- a flag "exactly one child" (most nodes of the deepest levels of a scan's surface), in a
  context of its occupied face neighbours, the children of its past neighbours (-x, -y, -z:
  coded before it, Morton order being monotonic along every axis) and the occupancy of the
  nodes two back along x and y;
- one child: its x, y and z bits, each in a context of where the past neighbours' children
  lie along that axis (and the nodes two back: the spacing of a scan's points shows there),
  whether the future neighbour on that axis is occupied, and the bits already coded; the z
  bit also sees whether the surface climbs or falls (the past x neighbour's own neighbours
  above and below, and which of the slabs above and below the node holds more of the 26 nodes
  around);
- two children or more: the eight child bits one by one (bit ``b = x + 2 y + 4 z``; the last
  ones implied when the count demands them), each in a context of the child's three past
  neighbours at the child's level (a sibling already coded, or a child of the past
  neighbour), the cells two steps back, the future face neighbours at the node's level and
  the side of the node the child lies on, the siblings occupied so far, the bit's position and
  whether more than one node of the slab on the child's side along z is occupied.

In the last two levels (:data:`MIX_LEVELS`), where a scan's points are one per node or two and
about two thirds of the bits go, a single child's x and y bits, the least random there, are each coded
by three models mixed by secondary estimation (:func:`_sse_cell`): the context above (A); the
footprints of the columns one and two back along the axis, the past neighbours' children seen
along z (B: a noisy surface scatters a scan's row over the z neighbours, which the face
neighbours miss); the occupied nodes of the 26 around counted per slab (C: the side the
surface goes on). The three probabilities, in buckets of log-odds, pick an adaptive cell that
codes the bit. In the FLAG_MIX_LEVELS levels above the last the single-child flag is mixed alike:
its context (A), the footprints at x - 1 and y - 1 with the occupied face neighbours (B), the
nodes of the 26 around counted per slab along z (C). (Mixing every event of every level took
the bench's scan at a 0.1 mm grid to 6.46 bits a point, against 6.75 so, but 2.2 times as
long to decode; the last level's x and y bits carry half of the gain at a sixth of that cost,
the flags of the two levels above a quarter of the rest at a few per cent more (those of a third
level, now mixed too, 0.001 bits more: their nodes are few); the x and y bits of the level above
the last another 0.05 bits (6.594 -> 6.543 on that scan, 6.761 -> 6.520
on the bunny's) at 3 % more decoding time, once the slab counts are computed once a node and
the buckets are a byte table. A third level of mixed x and y bits saves 0.0015 more, a fourth of
flags 0.0004.)

Neighbours are looked up in a dense map of the nodes of a 64^3-node region (the nodes
sharing an ancestor six levels up, consecutive in Morton order); a neighbour outside the
region counts as empty, in encoder and decoder alike; the region's occupancy is also kept as
one bit row (uint64) per row along x, for the slab counts. Models restart at every level, from
a prior probability trained offline (:mod:`shared.compress._octree_prior`; 0.007 bits a point fewer
on the bench scan at 0.1 mm than from 1/2). The
decoder loads every model (and cell) a node may use before the bits that choose among them are known,
so that the loads leave the decoding's dependency chain. Points sharing a voxel are counted
per voxel (in a table chosen by the previous voxel's count).

Attributes follow as integer channels in Morton order, each the difference from the previous
point (neighbours in Morton order are near in space, so the differences are small), each
channel in its own table.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from shared.compress._octree_prior import PRIOR_BOUNDS, PRIOR_P12, PRIOR_SHIFTS
from shared.compress._rans import (
    BIN,
    P_ONE,
    RANS_L,
    adapt_state,
    at,
    count_symbols,
    dec_init,
    decode_tables,
    encode_events,
    get_bit,
    get_symbol,
    get_value,
    model_p,
    model_update,
    normalise,
    pack_tables,
    put,
    put_value,
    set_at,
    state_next,
    state_p,
    unpack_tables,
    unzigzag,
    zigzag,
)
from shared.core.bits import popcount
from shared.core.morton import compact21, spread21

T_DUPF = 0  # any voxel holding more than one point?
T_DUP = 1  # 4 tables: points per voxel - 1, by the previous voxel's count (1, 2, 3, 4+)
T_ATTR = T_DUP + 4
MAX_CHANNELS = 16
NTABLES = T_ATTR + MAX_CHANNELS
L_DUP = 2
MAX_DEPTH = 21
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


@njit(cache=True, nogil=True)
def morton(q):
    """Morton codes (N,) int64 of non-negative integer coordinates (N, 3) below 2**21 (x lowest)."""
    n = q.shape[0]
    out = np.empty(n, np.int64)
    for i in range(n):
        out[i] = spread21(q[i, 0]) | (spread21(q[i, 1]) << 1) | (spread21(q[i, 2]) << 2)
    return out


@njit(cache=True, nogil=True)
def voxel_centres(codes, ox, oy, oz, precision, x, y, z):
    """The centres of the voxels of Morton codes ``codes`` (N,) int64, offset by the chunk's
    minimum voxel (``ox``, ``oy``, ``oz``) on the grid of step ``precision``, written into ``x``,
    ``y``, ``z`` (N,) (float, any stride: the fields of the output records). The same float64
    arithmetic as ``(q + o + 0.5) * precision`` in numpy, in one pass without temporaries."""
    for i in range(codes.shape[0]):
        c = codes[i]
        x[i] = (compact21(c) + ox + 0.5) * precision
        y[i] = (compact21(c >> 1) + oy + 0.5) * precision
        z[i] = (compact21(c >> 2) + oz + 0.5) * precision


# The scalar helpers below (contexts, cells, counter steps, the SSE cell, the map's marks, and
# the rANS coder's at/set_at/get_bit/state_* they call) are plain kernels, inlined by LLVM when
# their callers are optimised; numba's own inlining (inline="always") re-reads the callee's
# bytecode and deep-copies its IR at every call site (hundreds of copies of ``at`` alone):
# dropping it took the cloud codec's compilation from 81 s to 28 s, for no speed (A/B in the
# commits). Inlined by numba still: _bit_context (the decoder's innermost loop), and _around,
# _learn, _emit, _emit_mixed, which LLVM leaves as calls in the encoder or the decoder.
@njit(cache=True, nogil=True)
def _cell(key):
    """Index of a node in its region's map."""
    c = key & ((1 << REGION_SHIFT) - 1)
    return ORIGIN + (compact21(c >> 2) * PAD + compact21(c >> 1)) * PAD + compact21(c)


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _neighbours(atlas, ci):
    """The region map's values of the node's face neighbours (0 outside the region) -x, -y,
    -z, +x, +y, +z, of the nodes two back along x and y, and the occupancy of the past x and y
    neighbours' neighbours above and below (4 bits: where the surface climbs or falls)."""
    return (np.int64(at(atlas, ci - 1)), np.int64(at(atlas, ci - PAD)), np.int64(at(atlas, ci - PAD * PAD)),
            np.int64(at(atlas, ci + 1)), np.int64(at(atlas, ci + PAD)), np.int64(at(atlas, ci + PAD * PAD)),
            np.int64(at(atlas, ci - 2)), np.int64(at(atlas, ci - 2 * PAD)),
            ((at(atlas, ci - 1 + PAD * PAD) >> 8) & 1) | (((at(atlas, ci - 1 - PAD * PAD) >> 8) & 1) << 1)
            | (((at(atlas, ci - PAD + PAD * PAD) >> 8) & 1) << 2) | (((at(atlas, ci - PAD - PAD * PAD) >> 8) & 1) << 3))


@njit(cache=True, nogil=True, inline="always")
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


@njit(cache=True, nogil=True)
def _slab_z(sz0, sz2):
    """Whether more than one of the nine nodes of the slab below a node are occupied (bit 0;
    ``sz0`` of :func:`_around`) and of the slab above (bit 1, ``sz2``): the side of the node the
    surface lies on, for its child bits (a noisy scan's surface crosses neighbours that the face
    and past-neighbour contexts do not see). (0, 1-2, 3-4, 5+ each: 0.0025 bits a point more on
    the bench scan at 0.1 mm, 0.008 fewer on the bunny's, for twice the contexts; more than two
    or three rather than one: 0.0007 and 0.004 more.)"""
    return (1 if sz0 > 1 else 0) | ((1 if sz2 > 1 else 0) << 1)


@njit(cache=True, nogil=True)
def _lean(sz0, sz2):
    """Which slab holds more of the 26 nodes around a node: 1 the one above (``sz2`` of
    :func:`_around`), 2 the one below (``sz0``), 0 neither; for the single child's z bit
    (:func:`_z_context`)."""
    return (1 if sz2 > sz0 else 0) | ((1 if sz0 > sz2 else 0) << 1)


@njit(cache=True, nogil=True)
def _any(v, mask):
    # Callers pass the mask as np.int64(...), not a literal: numba compiles a copy of a kernel
    # per literal argument value (nine copies of this one before).
    return np.int64((v & mask) != 0)


@njit(cache=True, nogil=True)
def _single_context(xm, ym, zm, xp, yp, zp, xm2, ym2):
    """Context of "the node has exactly one child": occupied face neighbours (0-6) x the
    children of the past neighbours (0-7+) x whether the nodes two back along x and y are occupied."""
    occ = ((xm >> 8) & 1) + ((ym >> 8) & 1) + ((zm >> 8) & 1) + ((xp >> 8) & 1) + ((yp >> 8) & 1) + ((zp >> 8) & 1)
    kids = min(popcount((xm & 255) | ((ym & 255) << 8) | ((zm & 255) << 16)), 7)
    return C_SINGLE + ((occ * 8 + kids) * 2 + ((xm2 >> 8) & 1)) * 2 + ((ym2 >> 8) & 1)


@njit(cache=True, nogil=True)
def _x_context(xm, ym, zm, xp, xm2):
    """Context of a single child's x bit: where the past neighbours' children lie along x."""
    return C_X + (_any(xm, np.int64(0xAA)) | (_any(xm, np.int64(0x55)) << 1) | (((xp >> 8) & 1) << 2) | (_any(ym, np.int64(0xAA)) << 3)
                  | (_any(ym, np.int64(0x55)) << 4) | (_any(zm, np.int64(0xAA)) << 5) | (_any(zm, np.int64(0x55)) << 6)
                  | (_any(xm2, np.int64(0xAA)) << 7) | (_any(xm2, np.int64(0x55)) << 8))


@njit(cache=True, nogil=True)
def _y_context(bx, xm, ym, zm, yp, ym2):
    """Context of a single child's y bit (its x bit ``bx`` known)."""
    return C_Y + (_any(ym, 0x44 << bx) | (_any(ym, 0x11 << bx) << 1) | (((yp >> 8) & 1) << 2)
                  | (_any(xm, np.int64(0x22)) << 3) | (_any(xm, np.int64(0x88)) << 4) | (((zm >> (4 | bx)) & 1) << 5)
                  | (((zm >> (6 | bx)) & 1) << 6) | (bx << 7) | (_any(ym2, np.int64(0xCC)) << 8) | (_any(ym2, np.int64(0x33)) << 9))


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _lat(v):
    """The footprint of a map value's children seen along z: 4 bits, bit ``x + 2 y``."""
    v = np.int64(v)
    return (v | (v >> 4)) & 15


@njit(cache=True, nogil=True, inline="always")
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


@njit(cache=True, nogil=True)
def _mark(atlas, rows, ci, on):
    """Mark the node at map index ``ci`` occupied (``on``) or empty, in the map and its bit rows."""
    r = ci // PAD
    if on:
        set_at(atlas, ci, _OCCUPIED)
        set_at(rows, r, at(rows, r) | (np.uint64(1) << np.uint64(ci - r * PAD - 1)))
    else:
        set_at(atlas, ci, 0)
        set_at(rows, r, 0)


@njit(cache=True, nogil=True)
def _mixed_x(xm, ym, zm, xp, xm2, sx0, sx1, sx2, fx1, fx2):
    """The three models (A, B, C) of a single child's x bit."""
    return (_x_context(xm, ym, zm, xp, xm2), B_X + (fx1 | (fx2 << 4) | (((xp >> 8) & 1) << 8)),
            C3_X + (sx0 * 10 + sx2) * 10 + (sx1 >> 1))


@njit(cache=True, nogil=True)
def _mixed_y(bx, xm, ym, zm, yp, ym2, sy0, sy1, sy2, fy1, fy2):
    """The three models (A, B, C) of a single child's y bit (its x bit ``bx`` known)."""
    return (_y_context(bx, xm, ym, zm, yp, ym2), B_Y + (fy1 | (fy2 << 4) | (((yp >> 8) & 1) << 8) | (bx << 9)),
            C3_Y + ((sy0 * 10 + sy2) * 10 + (sy1 >> 1)) * 2 + bx)


@njit(cache=True, nogil=True)
def _mixed_single(xm, ym, zm, xp, yp, zp, xm2, ym2, sz0, sz1, sz2, fx1, fy1):
    """The three models (A, B, C) of the single-child flag (``sz*``, ``fx1``, ``fy1``: from :func:`_around`)."""
    occ = ((xm >> 8) & 1) + ((ym >> 8) & 1) + ((zm >> 8) & 1) + ((xp >> 8) & 1) + ((yp >> 8) & 1) + ((zp >> 8) & 1)
    return (_single_context(xm, ym, zm, xp, yp, zp, xm2, ym2), B_SINGLE + (fx1 * 16 + fy1) * 7 + occ,
            C3_SINGLE + (sz0 * 9 + sz1) * 10 + sz2)


@njit(cache=True, nogil=True)
def _sse_cell(models, axis, ca, cb, cc):
    """The secondary-estimation cell (axis 0: x, 1: y, 2: the single-child flag) of an event
    whose models are ``ca``, ``cb``, ``cc``."""
    return (((axis * SSE_N + np.int64(at(SSE_BUCKET, state_p(at(models, ca))))) * SSE_N
             + np.int64(at(SSE_BUCKET, state_p(at(models, cb))))) * SSE_N + np.int64(at(SSE_BUCKET, state_p(at(models, cc)))))


@njit(cache=True, nogil=True)
def _sse_next(s, bit):
    """A cell's state ``s`` adapted to ``bit``: as :func:`shared.compress._rans.state_next`,
    the rate slowing further, to 1/128 (a cell sees many events)."""
    return adapt_state(s, bit, SSE_LIMIT)


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True, inline="always")
def _learn(models, sse, ca, cb, cc, cell, bit):
    """Adapt a mixed event's three models and its cell to ``bit``."""
    set_at(models, ca, state_next(at(models, ca), bit))
    set_at(models, cb, _fixed_next(at(models, cb), bit))
    set_at(models, cc, _fixed_next(at(models, cc), bit))
    set_at(sse, cell, _sse_next(at(sse, cell), bit))


@njit(cache=True, nogil=True, inline="always")
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


@njit(cache=True, nogil=True)
def _prior_states():
    """Every model's first state, (N_MODELS,) uint32: the probability of a one of its group in
    :data:`shared.compress._octree_prior.PRIOR_P12` (16 bits), a count of zero. Built once a chunk
    (a few hundred microseconds: the table in the source is 13 k groups, not 400 k models)."""
    out = np.empty(N_MODELS, np.uint32)
    g = 0
    for r in range(PRIOR_SHIFTS.shape[0]):
        a = PRIOR_BOUNDS[r]
        s = PRIOR_SHIFTS[r]
        for i in range(PRIOR_BOUNDS[r + 1] - a):
            out[a + i] = np.uint32(PRIOR_P12[g + (i >> s)]) << 4
        g += ((PRIOR_BOUNDS[r + 1] - a - 1) >> s) + 1
    return out


@njit(cache=True, nogil=True)
def _levels(vox, depth):
    """Every level of the octree of sorted distinct codes ``vox``, top-down in one array
    (level d from ``starts[d]`` to ``starts[d + 1]``), and ``starts`` (depth + 2,)."""
    tmp = [vox.copy()]
    for _ in range(depth):
        prev = tmp[-1]
        m = 0
        nxt = np.empty(prev.shape[0], np.int64)
        for i in range(prev.shape[0]):
            k = prev[i] >> 3
            if m == 0 or nxt[m - 1] != k:
                nxt[m] = k
                m += 1
        tmp.append(nxt[:m])
    starts = np.zeros(depth + 2, np.int64)
    for d in range(depth + 1):
        starts[d + 1] = starts[d] + tmp[depth - d].shape[0]
    levels = np.empty(starts[depth + 1], np.int64)
    for d in range(depth + 1):
        levels[starts[d] : starts[d + 1]] = tmp[depth - d]
    return levels, starts


@njit(cache=True, nogil=True)
def _events(levels, starts, counts, depth, chan, log2d, tab, val, nb):
    """Every event of one chunk: child bits level by level, duplicate counts (when any voxel
    holds more than one point), attribute channels. -1 when the buffers are too small."""
    n = 0
    cells = np.empty(counts.shape[0], np.int64)
    models = np.empty(N_MODELS, np.uint32)
    sse = np.empty(N_SSE, np.uint32)
    atlas = np.zeros(PAD * PAD * PAD, np.int16)
    rows = np.zeros(MAP_ROWS, np.uint64)
    prior = _prior_states()
    for d in range(depth):
        models[:] = prior  # a copy, as cheap as the fill of 1/2 it replaces
        for k in range(3):
            sse[k * SSE_N**3 : (k + 1) * SSE_N**3] = SSE_INIT
        mixed = d >= depth - MIX_LEVELS
        mixed_flag = depth - 1 - FLAG_MIX_LEVELS <= d < depth - 1
        a0 = starts[d]
        a1 = starts[d + 1]
        c1 = starts[d + 2]
        j = a1
        r0 = a0
        while r0 < a1:
            reg = levels[r0] >> REGION_SHIFT
            r1 = r0
            while r1 < a1 and (levels[r1] >> REGION_SHIFT) == reg:
                cells[r1 - a0] = _cell(levels[r1])
                _mark(atlas, rows, cells[r1 - a0], True)
                r1 += 1
            for i in range(r0, r1):
                key = levels[i]
                ci = cells[i - a0]
                byte = 0
                while j < c1 and (levels[j] >> 3) == key:
                    byte |= 1 << (levels[j] & 7)
                    j += 1
                xm, ym, zm, xp, yp, zp, xm2, ym2, slope = _neighbours(atlas, ci)
                single = popcount(byte) == 1
                sx0, sx1, sx2, sy0, sy1, sy2, sz0, sz1, sz2, fx1, fy1, fx2, fy2 = _around(atlas, rows, ci)
                slabs = _slab_z(sz0, sz2)
                lean = _lean(sz0, sz2)
                if mixed_flag:
                    ca, cb, cc = _mixed_single(xm, ym, zm, xp, yp, zp, xm2, ym2, sz0, sz1, sz2, fx1, fy1)
                    n = _emit_mixed(tab, val, nb, n, models, sse, np.int64(2), ca, cb, cc, 1 if single else 0, np.int64(0))
                else:
                    n = _emit(tab, val, nb, n, models, _single_context(xm, ym, zm, xp, yp, zp, xm2, ym2), 1 if single else 0, np.int64(0))
                if single:
                    bx = 1 if byte & 0xAA else 0
                    by = 1 if byte & 0xCC else 0
                    bz = 1 if byte & 0xF0 else 0
                    if mixed:
                        ca, cb, cc = _mixed_x(xm, ym, zm, xp, xm2, sx0, sx1, sx2, fx1, fx2)
                        n = _emit_mixed(tab, val, nb, n, models, sse, np.int64(0), ca, cb, cc, bx, np.int64(1))
                        ca, cb, cc = _mixed_y(bx, xm, ym, zm, yp, ym2, sy0, sy1, sy2, fy1, fy2)
                        n = _emit_mixed(tab, val, nb, n, models, sse, np.int64(1), ca, cb, cc, by, np.int64(2))
                    else:
                        n = _emit(tab, val, nb, n, models, _x_context(xm, ym, zm, xp, xm2), bx, np.int64(1))
                        n = _emit(tab, val, nb, n, models, _y_context(bx, xm, ym, zm, yp, ym2), by, np.int64(2))
                    n = _emit(tab, val, nb, n, models, _z_context(bx, by, xm, ym, zm, zp, xm2, ym2, np.int64(slope), lean), bz, np.int64(3))
                else:
                    cur = 0
                    ncur = 0
                    for b in range(7):
                        if ncur == 0 and b == 6:
                            break  # implied: bits 6 and 7 (two children at least)
                        ctx = _bit_context(b, cur, ncur, xm, ym, zm, xp, yp, zp, slabs)
                        bit = (byte >> b) & 1
                        n = _emit(tab, val, nb, n, models, ctx, bit, np.int64(4))
                        cur |= bit << b
                        ncur += bit
                    if ncur >= 2:  # else implied: bits 6 and 7, or bit 7 (two children at least)
                        ctx = _bit_context(7, cur, ncur, xm, ym, zm, xp, yp, zp, slabs)
                        n = _emit(tab, val, nb, n, models, ctx, (byte >> 7) & 1, np.int64(4))
                set_at(atlas, ci, _OCCUPIED | _CODED | byte)
            for i in range(r0, r1):
                _mark(atlas, rows, cells[i - a0], False)
            r0 = r1
    nv = counts.shape[0]
    dup = False
    for i in range(nv):
        if counts[i] > 1:
            dup = True
            break
    n = put(tab, val, nb, n, T_DUPF, 1 if dup else 0, 0)
    if dup:
        prev = 1
        for i in range(nv):
            n = put_value(tab, val, nb, n, T_DUP + min(prev, 4) - 1, counts[i] - 1, L_DUP)
            prev = counts[i]
    npts, nch = chan.shape
    for c in range(nch):
        for i in range(npts):
            n = put_value(tab, val, nb, n, T_ATTR + c, zigzag(chan[i, c]), log2d[c])
    return n


def encode_chunk(vox: np.ndarray, counts: np.ndarray, depth: int, chan: np.ndarray,
                 log2d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Code one chunk: ``vox`` (V,) int64 sorted distinct Morton codes, ``counts`` (V,) int64
    points per voxel, ``chan`` (N, C) int64 attribute differences in point order, ``log2d``
    (C,) int64 their tables' direct sizes. Returns (tables uint8, words uint16).

    Plain Python over the kernels (each releases the GIL): as a kernel of its own it cost numba
    2 s to compile (its module links and optimises every kernel it calls again), for six calls a chunk."""
    levels, starts = _levels(vox, np.int64(depth))
    npts = chan.shape[0]
    cap = int(8 * starts[depth] + 2 * vox.shape[0] + 2 * npts * chan.shape[1] + 4096)
    while True:
        tab = np.empty(cap, np.int8)
        val = np.empty(cap, np.int16)
        nb = np.empty(cap, np.int8)
        n = _events(levels, starts, counts, np.int64(depth), chan, log2d, tab, val, nb)
        if n >= 0:
            break
        cap *= 4
    freq = normalise(count_symbols(tab, val, n, NTABLES))
    return pack_tables(freq), encode_events(tab, val, nb, n, freq)


@njit(cache=True, nogil=True)
def _decode_level(words, nw, xa, xb, pos, cur, curc, ncur, nxt, nxtc, nvox, models, sse, atlas, rows, mixed_flag, mixed, last):
    """Decode one level of the octree (see :func:`decode_chunk`): the children of the ``ncur``
    nodes ``cur`` (Morton codes; map indices ``curc``) into ``nxt`` (and ``nxtc`` unless the
    level is the ``last``). Returns (children, xa, xb, pos); -1 children for a corrupt stream.
    :func:`decode_chunk` calls it with literal flags for the last level (``False``,
    :data:`_LAST_MIXED`, ``True``): numba compiles a copy of its own for those literal values
    (the flags' branches pruned; the level that takes most of the decode gets a loop without the
    other kinds' branches and live values), and one with the flags at run time (``last`` the
    literal ``False``) for the levels above. Two compiled copies, not numba IR inlines
    (``inline="always"``) into two wrappers: numba deep-copies an inlined function's IR block
    by block, each time with its whole variable scope (quadratic in the size of this loop)."""
    # int64 values, not literals: the context helpers are compiled once, not once a literal
    # value (LLVM folds the constant loads after inlining them)
    zero = _ZERO_ONE[0]
    one = _ZERO_ONE[1]
    m = 0
    r0 = 0
    while r0 < ncur:
        reg = cur[r0] >> REGION_SHIFT
        r1 = r0
        while r1 < ncur and (cur[r1] >> REGION_SHIFT) == reg:
            _mark(atlas, rows, curc[r1], True)
            r1 += 1
        for i in range(r0, r1):
            key = cur[i]
            ci = curc[i]
            xm, ym, zm, xp, yp, zp, xm2, ym2, slope = _neighbours(atlas, ci)
            # Every model (and cell) this node may use next is loaded before the bit that
            # picks it is known: the loads leave the decoding's dependency chain.
            sx0, sx1, sx2, sy0, sy1, sy2, sz0, sz1, sz2, fx1, fy1, fx2, fy2 = _around(atlas, rows, ci)
            slabs = _slab_z(sz0, sz2)
            lean = _lean(sz0, sz2)
            if mixed_flag:
                cs, cbs, ccs = _mixed_single(xm, ym, zm, xp, yp, zp, xm2, ym2, sz0, sz1, sz2, fx1, fy1)
                cfs = _sse_cell(models, np.int64(2), cs, cbs, ccs)
                ss = at(sse, cfs)
            else:
                cs = _single_context(xm, ym, zm, xp, yp, zp, xm2, ym2)
                cbs = ccs = cfs = 0
                ss = at(models, cs)
            if mixed:
                # x and y: three models each and their cell (x and y have a table each: the x
                # event changes no y cell)
                cax, cbx, ccx = _mixed_x(xm, ym, zm, xp, xm2, sx0, sx1, sx2, fx1, fx2)
                cay0, cby0, ccy0 = _mixed_y(zero, xm, ym, zm, yp, ym2, sy0, sy1, sy2, fy1, fy2)
                cay1, cby1, ccy1 = _mixed_y(one, xm, ym, zm, yp, ym2, sy0, sy1, sy2, fy1, fy2)
                cx = _sse_cell(models, np.int64(0), cax, cbx, ccx)
                cy0 = _sse_cell(models, np.int64(1), cay0, cby0, ccy0)
                cy1 = _sse_cell(models, np.int64(1), cay1, cby1, ccy1)
                sx = at(sse, cx)
                sy0 = at(sse, cy0)
                sy1 = at(sse, cy1)
            else:
                cax = cbx = ccx = cay0 = cby0 = ccy0 = cay1 = cby1 = ccy1 = 0
                cx = _x_context(xm, ym, zm, xp, xm2)
                cy0 = _y_context(zero, xm, ym, zm, yp, ym2)
                cy1 = _y_context(one, xm, ym, zm, yp, ym2)
                sx = at(models, cx)
                sy0 = at(models, cy0)
                sy1 = at(models, cy1)
            single, xa, xb, pos = get_bit(xa, xb, pos, words, nw, state_p(ss))
            if mixed_flag:
                # the flag's models and cell are none of the x and y bits' (loaded above)
                _learn(models, sse, cs, cbs, ccs, cfs, single)
            else:
                set_at(models, cs, state_next(ss, single))
            if single:
                czs = (_z_context(zero, zero, xm, ym, zm, zp, xm2, ym2, np.int64(slope), lean),
                       _z_context(one, zero, xm, ym, zm, zp, xm2, ym2, np.int64(slope), lean),
                       _z_context(zero, one, xm, ym, zm, zp, xm2, ym2, np.int64(slope), lean),
                       _z_context(one, one, xm, ym, zm, zp, xm2, ym2, np.int64(slope), lean))
                sz = (at(models, czs[0]), at(models, czs[1]), at(models, czs[2]), at(models, czs[3]))
                bx, xa, xb, pos = get_bit(xa, xb, pos, words, nw, state_p(sx))
                by, xa, xb, pos = get_bit(xa, xb, pos, words, nw, state_p(sy1 if bx else sy0))
                if mixed:
                    _learn(models, sse, cax, cbx, ccx, cx, bx)
                    if bx:
                        _learn(models, sse, cay1, cby1, ccy1, cy1, by)
                    else:
                        _learn(models, sse, cay0, cby0, ccy0, cy0, by)
                else:
                    set_at(models, cx, state_next(sx, bx))
                    if bx:
                        set_at(models, cy1, state_next(sy1, by))
                    else:
                        set_at(models, cy0, state_next(sy0, by))
                col = bx | (by << 1)
                cz = czs[col]
                s_z = sz[col]
                bz, xa, xb, pos = get_bit(xa, xb, pos, words, nw, state_p(s_z))
                set_at(models, cz, state_next(s_z, bz))
                byte = 1 << (col | (bz << 2))
                nset = 1
            else:
                byte = 0
                nset = 0
                c_next = _bit_context(0, 0, 0, xm, ym, zm, xp, yp, zp, slabs)
                s_next = at(models, c_next)
                for b in range(7):
                    if nset == 0 and b == 6:
                        break
                    ctx = c_next
                    st = s_next
                    # the next bit's two possible contexts (this bit 0 or 1), loaded now
                    c0 = _bit_context(b + 1, byte, nset, xm, ym, zm, xp, yp, zp, slabs)
                    c1 = _bit_context(b + 1, byte | (1 << b), nset + 1, xm, ym, zm, xp, yp, zp, slabs)
                    s0 = at(models, c0)
                    s1 = at(models, c1)
                    bit, xa, xb, pos = get_bit(xa, xb, pos, words, nw, state_p(st))
                    set_at(models, ctx, state_next(st, bit))
                    byte |= bit << b
                    nset += bit
                    c_next = c1 if bit else c0
                    s_next = s1 if bit else s0
                if nset >= 2:
                    bit, xa, xb, pos = get_bit(xa, xb, pos, words, nw, state_p(s_next))
                    set_at(models, c_next, state_next(s_next, bit))
                    byte |= bit << 7
                    nset += bit
                elif nset == 1:
                    byte |= 0x80
                    nset = 2
                else:
                    byte |= 0xC0
                    nset = 2
            if m + nset > nvox:
                return -1, xa, xb, pos
            rest = byte
            while rest:
                b = at(LOWEST, rest)
                rest &= rest - 1
                nxt[m] = (key << 3) | b
                if not last:
                    nxtc[m] = _child_cell(ci, b)
                m += 1
            set_at(atlas, ci, _OCCUPIED | _CODED | byte)
        for i in range(r0, r1):
            _mark(atlas, rows, curc[i], False)
        r0 = r1
    return m, xa, xb, pos


@njit(cache=True, nogil=True)
def decode_chunk(tables, words, nvox, npts, depth, log2d, codes_out, chan_out):
    """Decode one chunk: the Morton codes of its ``npts`` points (sorted, repeated per
    duplicate) into ``codes_out`` and the attribute differences into ``chan_out`` (N, C).
    Returns 0, or -1 for a corrupt stream."""
    freq, used = unpack_tables(tables, np.int64(NTABLES))  # int64: one signature with the range codec's
    nw = words.shape[0]
    if used < 0 or used != tables.shape[0] or nw < 4:
        return -1
    sym, fb = decode_tables(freq)
    xa, xb, pos = dec_init(words)
    cur = np.zeros(max(nvox, 1), np.int64)
    nxt = np.empty(max(nvox, 1), np.int64)
    curc = np.full(max(nvox, 1), ORIGIN, np.int64)  # map indices of the nodes
    nxtc = np.empty(max(nvox, 1), np.int64)
    models = np.empty(N_MODELS, np.uint32)
    sse = np.empty(N_SSE, np.uint32)
    atlas = np.zeros(PAD * PAD * PAD, np.int16)
    rows = np.zeros(MAP_ROWS, np.uint64)
    ncur = np.int64(1)  # not the literal 1: the level function is compiled for int64 alone
    prior = _prior_states()
    for d in range(depth):
        models[:] = prior  # a copy, as cheap as the fill of 1/2 it replaces
        for k in range(3):
            sse[k * SSE_N**3 : (k + 1) * SSE_N**3] = SSE_INIT
        # The last level's flags are literals (a copy of the level loop of their own); the
        # rule below, as the encoder applies it, gives them at d = depth - 1.
        if d == depth - 1:  # the children are voxels: no map cells needed
            m, xa, xb, pos = _decode_level(words, nw, xa, xb, pos, cur, curc, ncur, nxt, nxt, nvox, models, sse,
                                           atlas, rows, False, _LAST_MIXED, True)  # fmt: skip
        else:
            mixed = d >= depth - MIX_LEVELS
            mixed_flag = depth - 1 - FLAG_MIX_LEVELS <= d < depth - 1
            m, xa, xb, pos = _decode_level(words, nw, xa, xb, pos, cur, curc, ncur, nxt, nxtc, nvox, models, sse,
                                           atlas, rows, mixed_flag, mixed, False)  # fmt: skip
        if m < 0:
            return -1
        cur, nxt = nxt, cur
        curc, nxtc = nxtc, curc
        ncur = m
        if pos > nw:
            return -1
    if ncur != nvox:
        return -1
    dup, xa, xb, pos = get_symbol(xa, xb, pos, words, nw, sym, fb, T_DUPF)
    k = 0
    if dup == 1:
        prev = 1
        for i in range(nvox):
            u, xa, xb, pos = get_value(xa, xb, pos, words, nw, sym, fb, T_DUP + min(prev, 4) - 1, L_DUP)
            c = np.int64(u) + 1
            if k + c > npts or c < 1:
                return -1
            for _ in range(c):
                codes_out[k] = cur[i]
                k += 1
            prev = c
    elif dup == 0:
        if nvox != npts:
            return -1
        codes_out[:npts] = cur[:npts]
        k = npts
    else:
        return -1
    if k != npts:
        return -1
    nch = chan_out.shape[1]
    for c in range(nch):
        for i in range(npts):
            u, xa, xb, pos = get_value(xa, xb, pos, words, nw, sym, fb, T_ATTR + c, log2d[c])
            chan_out[i, c] = unzigzag(u)
        if pos > nw:
            return -1
    if pos != nw or xa != RANS_L or xb != RANS_L:
        return -1
    return 0
