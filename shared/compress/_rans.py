"""A rANS entropy coder with many static context tables and adaptive binary models, in numba
(private kernels).

The coders of this package turn their data into a stream of *events*: a symbol of one of up
to :data:`MAX_TABLES` context tables, a few raw bits, or a binary decision carrying its own
probability (:data:`BIN`, from an adaptive model: :func:`state_p`, :func:`state_next`; the
encoder runs the models forward to fill the events, the decoder runs the same integer
updates as it reads). The encoder counts the symbols of
every table over a chunk, normalises the counts to :data:`PROB_BITS`-bit frequencies (each
table stored in the chunk, a few hundred bytes), and codes the events in reverse with one
32-bit rANS state emitting 16-bit words (Duda's range variant of ANS; renormalisation as in
Giesen's ``rans_byte`` with a 16-bit word). The decoder reads them forward. Per-chunk
tables adapt to each chunk's statistics at no per-symbol cost: decoding is one table look-up,
one multiply and a shift per symbol.

Values are binarised by :func:`put_value`: a value below the table's *direct* size ``D`` (a
power of two) is its own symbol; a larger one is the symbol ``D + (bit length - log2 D - 1)``
followed by its low bits raw (an Elias-gamma-like escape; the symbol may carry the ``m`` bits
below the top, their values' lower bits raw), so every table holds at most ``D + 64 * 2**m``
symbols and any unsigned 64-bit value can be coded.
"""

from __future__ import annotations

import numpy as np

from shared.core.jit import at, empty, full, helper, kernel, set_at, zeros

#: Frequency precision: probabilities are multiples of 2**-PROB_BITS.
PROB_BITS = 12
PROB_SCALE = 1 << PROB_BITS
#: The rANS state lives in [RANS_L, 2**32).
RANS_L = 1 << 16
#: Raw bits are coded in pieces of at most this many bits (a uniform "table").
RAW_PIECE = PROB_BITS
MAX_TABLES = 32
#: Symbols per table: a direct part of at most 256 and 64 escape classes, each in up to four
#: (:func:`put_value`'s bits below the top).
NSYM = 256 + 4 * 64
#: ``tab`` value of a raw-bits event.
RAW = -1
#: ``tab`` value of a binary event with its own probability: ``val = p << 1 | bit`` where
#: ``p / PROB_SCALE`` (1 <= p < PROB_SCALE) is the probability of a one (an adaptive model's
#: estimate, the same integers in encoder and decoder).
BIN = -2


@helper
def bitlen(u: np.uint64) -> int:
    n = 0
    while u > 0:
        u >>= np.uint64(1)
        n += 1
    return n


@helper
def put(tab, val, nb, n, t, v, bits):
    """Append one event (table ``t`` symbol ``v``, or ``t == RAW`` with ``bits`` raw bits); returns n+1
    (or -1 when the buffers are full, so the caller retries with larger ones)."""
    if n < 0 or n >= tab.shape[0]:
        return -1
    tab[n] = t
    val[n] = v
    nb[n] = bits
    return n + 1


@helper
def put_value(tab, val, nb, n, t, u, log2d, m):
    """Append unsigned value ``u`` in table ``t`` whose direct part is ``2**log2d`` symbols, an
    escape carrying the ``m`` bits below a value's top bit (:func:`symbol_of`)."""
    d = np.uint64(1) << np.uint64(log2d)
    u = np.uint64(u)
    if u < d:
        return put(tab, val, nb, n, t, np.int64(u), 0)
    # int64 arguments: constants would each type (and compile) a signature of their own
    return _put_escape(tab, val, nb, np.int64(n), np.int64(t), u, np.int64(log2d), d, np.int64(m))


@helper(inline=False)
def _put_escape(tab, val, nb, n, t, u, log2d, d, m):
    nbits = bitlen(u)
    rem = nbits - 1 - m  # the raw bits below the top bit and the m bits in the symbol
    top = np.int64((u >> np.uint64(rem)) & np.uint64((1 << m) - 1))
    n = put(tab, val, nb, n, t, np.int64(d) + ((nbits - log2d - 1) << m) + top, 0)
    low = u & ((np.uint64(1) << np.uint64(rem)) - np.uint64(1))
    while rem > 0:
        k = min(rem, RAW_PIECE)
        n = put(tab, val, nb, n, RAW, np.int64(low & ((np.uint64(1) << np.uint64(k)) - np.uint64(1))), k)
        low >>= np.uint64(k)
        rem -= k
    return n


