"""A lossless range band's check value (private kernels of :mod:`shared.compress.range`): a
32-bit hash of the float32 samples the decoder writes, which the encoder computes from its
targets and stores beside the band's stream.

The container's CRC-32 catches damage in storage or transit. A payload rewritten with a fresh
CRC (a buggy tool) is caught by the rANS stream's end state and position only where the damage
does not heal: on flat tables (a real capture's noisy residuals, raw bits) a corrupted state
often does, and 6 of 150 single-bit flips in a kamino410 capture's lossless chunks decoded to
another image (3 to 174 samples wrong) with every stream check passing. The hash makes that
one in 2**32: the decoder compares it with its own samples' before it hands the image on.
Order-sensitive (each sample mixed with its index) and a sum of mixed terms, so LLVM
vectorises it: about 1 ns a sample."""

from __future__ import annotations

import numpy as np
from numba import njit

#: A hole's bits (any NaN the decoder writes counts as this one).
HOLE = np.uint32(0x7FC00000)
_M1 = np.uint64(0xFF51AFD7ED558CCD)
_M2 = np.uint64(0xC4CEB9FE1A85EC53)
_S = np.uint64(33)


@njit(cache=True, nogil=True, inline="always")
def _mixed(u, i):
    """MurmurHash3's 64-bit finaliser of a sample's bits ``u`` (uint32) beside its index ``i``."""
    k = np.uint64(u) | (np.uint64(i) << np.uint64(32))
    k ^= k >> _S
    k *= _M1
    k ^= k >> _S
    k *= _M2
    return k ^ (k >> _S)


@njit(cache=True, nogil=True, inline="always")
def _fold(h):
    return np.uint32((h ^ (h >> np.uint64(32))) & np.uint64(0xFFFFFFFF))


@njit(cache=True, nogil=True)
def output_check(bits):
    """The check of a decoded band: ``bits`` (H, W) uint32, its float32 samples' bit patterns
    (C-contiguous rows). Returns uint32."""
    H, W = bits.shape
    h = np.uint64(0)
    for y in range(H):
        row = bits[y]
        for x in range(W):
            u = row[x]
            if (u & np.uint32(0x7F800000)) == np.uint32(0x7F800000) and (u & np.uint32(0x7FFFFF)) != 0:
                u = HOLE
            h += _mixed(u, y * W + x)
    return _fold(h)


@njit(cache=True, nogil=True)
def lossless_check(t, valid, scale, shift):
    """:func:`output_check` of the band the decoder will write from lossless targets ``t`` (H, W)
    int64 (fine units, ``shift`` bits below the quantum) and ``valid`` (H, W) bool: each valid
    sample ``float32((t >> shift) * scale)``, a hole NaN. Returns uint32."""
    H, W = t.shape
    row = np.empty(W, np.float32)
    ubits = row.view(np.uint32)
    h = np.uint64(0)
    for y in range(H):
        for x in range(W):
            row[x] = np.float32((t[y, x] >> shift) * scale) if valid[y, x] else np.float32(np.nan)
        for x in range(W):
            u = ubits[x]
            if not valid[y, x]:
                u = HOLE
            h += _mixed(u, y * W + x)
    return _fold(h)
