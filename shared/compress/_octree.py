"""Octree point-cloud chunk codec kernels (private; the public API is :mod:`shared.compress.cloud`).

Geometry: integer voxel coordinates (the cloud quantised to its precision grid, offset to
the chunk's minimum) become Morton codes; the octree is coded breadth-first, one occupancy
byte per occupied node, as in MPEG G-PCC. The byte's table (its context) is chosen by what
the decoder already knows about the node's neighbourhood: how many of its parent's eight
children are occupied, and how many of the node's three face neighbours inside the parent
are (a flat surface occupies 4 of 8 children with 2 sibling neighbours each; a corner fewer).
Points sharing a voxel are counted per voxel.

Attributes follow as integer channels in Morton order, each the difference from the previous
point (neighbours in Morton order are near in space, so the differences are small), each
channel in its own table.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from shared.compress._rans import (
    RANS_L,
    count_symbols,
    dec_init,
    decode_tables,
    encode_events,
    get_symbol,
    get_value,
    normalise,
    pack_tables,
    put,
    put_value,
    unpack_tables,
    unzigzag,
    zigzag,
)

T_OCC = 0  # 8 parent counts x 8 patterns of the three sibling face neighbours
N_OCC = 64
T_DUP = T_OCC + N_OCC
T_ATTR = T_DUP + 1
MAX_CHANNELS = 16
NTABLES = T_ATTR + MAX_CHANNELS
L_OCC = 8
L_DUP = 2
MAX_DEPTH = 21

POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.int64)
#: REFLECT[i, byte]: the occupancy byte seen from octant i (child bit b moves to b ^ i). Coding
#: every node's byte as if the node were child 0 of its parent makes the byte distributions of
#: all eight positions one (a floor's pattern looks the same from every octant), so a context's
#: table learns from eight times the nodes. Self-inverse.
REFLECT = np.array([[sum(((byte >> b) & 1) << (b ^ i) for b in range(8)) for byte in range(256)] for i in range(8)],
                   np.int64)


@njit(cache=True, nogil=True, inline="always")
def _spread(v):
    v &= 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


@njit(cache=True, nogil=True, inline="always")
def _compact(v):
    v &= 0x1249249249249249
    v = (v | (v >> 2)) & 0x10C30C30C30C30C3
    v = (v | (v >> 4)) & 0x100F00F00F00F00F
    v = (v | (v >> 8)) & 0x1F0000FF0000FF
    v = (v | (v >> 16)) & 0x1F00000000FFFF
    v = (v | (v >> 32)) & 0x1FFFFF
    return v


@njit(cache=True, nogil=True)
def morton(q):
    """Morton codes (N,) int64 of non-negative integer coordinates (N, 3) below 2**21 (x lowest)."""
    n = q.shape[0]
    out = np.empty(n, np.int64)
    for i in range(n):
        out[i] = _spread(q[i, 0]) | (_spread(q[i, 1]) << 1) | (_spread(q[i, 2]) << 2)
    return out


@njit(cache=True, nogil=True)
def unmorton(codes):
    n = codes.shape[0]
    out = np.empty((n, 3), np.int64)
    for i in range(n):
        c = codes[i]
        out[i, 0] = _compact(c)
        out[i, 1] = _compact(c >> 1)
        out[i, 2] = _compact(c >> 2)
    return out


@njit(cache=True, nogil=True, inline="always")
def _context(pbyte, idx):
    if pbyte == 0:
        return 0
    sib = ((pbyte >> (idx ^ 1)) & 1) | (((pbyte >> (idx ^ 2)) & 1) << 1) | (((pbyte >> (idx ^ 4)) & 1) << 2)
    return (POPCOUNT[pbyte] - 1) * 8 + sib


@njit(cache=True, nogil=True)
def _events(vox, counts, depth, chan, log2d, tab, val, nb):
    """Every event of one chunk: occupancy bytes level by level, duplicate counts (when any
    voxel holds more than one point), attribute channels. -1 when the buffers are too small."""
    n = 0
    nv = vox.shape[0]
    # levels bottom-up: level d holds the distinct codes >> 3 (depth - d)
    sizes = np.zeros(depth + 1, np.int64)
    starts = np.zeros(depth + 2, np.int64)
    total = 0
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
    for d in range(depth + 1):
        arr = tmp[depth - d]
        sizes[d] = arr.shape[0]
        total += arr.shape[0]
    levels = np.empty(total, np.int64)  # every level, top-down
    for d in range(depth + 1):
        arr = tmp[depth - d]
        starts[d + 1] = starts[d] + arr.shape[0]
        levels[starts[d] : starts[d + 1]] = arr
    # parent bytes of the nodes of the current level
    pb = np.zeros(1, np.int64)
    for d in range(depth):
        a0 = starts[d]
        c0 = starts[d + 1]
        c1 = starts[d + 2]
        npb = np.empty(c1 - c0, np.int64)
        j = c0
        for i in range(sizes[d]):
            key = levels[a0 + i]
            byte = 0
            j0 = j
            while j < c1 and (levels[j] >> 3) == key:
                byte |= 1 << (levels[j] & 7)
                j += 1
            for k in range(j0, j):
                npb[k - c0] = byte
            ctx = _context(pb[i], key & 7) if d > 0 else 0
            n = put(tab, val, nb, n, T_OCC + ctx, REFLECT[key & 7, byte] - 1, 0)
        pb = npb
    if n < 0:
        return -1
    dup = False
    for i in range(nv):
        if counts[i] > 1:
            dup = True
            break
    n = put(tab, val, nb, n, T_DUP, 1 if dup else 0, 0)
    if dup:
        for i in range(nv):
            n = put_value(tab, val, nb, n, T_DUP, counts[i] - 1, L_DUP)
    npts, nch = chan.shape
    for c in range(nch):
        for i in range(npts):
            n = put_value(tab, val, nb, n, T_ATTR + c, zigzag(chan[i, c]), log2d[c])
    return n


@njit(cache=True, nogil=True)
def encode_chunk(vox, counts, depth, chan, log2d):
    """Code one chunk: ``vox`` sorted distinct Morton codes, ``counts`` points per voxel,
    ``chan`` (N, C) int64 attribute differences in point order. Returns (tables, words)."""
    npts = chan.shape[0]
    cap = 2 * vox.shape[0] * 2 + npts * (chan.shape[1] + 1) + 4096
    while True:
        tab = np.empty(cap, np.int8)
        val = np.empty(cap, np.int16)
        nb = np.empty(cap, np.int8)
        n = _events(vox, counts, depth, chan, log2d, tab, val, nb)
        if n >= 0:
            break
        cap *= 4
    freq = normalise(count_symbols(tab, val, n, NTABLES))
    return pack_tables(freq), encode_events(tab, val, nb, n, freq)


@njit(cache=True, nogil=True)
def decode_chunk(tables, words, nvox, npts, depth, log2d, codes_out, chan_out):
    """Decode one chunk: the Morton codes of its ``npts`` points (sorted, repeated per
    duplicate) into ``codes_out`` and the attribute differences into ``chan_out`` (N, C).
    Returns 0, or -1 for a corrupt stream."""
    freq, used = unpack_tables(tables, NTABLES)
    nw = words.shape[0]
    if used < 0 or used != tables.shape[0] or nw < 4:
        return -1
    sym, fb = decode_tables(freq)
    xa, xb, pos = dec_init(words)
    cur = np.zeros(max(nvox, 1), np.int64)
    cpb = np.zeros(max(nvox, 1), np.int64)
    nxt = np.empty(max(nvox, 1), np.int64)
    npb = np.empty(max(nvox, 1), np.int64)
    ncur = 1
    for d in range(depth):
        m = 0
        for i in range(ncur):
            key = cur[i]
            ctx = _context(cpb[i], key & 7) if d > 0 else 0
            s, xa, xb, pos = get_symbol(xa, xb, pos, words, nw, sym, fb, T_OCC + ctx)
            if s > 254:
                return -1
            byte = REFLECT[key & 7, s + 1]
            if m + POPCOUNT[byte] > nvox:
                return -1
            for b in range(8):
                if (byte >> b) & 1:
                    nxt[m] = (key << 3) | b
                    npb[m] = byte
                    m += 1
        cur, nxt = nxt, cur
        cpb, npb = npb, cpb
        ncur = m
        if pos > nw:
            return -1
    if ncur != nvox:
        return -1
    dup, xa, xb, pos = get_symbol(xa, xb, pos, words, nw, sym, fb, T_DUP)
    k = 0
    if dup == 1:
        for i in range(nvox):
            u, xa, xb, pos = get_value(xa, xb, pos, words, nw, sym, fb, T_DUP, L_DUP)
            c = np.int64(u) + 1
            if k + c > npts or c < 1:
                return -1
            for _ in range(c):
                codes_out[k] = cur[i]
                k += 1
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