@helper
def symbol_of(u, log2d, m):
    """The symbol :func:`put_value` codes unsigned value ``u`` (int64 >= 0) with (its raw bits
    aside): the value below ``2**log2d``, else the escape of its bit length and the ``m`` bits
    below its top bit (``m <= log2d``)."""
    d = np.int64(1) << log2d
    if u < d:
        return u
    nbits = np.int64(bitlen(np.uint64(u)))
    return d + ((nbits - log2d - 1) << m) + ((u >> (nbits - 1 - m)) & ((1 << m) - 1))


@helper
def zigzag(r: np.int64) -> np.uint64:
    return np.uint64(r << 1) if r >= 0 else np.uint64((-r << 1) - 1)


@helper
def unzigzag(u: np.uint64) -> np.int64:
    return np.int64(u >> np.uint64(1)) if (u & np.uint64(1)) == 0 else -np.int64(u >> np.uint64(1)) - 1


@kernel
def count_symbols(tab, val, n, ntables):
    counts = zeros((ntables, NSYM), np.int64)
    for i in range(n):
        t = tab[i]
        if t >= 0:
            counts[t, val[i]] += 1
    return counts


@kernel
def normalise(counts):
    """Frequencies summing to PROB_SCALE per used table, every counted symbol at least 1."""
    nt, ns = counts.shape
    freq = zeros((nt, ns), np.int32)
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


