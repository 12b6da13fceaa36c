"""A static-model rANS entropy coder with many context tables, in numba (private kernels).

The coders of this package turn their data into a stream of *events*: a symbol of one of up
to :data:`MAX_TABLES` context tables, or a few raw bits. The encoder counts the symbols of
every table over a chunk, normalises the counts to :data:`PROB_BITS`-bit frequencies (each
table stored in the chunk, a few hundred bytes), and codes the events in reverse with one
32-bit rANS state emitting 16-bit words (Duda's range variant of ANS; renormalisation as in
Giesen's ``rans_byte`` with a 16-bit word). The decoder reads them forward. Per-chunk
tables adapt to each chunk's statistics at no per-symbol cost: decoding is one table look-up,
one multiply and a shift per symbol.

Values are binarised by :func:`put_value`: a value below the table's *direct* size ``D`` (a
power of two) is its own symbol; a larger one is the symbol ``D + (bit length - log2 D - 1)``
followed by its low bits raw (an Elias-gamma-like escape), so every table holds at most
``D + 64`` symbols and any unsigned 64-bit value can be coded.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Frequency precision: probabilities are multiples of 2**-PROB_BITS.
PROB_BITS = 14
PROB_SCALE = 1 << PROB_BITS
#: The rANS state lives in [RANS_L, 2**32).
RANS_L = 1 << 16
#: Raw bits are coded in pieces of at most this many bits (a uniform "table").
RAW_PIECE = PROB_BITS
MAX_TABLES = 32
#: Symbols per table: a direct part of at most 256 and 64 escape classes.
NSYM = 256 + 64
#: ``tab`` value of a raw-bits event.
RAW = -1


@njit(cache=True, nogil=True, inline="always")
def bitlen(u: np.uint64) -> int:
    n = 0
    while u > 0:
        u >>= np.uint64(1)
        n += 1
    return n


@njit(cache=True, nogil=True)
def put(tab, val, nb, n, t, v, bits):
    """Append one event (table ``t`` symbol ``v``, or ``t == RAW`` with ``bits`` raw bits); returns n+1
    (or -1 when the buffers are full, so the caller retries with larger ones)."""
    if n < 0 or n >= tab.shape[0]:
        return -1
    tab[n] = t
    val[n] = v
    nb[n] = bits
    return n + 1


@njit(cache=True, nogil=True)
def put_value(tab, val, nb, n, t, u, log2d):
    """Append unsigned value ``u`` in table ``t`` whose direct part is ``2**log2d`` symbols."""
    d = np.uint64(1) << np.uint64(log2d)
    u = np.uint64(u)
    if u < d:
        return put(tab, val, nb, n, t, np.int64(u), 0)
    nbits = bitlen(u)
    n = put(tab, val, nb, n, t, np.int64(d) + nbits - log2d - 1, 0)
    rem = nbits - 1
    low = u - (np.uint64(1) << np.uint64(rem))
    while rem > 0:
        k = min(rem, RAW_PIECE)
        n = put(tab, val, nb, n, RAW, np.int64(low & ((np.uint64(1) << np.uint64(k)) - np.uint64(1))), k)
        low >>= np.uint64(k)
        rem -= k
    return n


@njit(cache=True, nogil=True, inline="always")
def zigzag(r: np.int64) -> np.uint64:
    return np.uint64(r << 1) if r >= 0 else np.uint64((-r << 1) - 1)


@njit(cache=True, nogil=True, inline="always")
def unzigzag(u: np.uint64) -> np.int64:
    return np.int64(u >> np.uint64(1)) if (u & np.uint64(1)) == 0 else -np.int64(u >> np.uint64(1)) - 1


@njit(cache=True, nogil=True)
def count_symbols(tab, val, n, ntables):
    counts = np.zeros((ntables, NSYM), np.int64)
    for i in range(n):
        t = tab[i]
        if t >= 0:
            counts[t, val[i]] += 1
    return counts


@njit(cache=True, nogil=True)
def normalise(counts):
    """Frequencies summing to PROB_SCALE per used table, every counted symbol at least 1."""
    nt, ns = counts.shape
    freq = np.zeros((nt, ns), np.int32)
    for t in range(nt):
        total = 0
        used = 0
        for s in range(ns):
            total += counts[t, s]
            used += counts[t, s] > 0
        if total == 0:
            continue
        if used == 1:
            for s in range(ns):
                if counts[t, s] > 0:
                    freq[t, s] = PROB_SCALE
            continue
        acc = 0
        best = 0
        for s in range(ns):
            c = counts[t, s]
            if c > 0:
                f = max(1, np.int64(c * PROB_SCALE / total + 0.5))
                freq[t, s] = f
                acc += f
                if c > counts[t, best]:
                    best = s
        # Fix the sum on the largest symbols (costs least there); shave others if one cannot absorb it.
        diff = PROB_SCALE - acc
        while diff != 0:
            if diff > 0:
                freq[t, best] += diff
                diff = 0
            else:
                s_max = 0
                for s in range(ns):
                    if freq[t, s] > freq[t, s_max]:
                        s_max = s
                take = min(-diff, freq[t, s_max] - 1)
                freq[t, s_max] -= take
                diff += take
    return freq


@njit(cache=True, nogil=True)
def encode_events(tab, val, nb, n, freq):
    """rANS-code events 0..n-1 (in reverse); returns the 16-bit words in decoding order."""
    nt, ns = freq.shape
    cum = np.zeros((nt, ns), np.int64)
    for t in range(nt):
        c = 0
        for s in range(ns):
            cum[t, s] = c
            c += freq[t, s]
    out = np.empty(n + 4, np.uint16)
    pos = out.shape[0]
    x = np.uint64(RANS_L)
    for i in range(n - 1, -1, -1):
        t = tab[i]
        if t >= 0:
            f = np.uint64(freq[t, val[i]])
            c = np.uint64(cum[t, val[i]])
        else:
            sh = PROB_BITS - nb[i]
            f = np.uint64(1) << np.uint64(sh)
            c = np.uint64(val[i]) << np.uint64(sh)
        x_max = np.uint64((RANS_L >> PROB_BITS) << 16) * f
        while x >= x_max:
            pos -= 1
            out[pos] = np.uint16(x & np.uint64(0xFFFF))
            x >>= np.uint64(16)
        x = ((x // f) << np.uint64(PROB_BITS)) + (x % f) + c
    pos -= 1
    out[pos] = np.uint16(x >> np.uint64(16))
    pos -= 1
    out[pos] = np.uint16(x & np.uint64(0xFFFF))
    return out[pos:].copy()


@njit(cache=True, nogil=True)
def decode_tables(freq):
    """Cumulative frequencies and the slot -> symbol look-up of every used table."""
    nt, ns = freq.shape
    cum = np.zeros((nt, ns), np.int32)
    lut = np.zeros((nt, PROB_SCALE), np.int16)
    for t in range(nt):
        c = 0
        for s in range(ns):
            cum[t, s] = c
            f = freq[t, s]
            for k in range(c, c + f):
                lut[t, k] = s
            c += f
    return cum, lut


@njit(cache=True, nogil=True)
def dec_init(words):
    """The decoder state: ``st = [x, pos]`` (numba has no cheap mutable scalars to share)."""
    st = np.zeros(2, np.uint64)
    if words.shape[0] < 2:
        st[1] = np.uint64(1 << 62)  # marks a broken stream
        return st
    st[0] = (np.uint64(words[1]) << np.uint64(16)) | np.uint64(words[0])
    st[1] = np.uint64(2)
    return st


@njit(cache=True, nogil=True, inline="always")
def _renorm(st, words):
    x = st[0]
    pos = st[1]
    while x < np.uint64(RANS_L):
        if pos < np.uint64(words.shape[0]):
            x = (x << np.uint64(16)) | np.uint64(words[pos])
        else:
            x = (x << np.uint64(16))
            pos = np.uint64(1 << 62)
            break
        pos += np.uint64(1)
    st[0] = x
    st[1] = pos


@njit(cache=True, nogil=True, inline="always")
def get_symbol(st, words, freq, cum, lut, t):
    x = st[0]
    slot = x & np.uint64(PROB_SCALE - 1)
    s = lut[t, slot]
    st[0] = np.uint64(freq[t, s]) * (x >> np.uint64(PROB_BITS)) + slot - np.uint64(cum[t, s])
    _renorm(st, words)
    return s


@njit(cache=True, nogil=True, inline="always")
def get_raw(st, words, k):
    x = st[0]
    slot = x & np.uint64(PROB_SCALE - 1)
    sh = np.uint64(PROB_BITS - k)
    v = slot >> sh
    f = np.uint64(1) << sh
    st[0] = f * (x >> np.uint64(PROB_BITS)) + (slot & (f - np.uint64(1)))
    _renorm(st, words)
    return v


@njit(cache=True, nogil=True)
def get_value(st, words, freq, cum, lut, t, log2d):
    s = np.int64(get_symbol(st, words, freq, cum, lut, t))
    d = np.int64(1) << log2d
    if s < d:
        return np.uint64(s)
    nbits = s - d + log2d + 1
    rem = nbits - 1
    u = np.uint64(1) << np.uint64(rem)
    shift = 0
    while rem > 0:
        k = min(rem, RAW_PIECE)
        u |= get_raw(st, words, k) << np.uint64(shift)
        shift += k
        rem -= k
    return u


@njit(cache=True, nogil=True)
def pack_tables(freq):
    """Serialise the frequency tables: per table a varint count of its symbols up to the last
    used one (0 for an unused table), then each frequency as a varint."""
    nt, ns = freq.shape
    out = np.empty(nt * (ns * 3 + 3), np.uint8)
    n = 0
    for t in range(nt):
        last = -1
        for s in range(ns):
            if freq[t, s] > 0:
                last = s
        v = last + 1
        while True:
            b = v & 0x7F
            v >>= 7
            out[n] = b | (0x80 if v else 0)
            n += 1
            if not v:
                break
        for s in range(last + 1):
            v = freq[t, s]
            while True:
                b = v & 0x7F
                v >>= 7
                out[n] = b | (0x80 if v else 0)
                n += 1
                if not v:
                    break
    return out[:n].copy()


@njit(cache=True, nogil=True)
def unpack_tables(buf, ntables):
    """Inverse of :func:`pack_tables`; returns (freq, bytes read) or (freq, -1) when malformed."""
    freq = np.zeros((ntables, NSYM), np.int32)
    n = 0
    for t in range(ntables):
        v = 0
        sh = 0
        while True:
            if n >= buf.shape[0] or sh > 28:
                return freq, -1
            b = buf[n]
            n += 1
            v |= (b & 0x7F) << sh
            sh += 7
            if not (b & 0x80):
                break
        cnt = v
        if cnt > NSYM:
            return freq, -1
        total = 0
        for s in range(cnt):
            v = 0
            sh = 0
            while True:
                if n >= buf.shape[0] or sh > 28:
                    return freq, -1
                b = buf[n]
                n += 1
                v |= (b & 0x7F) << sh
                sh += 7
                if not (b & 0x80):
                    break
            freq[t, s] = v
            total += v
        if cnt > 0 and total != PROB_SCALE:
            return freq, -1
    return freq, n
