"""The decoder's 32-bit and index-compaction intrinsics agree with the plain operations they stand for.

The decoder's bit-identity rests on them: ``compress_index`` must write exactly what the scalar
loop ``dst[n] = x; n += cond`` writes, for every mask of 16 lanes (NaN, -0.0 and negatives
included), on whatever vector unit LLVM targets; the int32 helpers must equal numba's 64-bit
operations on the values the decoder gives them.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from shared.core.bits import popcount
from shared.scan._i32 import (
    LANES,
    add32,
    and32,
    compress_index,
    eq32,
    ge32,
    gt32,
    le32,
    lt32,
    ne32,
    or32,
    shl32,
    shr32,
    sub32,
    xor32,
)


@numba.njit
def _compact_all(src, dst):  # pragma: no cover - compiled
    """Compact every whole block of LANES; return the count and each block's mask."""
    n = 0
    masks = np.empty(len(src) // LANES, np.int64)
    for b in range(len(src) // LANES):
        m = compress_index(src, b * LANES, dst, n)
        masks[b] = m
        n += popcount(m)
    return n, masks


@numba.njit
def _ops(a, b, s):  # pragma: no cover - compiled
    out = np.empty((len(a), 13), np.int64)
    for i in range(len(a)):
        x, y, k = a[i], b[i], s[i]
        out[i, 0] = and32(x, y)
        out[i, 1] = or32(x, y)
        out[i, 2] = xor32(x, y)
        out[i, 3] = add32(x, y)
        out[i, 4] = sub32(x, y)
        out[i, 5] = shl32(x & 0xFFFF, k)
        out[i, 6] = shr32(x & 0x7FFFFFFF, k)
        out[i, 7] = eq32(x, y)
        out[i, 8] = ne32(x, y)
        out[i, 9] = lt32(x, y)
        out[i, 10] = le32(x, y)
        out[i, 11] = gt32(x, y)
        out[i, 12] = ge32(x, y)
    return out


def _reference(src: np.ndarray) -> np.ndarray:
    keep = src >= 0.0 if src.dtype == np.float64 else src
    return np.flatnonzero(keep).astype(np.int32)


@pytest.mark.parametrize("dtype", [np.float64, np.bool_])
def test_compress_index_writes_what_the_scalar_loop_writes(dtype: type) -> None:
    rng = np.random.default_rng(7)
    n = LANES * 400
    if dtype is np.float64:
        src = rng.normal(size=n)
        special = rng.choice(n, n // 4, replace=False)
        src[special[: n // 12]] = np.nan  # NaN is not >= 0
        src[special[n // 12: n // 6]] = -0.0  # -0.0 >= 0.0 is true
        src[special[n // 6:]] = 0.0
        src[: LANES] = np.nan  # an empty block
        src[LANES: 2 * LANES] = 1.0  # a full one
    else:
        src = rng.random(n) < 0.3
        src[: LANES] = False
        src[LANES: 2 * LANES] = True
    dst = np.full(n, -1, np.int32)
    count, masks = _compact_all(src, dst)
    ref = _reference(src)
    assert count == len(ref)
    np.testing.assert_array_equal(dst[:count], ref)
    assert (dst[count:] == -1).all()  # nothing written past the kept indices
    keep = (src >= 0.0) if dtype is np.float64 else src
    bits = (keep.reshape(-1, LANES) * (1 << np.arange(LANES))).sum(1)
    np.testing.assert_array_equal(masks, bits)
    assert masks[0] == 0 and masks[1] == (1 << LANES) - 1


def test_int32_helpers_equal_the_64_bit_operations_in_range() -> None:
    rng = np.random.default_rng(3)
    a = rng.integers(-(2**30), 2**30, 5000)
    b = np.where(rng.random(5000) < 0.2, a, rng.integers(-(2**30), 2**30, 5000))
    s = rng.integers(0, 16, 5000)
    got = _ops(a, b, s)
    want = np.stack([a & b, a | b, a ^ b, a + b, a - b, (a & 0xFFFF) << s, (a & 0x7FFFFFFF) >> s,
                     a == b, a != b, a < b, a <= b, a > b, a >= b], 1).astype(np.int64)  # fmt: skip
    np.testing.assert_array_equal(got, want)
