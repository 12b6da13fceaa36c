"""The numba kernels of the Potree tile build (:mod:`shared.render.octree` drives them): Morton
codes, the passes' scans, counts and distribution, and the nodes' sampling."""

from __future__ import annotations

import numba
import numpy as np

from shared.core.jit import empty, full, zeros
from shared.core.morton import spread21

MORTON_BITS = 21  # bits an axis in a 63-bit Morton code
GRID_LEVELS = 7  # 2**7 = 128 cells a side: node spacing = node cube / 128


@numba.njit(cache=True, inline="always")
def _morton3(qx: np.int64, qy: np.int64, qz: np.int64, scale: float, top: np.int64) -> np.int64:
    """Morton code of one integer position; ``scale`` = 2**21 / qsize, ``top`` = 2**21 - 1."""
    mx = min(np.int64(qx * scale), top)
    my = min(np.int64(qy * scale), top)
    mz = min(np.int64(qz * scale), top)
    return (spread21(mx) << 2) | (spread21(my) << 1) | spread21(mz)


@numba.njit(cache=True, inline="always")
def _quantise1(v: float, offset: float, inv: float, top: np.int64) -> np.int64:
    """One coordinate to its integer step, clamped to ``[0, top]``."""
    return min(max(np.int64(np.floor((np.float64(v) - offset) * inv + 0.5)), 0), top)


@numba.njit(cache=True, nogil=True)
def morton_codes(ipos: np.ndarray, qsize: int) -> np.ndarray:
    """Morton codes of integer positions.

    Parameters
    ----------
    ipos : (N, 3) int32 positions in ``[0, qsize)``.
    qsize : edge of the cube in integer steps.

    Returns
    -------
    (N,) int64 codes, 3 x 21 bits, x the most significant bit of every triple (Potree order).
    """
    n = ipos.shape[0]
    out = empty(n, np.int64)
    scale = (1 << MORTON_BITS) / qsize
    top = np.int64((1 << MORTON_BITS) - 1)
    for i in range(n):
        out[i] = _morton3(np.int64(ipos[i, 0]), np.int64(ipos[i, 1]), np.int64(ipos[i, 2]), scale, top)
    return out


@numba.njit(cache=True, nogil=True)
def _count_unassigned(assigned: np.ndarray, lo: int, hi: int) -> int:
    c = 0
    for i in range(lo, hi):
        if assigned[i] < 0:
            c += 1
    return c


@numba.njit(cache=True, nogil=True)
def _sample(codes: np.ndarray, assigned: np.ndarray, lo: int, hi: int, shift: int, node: int) -> int:
    """Give ``node`` the first unassigned point of every cell (``code >> shift``) in [lo, hi)."""
    last = np.int64(-1)
    taken = 0
    for i in range(lo, hi):
        if assigned[i] < 0:
            key = codes[i] >> shift
            if key != last:
                assigned[i] = node
                last = key
                taken += 1
    return taken


@numba.njit(cache=True, nogil=True)
def _take_all(assigned: np.ndarray, lo: int, hi: int, node: int) -> int:
    taken = 0
    for i in range(lo, hi):
        if assigned[i] < 0:
            assigned[i] = node
            taken += 1
    return taken


@numba.njit(cache=True, nogil=True)
def _counting_order(keys: np.ndarray, nkeys: int) -> tuple[np.ndarray, np.ndarray]:
    """Stable order sorting small non-negative integer ``keys``; also the (nkeys + 1,) bucket starts."""
    starts = zeros(nkeys + 1, np.int64)
    for k in keys:
        starts[k + 1] += 1
    for k in range(nkeys):
        starts[k + 1] += starts[k]
    fill = starts[:-1].copy()
    order = empty(keys.shape[0], np.int64)
    for i in range(keys.shape[0]):
        k = keys[i]
        order[fill[k]] = i
        fill[k] += 1
    return order, starts


@numba.njit(cache=True, inline="always")
def _grow(amin, amax, k: int, v: float) -> bool:
    """Grow ``amin[k]``/``amax[k]`` by ``v``; False (and no change) when ``v`` is not finite."""
    if not np.isfinite(v):
        return False
    amin[k] = min(amin[k], v)
    amax[k] = max(amax[k], v)
    return True


