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

# The map, contexts and models (split off by size); their constants are also read from here by
# the tests and the prior's trainer (tests/bench/train_cloud_prior.py).
from shared.compress._octree_ctx import (  # noqa: F401
    _CODED,
    _LAST_MIXED,
    _OCCUPIED,
    _ZERO_ONE,
    B_SINGLE,
    B_X,
    B_Y,
    C3_SINGLE,
    C3_X,
    C3_Y,
    C_BIT,
    C_BIT_SPAN,
    C_SINGLE,
    C_X,
    C_Y,
    C_Z,
    FLAG_MIX_LEVELS,
    LOWEST,
    MAP_ROWS,
    MIX_LEVELS,
    N_MODELS,
    N_OCC_CTX,
    N_SSE,
    ORIGIN,
    PAD,
    REGION,
    REGION_LOG,
    REGION_SHIFT,
    SSE_BUCKET,
    SSE_EDGES,
    SSE_INIT,
    SSE_INIT_COUNT,
    SSE_INIT_M,
    SSE_LIMIT,
    SSE_N,
    _around,
    _bit_context,
    _cell,
    _child_cell,
    _emit,
    _emit_mixed,
    _lean,
    _learn,
    _mark,
    _mixed_single,
    _mixed_x,
    _mixed_y,
    _neighbours,
    _prior_states,
    _single_context,
    _slab_z,
    _sse_cell,
    _x_context,
    _y_context,
    _z_context,
)
from shared.compress._rans import (
    RANS_L,
    at,
    count_symbols,
    dec_init,
    decode_tables,
    encode_events,
    get_bit,
    get_symbol,
    get_value,
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
from shared.core.jit import empty, kernel, zeros
from shared.core.morton import compact21, spread21

T_DUPF = 0  # any voxel holding more than one point?
T_DUP = 1  # 4 tables: points per voxel - 1, by the previous voxel's count (1, 2, 3, 4+)
T_ATTR = T_DUP + 4
MAX_CHANNELS = 16
NTABLES = T_ATTR + MAX_CHANNELS
L_DUP = 2
MAX_DEPTH = 21


@kernel
def morton(q):
    """Morton codes (N,) int64 of non-negative integer coordinates (N, 3) below 2**21 (x lowest)."""
    n = q.shape[0]
    out = empty(n, np.int64)
    for i in range(n):
        out[i] = spread21(q[i, 0]) | (spread21(q[i, 1]) << 1) | (spread21(q[i, 2]) << 2)
    return out


@kernel
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


# Arrays are copied by loops, not slice assignments (``a[i:j] = b``): numba links a shape
# mismatch's error message (string formatting) into every kernel holding one, 0.2 s more
# compilation each and 2.4 s once a process.
@kernel
def _restart(models, sse, prior):
    """Every model back to its prior ``prior`` and every SSE cell to its first state (a level's start)."""
    for i in range(N_MODELS):
        models[i] = prior[i]  # a copy, as cheap as the fill of 1/2 it replaces
    for k in range(3):
        for i in range(SSE_N**3):
            sse[k * SSE_N**3 + i] = SSE_INIT[i]


@kernel
def _levels(vox, depth):
    """Every level of the octree of sorted distinct codes ``vox``, top-down in one array
    (level d from ``starts[d]`` to ``starts[d + 1]``), and ``starts`` (depth + 2,)."""
    tmp = [vox.copy()]
    for _ in range(depth):
        prev = tmp[-1]
        m = 0
        nxt = empty(prev.shape[0], np.int64)
        for i in range(prev.shape[0]):
            k = prev[i] >> 3
            if m == 0 or nxt[m - 1] != k:
                nxt[m] = k
                m += 1
        tmp.append(nxt[:m])
    starts = zeros(depth + 2, np.int64)
    for d in range(depth + 1):
        starts[d + 1] = starts[d] + tmp[depth - d].shape[0]
    levels = empty(starts[depth + 1], np.int64)
    for d in range(depth + 1):
        lev = tmp[depth - d]
        for i in range(lev.shape[0]):
            levels[starts[d] + i] = lev[i]
    return levels, starts


@kernel
def _events(levels, starts, counts, depth, chan, log2d, tab, val, nb):
    """Every event of one chunk: child bits level by level, duplicate counts (when any voxel
    holds more than one point), attribute channels. -1 when the buffers are too small."""
    n = np.int64(0)  # not the literal 0: _emit is compiled for int64 alone
    cells = empty(counts.shape[0], np.int64)
    models = empty(N_MODELS, np.uint32)
    sse = empty(N_SSE, np.uint32)
    atlas = zeros(PAD * PAD * PAD, np.int16)
    rows = zeros(MAP_ROWS, np.uint64)
    prior = _prior_states()
    for d in range(depth):
        _restart(models, sse, prior)
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
            n = put_value(tab, val, nb, n, T_DUP + min(prev, 4) - 1, counts[i] - 1, L_DUP, 0)
            prev = counts[i]
    npts, nch = chan.shape
    for c in range(nch):
        for i in range(npts):
            n = put_value(tab, val, nb, n, T_ATTR + c, zigzag(chan[i, c]), log2d[c], 0)
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


@kernel
def _decode_level(words, nw, xa, xb, pos, cur, curc, ncur, nxt, nxtc, nvox, models, sse, atlas, rows, mixed_flag, mixed, last):
    """Decode one level of the octree (see :func:`decode_chunk`): the children of the ``ncur``
    nodes ``cur`` (Morton codes; map indices ``curc``) into ``nxt`` (and ``nxtc`` unless the
    level is the ``last``). Returns (children, xa, xb, pos); -1 children for a corrupt stream.
    :func:`_decode_last_level` calls it with literal flags for the last level (``False``,
    :data:`_LAST_MIXED`, ``True``): numba compiles a copy of its own for those literal values
    (the flags' branches pruned; the level that takes most of the decode gets a loop without the
    other kinds' branches and live values), and :func:`decode_chunk` one with the flags at run
    time for the levels above. Two compiled copies, not numba IR inlines
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


@kernel
def _decode_last_level(words, nw, xa, xb, pos, cur, curc, ncur, nxt, nvox, models, sse, atlas, rows):
    """:func:`_decode_level` for the last level: its flags literals (``False``,
    :data:`_LAST_MIXED`, ``True``), for the copy numba compiles for them (called from Python,
    a kernel's flags are never literals). The children are voxels: no map cells needed."""
    return _decode_level(words, nw, xa, xb, pos, cur, curc, ncur, nxt, nxt, nvox, models, sse, atlas, rows,
                         False, _LAST_MIXED, True)  # fmt: skip


def decode_chunk(tables: np.ndarray, words: np.ndarray, nvox: int, npts: int, depth: int, log2d: np.ndarray,
                 codes_out: np.ndarray, chan_out: np.ndarray) -> int:
    """Decode one chunk: ``tables`` uint8 and ``words`` uint16 (C-contiguous) as
    :func:`encode_chunk` returns them; the Morton codes of its ``npts`` points (sorted, repeated
    per duplicate) into ``codes_out`` (N,) int64 and the attribute differences into ``chan_out``
    (N, C) int64 (``log2d`` (C,) int64: their tables' direct sizes). Returns 0, or -1 for a
    corrupt stream.

    Plain Python over the kernels (each releases the GIL), a call a level: as one kernel it cost
    numba 1.5 s more to compile, linking and optimising the level decoder's two copies again."""
    freq, used = unpack_tables(tables, np.int64(NTABLES))  # int64: one signature with the range codec's
    nw = words.shape[0]
    if used < 0 or used != tables.shape[0] or nw < 4:
        return -1
    sym, fb = decode_tables(freq)
    xa, xb, pos = dec_init(words)
    size = max(nvox, 1)
    cur = np.zeros(size, np.int64)
    nxt = np.empty(size, np.int64)
    curc = np.full(size, ORIGIN, np.int64)  # map indices of the nodes
    nxtc = np.empty(size, np.int64)
    models = np.empty(N_MODELS, np.uint32)
    sse = np.empty(N_SSE, np.uint32)
    atlas = np.zeros(PAD * PAD * PAD, np.int16)
    rows = np.zeros(MAP_ROWS, np.uint64)
    ncur = 1
    prior = _prior_states()
    for d in range(depth):
        _restart(models, sse, prior)
        # The last level's flags are literals (a copy of the level loop of their own); the
        # rule below, as the encoder applies it, gives them at d = depth - 1.
        if d == depth - 1:
            m, xa, xb, pos = _decode_last_level(words, nw, xa, xb, pos, cur, curc, ncur, nxt, nvox, models, sse, atlas, rows)
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
    return _decode_tail(words, nw, xa, xb, pos, sym, fb, cur, nvox, npts, log2d, codes_out, chan_out)


@kernel
def _decode_tail(words, nw, xa, xb, pos, sym, fb, vox, nvox, npts, log2d, codes_out, chan_out):
    """What follows the octree (see :func:`decode_chunk`): the points per voxel of ``vox``
    (nvox,) into ``codes_out``, the attribute differences into ``chan_out``; 0, or -1 for a
    corrupt stream (or one that does not end where the encoder began)."""
    dup, xa, xb, pos = get_symbol(xa, xb, pos, words, nw, sym, fb, T_DUPF)
    k = 0
    if dup == 1:
        prev = 1
        for i in range(nvox):
            u, xa, xb, pos = get_value(xa, xb, pos, words, nw, sym, fb, T_DUP + min(prev, 4) - 1, L_DUP, 0)
            c = np.int64(u) + 1
            if k + c > npts or c < 1:
                return -1
            for _ in range(c):
                codes_out[k] = vox[i]
                k += 1
            prev = c
    elif dup == 0:
        if nvox != npts:
            return -1
        for i in range(npts):
            codes_out[i] = vox[i]
        k = npts
    else:
        return -1
    if k != npts:
        return -1
    nch = chan_out.shape[1]
    for c in range(nch):
        for i in range(npts):
            u, xa, xb, pos = get_value(xa, xb, pos, words, nw, sym, fb, T_ATTR + c, log2d[c], 0)
            chan_out[i, c] = unzigzag(u)
        if pos > nw:
            return -1
    if pos != nw or xa != RANS_L or xb != RANS_L:
        return -1
    return 0