@kernel
def encode_events(tab, val, nb, n, freq):
    """rANS-code events 0..n-1 with two interleaved states (event i on state i % 2, which
    doubles the decoder's instruction-level parallelism), in reverse; returns the 16-bit
    words in decoding order."""
    nt, ns = freq.shape
    cum = zeros((nt, ns), np.int64)
    for t in range(nt):
        c = 0
        for s in range(ns):
            cum[t, s] = c
            c += freq[t, s]
    out = empty(n + 8, np.uint16)
    pos = out.shape[0]
    st = full(2, RANS_L, np.int64)
    for i in range(n - 1, -1, -1):
        t = tab[i]
        if t >= 0:
            f = np.int64(freq[t, val[i]])
            c = cum[t, val[i]]
        elif t == BIN:
            p = np.int64(val[i]) >> 1
            if val[i] & 1:
                f = p
                c = np.int64(0)
            else:
                f = PROB_SCALE - p
                c = p
        else:
            sh = PROB_BITS - nb[i]
            f = np.int64(1) << sh
            c = np.int64(val[i]) << sh
        x = st[i & 1]
        x_max = ((RANS_L >> PROB_BITS) << 16) * f
        if x >= x_max:  # one word always suffices: x < 2**32
            pos -= 1
            out[pos] = np.uint16(x & 0xFFFF)
            x >>= 16
        st[i & 1] = ((x // f) << PROB_BITS) + (x % f) + c
    for k in (1, 0):
        pos -= 1
        out[pos] = np.uint16(st[k] >> 16)
        pos -= 1
        out[pos] = np.uint16(st[k] & 0xFFFF)
    return out[pos:].copy()


@kernel
def decode_tables(freq):
    """Per table and slot: the symbol, and ``freq << 16 | (slot - cum)`` packed in 32 bits."""
    nt, ns = freq.shape
    sym = zeros((nt, PROB_SCALE), np.int16)
    fb = zeros((nt, PROB_SCALE), np.uint32)
    for t in range(nt):
        c = 0
        for s in range(ns):
            f = freq[t, s]
            for k in range(c, c + f):
                sym[t, k] = s
                fb[t, k] = (f << 16) | (k - c)
            c += f
    return sym, fb


# The decoder's state is two plain integers (xa, the state of the next event, and xb) and the
# read position; every helper returns them swapped for the next event. Locals, not an array:
# the compiler keeps them in registers.


@kernel
def dec_init(words):
    """Initial (xa, xb, pos) of a stream (pos beyond the end when it is too short)."""
    if words.shape[0] < 4:
        return RANS_L, RANS_L, words.shape[0] + 1
    xa = (np.int64(words[1]) << 16) | np.int64(words[0])
    xb = (np.int64(words[3]) << 16) | np.int64(words[2])
    return xa, xb, 4


# numba-inlined, not a helper: with it and the octree's context helpers LLVM-inlined
# (shared.compress._octree_ctx), the cloud decoder ran 2.5-3.5 % slower than with numba's
# inlining (A/B in alternating processes), for 2.5-3 s less compilation.
@kernel(inline="always")
def _next(xa, pos, words, nw):
    # Branch-free renormalisation (the branch would be mispredicted on about a third of the
    # symbols). A corrupt stream may run past its end: the read is clamped to the last word
    # (callers check nw >= 4) and the final position check reports it.
    need = np.int64(xa < RANS_L)
    w = np.int64(at(words, min(pos, nw - 1)))
    xa = (xa << (need << 4)) | (w & -need)
    return xa, pos + need


# get_symbol and get_value keep numba's inlining for the cloud decoder (and Python callers):
# as helpers, its duplicate counts (_octree._decode_tail) decoded at 0.5 mm in 105-108 ms of
# CPU against 88 ms, in three of four alternating runs. The range decoders' kernels call their
# helper twins, read_symbol and read_value, instead.
@kernel(inline="always")
def get_symbol(xa, xb, pos, words, nw, sym, fb, t):
    """Decode a symbol of table t: returns (symbol, xa, xb, pos) for the next event."""
    slot = xa & (PROB_SCALE - 1)
    s = np.int64(sym[t, slot])
    e = np.int64(fb[t, slot])
    xa = (e >> 16) * (xa >> PROB_BITS) + (e & 0xFFFF)
    xa, pos = _next(xa, pos, words, nw)
    return s, xb, xa, pos


@helper
def get_raw(xa, xb, pos, words, nw, k):
    """Decode k <= RAW_PIECE raw bits: returns (value, xa, xb, pos)."""
    slot = xa & (PROB_SCALE - 1)
    sh = PROB_BITS - k
    v = slot >> sh
    xa = (np.int64(1) << sh) * (xa >> PROB_BITS) + (slot & ((np.int64(1) << sh) - 1))
    xa, pos = _next(xa, pos, words, nw)
    return v, xb, xa, pos


#: -log2(p / PROB_SCALE): the bits of a binary event of probability p (:func:`binary_bits`).
BIN_BITS = -np.log2(np.maximum(np.arange(PROB_SCALE + 1), 0.5) / PROB_SCALE)


@kernel
def binary_bits(tab, val):
    """The bits the coder spends on the :data:`BIN` events among ``tab``, ``val``."""
    bits = 0.0
    for i in range(tab.shape[0]):
        if tab[i] == BIN:
            p = np.int64(val[i]) >> 1
            bits += BIN_BITS[p if val[i] & 1 else PROB_SCALE - p]
    return bits


@helper(inline=False)
def get_bit(xa, xb, pos, words, nw, p):
    """Decode a :data:`BIN` event of probability ``p / PROB_SCALE`` of a one: returns (bit, xa, xb, pos)."""
    slot = xa & (PROB_SCALE - 1)
    one = slot < p
    f = p if one else PROB_SCALE - p
    c = 0 if one else p
    xa = f * (xa >> PROB_BITS) + slot - c
    xa, pos = _next(xa, pos, words, nw)
    return np.int64(one), xb, xa, pos


#: Adaptive binary models, one uint32 per context: the probability of a one in the low 16 bits,
#: how often the model was used (up to 255) above them. The ``n``-th update moves the
#: probability about 1 / (n + 2) of the way to the bit (the running frequency with a prior of one
#: zero and one one, which learns a sparse context's few events at their worth; as a shift, not a
#: multiply: the update lies on the decoder's chain when a context repeats), until the rate
#: reaches its floor (:func:`adapt_state`): then it tracks drifting statistics.
P_ONE = 1 << 16
P_MIN = 32
MODEL_INIT = P_ONE >> 1
#: Slowest update of a model, as a count: rate 2**-RATE_SHIFT[MODEL_LIMIT] = 1/32. Measured on
#: the octree codec's clouds (bench scan and bunny scan, 0.1 and 0.5 mm grids), the rate
#: 1 / (n + 2) with floors at counts of 22 to 40 costs within 0.3 % of each other; the rates this
#: replaces (1/4 halving every second event down to 1/64) cost 0.5 % (scan, 0.1 mm) to 4 %
#: (bunny, 0.5 mm) more.
MODEL_LIMIT = 32
#: RATE_SHIFT[n] = log2(n + 2) rounded (at least 1), in integers: the shift of the update of a
#: model used n times (n < 256).
RATE_SHIFT = np.array([max(1, ((2 * (k + 2) ** 2).bit_length() - 1) // 2) for k in range(256)], np.int64)


@kernel
def state_p(s):
    """The :data:`BIN` event probability (PROB_BITS) of a model's state ``s``."""
    return np.int64(s & 0xFFFF) >> (16 - PROB_BITS)


@helper(inline=False)
def state_next(s, bit):
    """A model's state ``s`` adapted to ``bit`` (integers only: encoder and decoder agree)."""
    return adapt_state(s, bit, np.int64(MODEL_LIMIT))  # int64, not a literal: one copy with the SSE cells'


@helper(inline=False)
def adapt_state(s, bit, limit):
    """State ``s`` (16-bit probability of a one, event count above it) adapted to ``bit``: the
    n-th update moves the probability 2**-RATE_SHIFT[min(n, limit)] (about 1 / (n + 2)) of the
    way to the bit (``limit`` < 256)."""
    s = np.int64(s)
    p = s & 0xFFFF
    n = s >> 16
    r = at(RATE_SHIFT, min(n, limit))
    if bit:
        p += (P_ONE - p) >> r
    else:
        p -= p >> r
    p = min(max(p, P_MIN), P_ONE - P_MIN)
    return np.uint32(p | (min(n + 1, 255) << 16))


@helper(inline=False)
def model_p(models, ctx):
    """The :data:`BIN` event probability (PROB_BITS) of context ``ctx``'s model."""
    return state_p(at(models, ctx))


@helper(inline=False)
def model_update(models, ctx, bit):
    """Adapt context ``ctx``'s model to ``bit``."""
    set_at(models, ctx, state_next(at(models, ctx), bit))


@helper(inline=False)
def _get_escape(xa, xb, pos, words, nw, s, d, log2d, m):
    nbits = ((s - d) >> m) + log2d + 1
    rem = nbits - 1 - m
    if nbits > 64:
        return np.uint64(0), xa, xb, nw + 1  # corrupt: position beyond the end
    u = (np.uint64(1) << np.uint64(nbits - 1)) | (np.uint64((s - d) & ((1 << m) - 1)) << np.uint64(rem))
    shift = 0
    while rem > 0:
        k = min(rem, RAW_PIECE)
        v, xa, xb, pos = get_raw(xa, xb, pos, words, nw, k)
        u |= np.uint64(v) << np.uint64(shift)
        shift += k
        rem -= k
    return u, xa, xb, pos


@kernel(inline="always")
def get_value(xa, xb, pos, words, nw, sym, fb, t, log2d, m):
    """Decode a value put by :func:`put_value`: returns (value uint64, xa, xb, pos)."""
    s, xa, xb, pos = get_symbol(xa, xb, pos, words, nw, sym, fb, t)
    d = np.int64(1) << log2d
    if s < d:
        return np.uint64(s), xa, xb, pos
    return _get_escape(xa, xb, np.int64(pos), words, np.int64(nw), s, np.int64(d), np.int64(log2d), np.int64(m))


# get_symbol and get_value as helpers (LLVM inlines them): the range decoders' kernels
# (the quadtree's, the residuals', the interpolation order's, the mask's) call these. Measured
# against numba's inlining there side by side, one core and one thread each, four rounds with
# the cores swapped (ms a decode, best of 8): the 15 MP image lossless 305-317 against 318-337,
# within 0.1 mm 293-318 against 311-348, the 3 MP synthetic image 50-52 (one 68) against 54-56;
# both codecs' kernels compiled in 30.3-34.5 s against 31.5-38.2 s (three rounds side by side).
# Separate functions, not one wrapped twice: numba's cache names its files after the function,
# and a helper and a kernel of one function would share them.
@helper
def read_symbol(xa, xb, pos, words, nw, sym, fb, t):
    """:func:`get_symbol`, LLVM-inlined."""
    slot = xa & (PROB_SCALE - 1)
    s = np.int64(sym[t, slot])
    e = np.int64(fb[t, slot])
    xa = (e >> 16) * (xa >> PROB_BITS) + (e & 0xFFFF)
    xa, pos = _next(xa, pos, words, nw)
    return s, xb, xa, pos


@helper
def read_value(xa, xb, pos, words, nw, sym, fb, t, log2d, m):
    """:func:`get_value`, LLVM-inlined."""
    s, xa, xb, pos = read_symbol(xa, xb, pos, words, nw, sym, fb, t)
    d = np.int64(1) << log2d
    if s < d:
        return np.uint64(s), xa, xb, pos
    return _get_escape(xa, xb, np.int64(pos), words, np.int64(nw), s, np.int64(d), np.int64(log2d), np.int64(m))


@kernel
def pack_tables(freq):
    """Serialise the frequency tables: per table a varint count of its symbols up to the last
    used one (0 for an unused table), then each frequency as a varint."""
    nt, ns = freq.shape
    out = empty(nt * (ns * 3 + 3), np.uint8)
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


@kernel
def unpack_tables(buf, ntables):
    """Inverse of :func:`pack_tables`; returns (freq, bytes read) or (freq, -1) when malformed."""
    freq = zeros((ntables, NSYM), np.int32)
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