@numba.njit(cache=True, nogil=True)
def _scan_kernel(x, y, z, r, g, b, nx, ny, nz, sz, flags, lo, hi, amin, amax) -> tuple[int, int]:
    """One pass over a slice: grow the bounds ``lo``/``hi`` (3,) by the finite points and the
    attribute ranges ``amin``/``amax`` (7,: rgb, normal, size) by the finite values.

    Returns the number of points with a non-finite coordinate and of non-finite sizes.
    """
    bad = 0
    bad_size = 0
    for i in range(x.shape[0]):
        a, bb, c = np.float64(x[i]), np.float64(y[i]), np.float64(z[i])
        if np.isfinite(a) and np.isfinite(bb) and np.isfinite(c):
            lo[0] = min(lo[0], a)
            lo[1] = min(lo[1], bb)
            lo[2] = min(lo[2], c)
            hi[0] = max(hi[0], a)
            hi[1] = max(hi[1], bb)
            hi[2] = max(hi[2], c)
        else:
            bad += 1
        if flags[0]:
            _grow(amin, amax, 0, np.float64(r[i]))
            _grow(amin, amax, 1, np.float64(g[i]))
            _grow(amin, amax, 2, np.float64(b[i]))
        if flags[1]:
            _grow(amin, amax, 3, np.float64(nx[i]))
            _grow(amin, amax, 4, np.float64(ny[i]))
            _grow(amin, amax, 5, np.float64(nz[i]))
        if flags[2]:
            if not _grow(amin, amax, 6, np.float64(sz[i])):
                bad_size += 1
    return bad, bad_size


@numba.njit(cache=True, nogil=True)
def _quantise_kernel(x, y, z, offset, scale: float, qsize: int, out) -> None:
    inv = 1.0 / scale
    top = np.int64(qsize - 1)
    for i in range(x.shape[0]):
        out[i, 0] = _quantise1(x[i], offset[0], inv, top)
        out[i, 1] = _quantise1(y[i], offset[1], inv, top)
        out[i, 2] = _quantise1(z[i], offset[2], inv, top)


@numba.njit(cache=True, nogil=True)
def _count_kernel(x, y, z, offset, scale: float, qsize: int, shift: int, counts) -> None:
    """Quantise, Morton-code and count one slice into ``counts`` (cells of ``code >> shift``)."""
    inv = 1.0 / scale
    top = np.int64(qsize - 1)
    mscale = (1 << MORTON_BITS) / qsize
    mtop = np.int64((1 << MORTON_BITS) - 1)
    for i in range(x.shape[0]):
        qx = _quantise1(x[i], offset[0], inv, top)
        qy = _quantise1(y[i], offset[1], inv, top)
        qz = _quantise1(z[i], offset[2], inv, top)
        counts[_morton3(qx, qy, qz, mscale, mtop) >> shift] += 1


@numba.njit(cache=True, nogil=True)
def _distribute_kernel(
    x, y, z, r, g, b, nx, ny, nz, sz, flags, offset, scale, qsize, shift, cell_to_chunk, nchunks,
    pos, rgb, nrm, size, q, cid,
) -> np.ndarray:  # fmt: skip
    """Quantise and pack one slice into records grouped by chunk (file order kept inside a
    chunk); returns the (nchunks + 1,) starts of every chunk's run in the records. ``q``
    (>= N, 3) int32 and ``cid`` (>= N,) int32 are scratch buffers."""
    n = x.shape[0]
    inv = 1.0 / scale
    top = np.int64(qsize - 1)
    mscale = (1 << MORTON_BITS) / qsize
    mtop = np.int64((1 << MORTON_BITS) - 1)
    starts = zeros(nchunks + 1, np.int64)
    for i in range(n):
        qx = _quantise1(x[i], offset[0], inv, top)
        qy = _quantise1(y[i], offset[1], inv, top)
        qz = _quantise1(z[i], offset[2], inv, top)
        q[i, 0], q[i, 1], q[i, 2] = qx, qy, qz
        c = cell_to_chunk[_morton3(qx, qy, qz, mscale, mtop) >> shift]
        cid[i] = c
        starts[c + 1] += 1
    for k in range(nchunks):
        starts[k + 1] += starts[k]
    fill = starts[:-1].copy()
    for i in range(n):
        j = fill[cid[i]]
        fill[cid[i]] += 1
        pos[j, 0], pos[j, 1], pos[j, 2] = q[i, 0], q[i, 1], q[i, 2]
        if flags[0]:
            rgb[j, 0] = np.uint16(r[i]) * 257  # 8-bit colour to Potree's 16-bit range
            rgb[j, 1] = np.uint16(g[i]) * 257
            rgb[j, 2] = np.uint16(b[i]) * 257
        else:
            rgb[j, 0] = rgb[j, 1] = rgb[j, 2] = 65535
        if flags[1]:
            nrm[j, 0] = nx[i]
            nrm[j, 1] = ny[i]
            nrm[j, 2] = nz[i]
        else:
            nrm[j, 0] = nrm[j, 1] = nrm[j, 2] = 0.0
        size[j] = sz[i] if flags[2] else 0.0
    return starts


@numba.njit(cache=True, nogil=True)
def _pack_keys(codes: np.ndarray, base: int, drop: int, idx_bits: int) -> np.ndarray:
    out = empty(codes.shape[0], np.uint64)
    for i in range(codes.shape[0]):
        out[i] = (np.uint64((codes[i] - base) >> drop) << np.uint64(idx_bits)) | np.uint64(i)
    return out


