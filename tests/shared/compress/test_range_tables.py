"""The range codec's residual tables (``quadtree-lp-7``): the activity levels partitioned into
runs, one table a run, by the bits the coder spends (code lengths and stored tables), which the
estimate matches; the partition never costs more than the tables' sliding and merging; values
whose escape symbol carries the bits below their top bit round-trip at every bit length."""

from __future__ import annotations

import numpy as np
import pytest

from shared.compress import _levels as lv
from shared.compress import _lpred as lp
from shared.compress._rans import (
    NSYM,
    count_symbols,
    dec_init,
    decode_tables,
    encode_events,
    get_value,
    normalise,
    put_value,
    symbol_of,
)
from shared.compress._tables import pack_codes, quantise_tables, table_bits
from shared.core.jit import kernel


def laplacian(n: int, scale: float, rng: np.random.Generator) -> np.ndarray:
    """Zigzagged residuals of ``n`` samples, Laplacian of ``scale`` quanta, as direct symbols."""
    r = np.round(rng.laplace(0.0, scale, n)).astype(np.int64)
    u = np.where(r >= 0, 2 * r, -2 * r - 1)
    return np.minimum(u, 255)


def coded_bits(symbols: np.ndarray) -> int:
    """The bits of a stream of ``symbols`` in one table: its rANS words and its stored table."""
    n = symbols.size
    tab, val, nb = np.zeros(n, np.int8), symbols.astype(np.int16), np.zeros(n, np.int8)
    codes, freq = quantise_tables(normalise(count_symbols(tab, val, np.int64(n), np.int64(1))))
    return 16 * encode_events(tab, val, nb, np.int64(n), freq).size + 8 * pack_codes(codes).size


@pytest.mark.parametrize("n, scale", [(30, 20.0), (2000, 3.0), (200000, 40.0)])
def test_a_tables_bits_are_what_the_coder_spends(n: int, scale: float) -> None:
    symbols = laplacian(n, scale, np.random.default_rng(n))
    counts = np.bincount(symbols, minlength=NSYM)[None, :].astype(np.int64)
    est = table_bits(counts)
    assert abs(coded_bits(symbols) - est) <= 0.002 * est + 72  # the stream's start and end, bytes' padding


def _counts(levels: dict[int, tuple[int, float]], seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    counts = np.zeros((lp.NLEVEL, NSYM), np.int64)
    for lev, (n, scale) in levels.items():
        counts[lev] = np.bincount(laplacian(n, scale, rng), minlength=NSYM)
    return counts


def _exact_bits(counts: np.ndarray, lut: np.ndarray) -> float:
    merged = np.zeros((lp.NLEVEL, NSYM), np.int64)
    np.add.at(merged, lut, counts)
    return sum(table_bits(merged[k : k + 1]) for k in range(lp.NLEVEL))


@pytest.mark.parametrize("seed", range(3))
def test_the_partition_is_a_valid_one_and_never_costs_more_than_sliding_and_merging(seed: int) -> None:
    rng = np.random.default_rng(seed)
    levels = {lev: (int(rng.integers(0, 3000)) if rng.random() < 0.7 else 0, 0.5 * 1.41 ** (lev / 2))
              for lev in range(lp.NLEVEL)}
    counts = _counts(levels, seed)
    bits, lut = lv.level_partition(counts, 0.0)
    np.testing.assert_array_equal(lv.partition_tables(np.diff(lut)), lut)  # what the decoder rebuilds
    assert bits == pytest.approx(_exact_bits(counts, lut))
    for cofs in range(lp.MAX_COFS + 1):
        for cshift in range(3):
            assert bits <= _exact_bits(counts, lv.level_tables(np.int64(cofs), np.int64(cshift))) + 1e-6


def test_quiet_levels_share_a_table_and_busy_ones_keep_their_own() -> None:
    # a real capture's quiet levels hold a few dozen residuals each, spread over a hundred
    # symbols: each table stored would cost more than the levels' distributions differ
    counts = _counts({12: (30, 20.0), 13: (40, 25.0), 14: (35, 30.0), 20: (100000, 4.0), 21: (100000, 8.0)})
    lut = lv.level_partition(counts, 0.0)[1]
    assert lut[12] == lut[13] == lut[14]
    assert len({lut[14], lut[20], lut[21]}) == 3


# put_value and symbol_of are kernel helpers (no Python entry point): called here through
# kernels of the test's own
@kernel(cache=False)
def _put_value(tab, val, nb, n, t, u, log2d, m):
    return put_value(tab, val, nb, n, t, u, log2d, m)


@kernel(cache=False)
def _symbol_of(u, log2d, m):
    return symbol_of(u, log2d, m)


def _coded_values(values: np.ndarray, log2d: int, m: int) -> np.ndarray:
    """``values`` put by ``put_value`` in one table and decoded back."""
    cap = 8 * values.size + 64
    tab, val, nb = np.zeros(cap, np.int8), np.zeros(cap, np.int16), np.zeros(cap, np.int8)
    n = np.int64(0)
    for u in values:
        n = _put_value(tab, val, nb, n, np.int64(0), np.uint64(u), np.int64(log2d), np.int64(m))
    freq = quantise_tables(normalise(count_symbols(tab, val, n, np.int64(1))))[1]
    words = encode_events(tab, val, nb, n, freq)
    sym, fb = decode_tables(freq)
    xa, xb, pos = dec_init(words)
    out = np.zeros(values.size, np.uint64)
    for i in range(values.size):
        out[i], xa, xb, pos = get_value(xa, xb, pos, words, np.int64(words.size), sym, fb, np.int64(0), np.int64(log2d),
                                        np.int64(m))
    assert pos == words.size
    return out


@pytest.mark.parametrize("log2d, m", [(8, 2), (8, 0), (4, 0), (2, 2)])
def test_values_with_bits_in_their_escape_symbol_round_trip(log2d: int, m: int) -> None:
    # the residuals' escapes carry the two bits below a value's top bit (M_RES); every bit
    # length up to 64 bits, and the values either side of each power of two
    edges = [v for k in range(1, 64) for v in ((1 << k) - 1, 1 << k, (1 << k) + 1, (1 << k) + (1 << (k - 1)))]
    values = np.array([0, 1, 2, 3, *edges, (1 << 64) - 1], np.uint64)
    np.testing.assert_array_equal(_coded_values(values, log2d, m), values)
    # the symbols counted for the sign contexts' estimate are the ones put
    tab, val, nb = np.zeros(8, np.int8), np.zeros(8, np.int16), np.zeros(8, np.int8)
    for u in values[values < (1 << 62)]:
        _put_value(tab, val, nb, np.int64(0), np.int64(0), np.uint64(u), np.int64(log2d), np.int64(m))
        assert _symbol_of(np.int64(u), np.int64(log2d), np.int64(m)) == val[0]