@numba.njit(cache=True, nogil=True)
def _unpack_keys(keys: np.ndarray, base: int, drop: int, idx_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Point index and Morton code (its dropped bits zero) of every sorted key."""
    mask = np.uint64((1 << idx_bits) - 1)
    index = empty(keys.shape[0], np.int64)
    codes = empty(keys.shape[0], np.int64)
    for i in range(keys.shape[0]):
        index[i] = np.int64(keys[i] & mask)
        codes[i] = (np.int64(keys[i] >> np.uint64(idx_bits)) << drop) + base
    return index, codes


@numba.njit(cache=True, nogil=True)
def _push(arr: np.ndarray, count: int, value: int) -> np.ndarray:
    if count == arr.shape[0]:
        grown = empty(2 * arr.shape[0], arr.dtype)
        # element by element: a slice assignment compiles numba's shape-mismatch message (its
        # string formatting, 2.5 s of the warm-up) for a mismatch that cannot happen here
        for i in range(count):
            grown[i] = arr[i]
        arr = grown
    arr[count] = value
    return arr


@numba.njit(cache=True, nogil=True)
def _sample_split(
    codes: np.ndarray, assigned: np.ndarray, lo: int, hi: int, shift: int, cshift: int, node: int,
    child_left: np.ndarray,
) -> None:  # fmt: skip
    """:func:`_sample` into ``node``, counting in the same pass the points each child
    (``(code >> cshift) & 7``) is left with in ``child_left`` (8,)."""
    child_left[:] = 0
    last = np.int64(-1)
    for i in range(lo, hi):
        if assigned[i] < 0:
            key = codes[i] >> shift
            if key != last:
                assigned[i] = node
                last = key
            else:
                child_left[(codes[i] >> cshift) & 7] += 1


@numba.njit(cache=True, nogil=True)
def _build_nodes(
    codes: np.ndarray, level_c: int, prefix_c: int, max_leaf: int, max_depth: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Assign every point of a chunk (Morton-sorted ``codes``) to one node.

    Returns ``assigned`` (N,) node numbers and per node its level, prefix and whether it lies
    inside the chunk (nodes above it are shared with other chunks), in creation order: the
    chunk's ancestors root first, then its subtree depth first, child 0 first.
    """
    n = codes.shape[0]
    assigned = full(n, -1, np.int32)
    levels = empty(64, np.int64)
    prefixes = empty(64, np.int64)
    own = empty(64, np.int64)
    nodes = 0
    # Upper nodes: this chunk's share of every ancestor's grid sample.
    for level in range(level_c):
        levels = _push(levels, nodes, level)
        prefixes = _push(prefixes, nodes, prefix_c >> (3 * (level_c - level)))
        own = _push(own, nodes, 0)
        _sample(codes, assigned, 0, n, 3 * (MORTON_BITS - level - GRID_LEVELS), nodes)
        nodes += 1

    # Depth first, child 0 first; an entry is level, prefix, lo, hi and the points left there.
    stack = empty((64, 5), np.int64)
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = level_c, prefix_c, 0, n
    stack[0, 4] = _count_unassigned(assigned, 0, n)
    top = 1
    edges = empty(9, np.int64)
    child_left = zeros(8, np.int64)
    while top > 0:
        top -= 1
        level, prefix, lo, hi, remaining = (
            stack[top, 0],
            stack[top, 1],
            stack[top, 2],
            stack[top, 3],
            stack[top, 4],
        )
        if remaining == 0:  # a small chunk whose points all went to the nodes above it
            continue
        node = nodes
        levels = _push(levels, nodes, level)
        prefixes = _push(prefixes, nodes, prefix)
        own = _push(own, nodes, 1)
        nodes += 1
        if remaining <= max_leaf or level >= max_depth:
            _take_all(assigned, lo, hi, node)
            continue
        cshift = 3 * (MORTON_BITS - level - 1)
        _sample_split(
            codes, assigned, lo, hi, 3 * (MORTON_BITS - level - GRID_LEVELS), cshift, node, child_left
        )
        for k in range(8):
            edges[k] = lo + np.searchsorted(codes[lo:hi], (prefix * 8 + k) << cshift)
        edges[8] = hi
        for k in range(7, -1, -1):
            if child_left[k] > 0:
                if top == stack.shape[0]:
                    grown = empty((2 * top, 5), np.int64)
                    for i in range(top):  # not a slice assignment: see _push
                        for j in range(5):
                            grown[i, j] = stack[i, j]
                    stack = grown
                stack[top, 0], stack[top, 1], stack[top, 2] = level + 1, prefix * 8 + k, edges[k]
                stack[top, 3], stack[top, 4] = edges[k + 1], child_left[k]
                top += 1
    return assigned, levels[:nodes].copy(), prefixes[:nodes].copy(), own[:nodes].copy()
