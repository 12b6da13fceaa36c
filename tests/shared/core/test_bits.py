import numba
import numpy as np

from shared.core.bits import popcount


@numba.njit
def _counts(v):  # pragma: no cover - compiled
    out = np.empty(len(v), np.int64)
    for i in range(len(v)):
        out[i] = popcount(v[i])
    return out


def test_popcount_counts_set_bits_of_every_integer_type() -> None:
    rng = np.random.default_rng(7)
    v = np.concatenate([np.array([0, 1, 0xFFFF, 2**62, -1, 0x5555], np.int64),
                        rng.integers(-(2**63), 2**63 - 1, 1000, dtype=np.int64)])  # fmt: skip
    want = [bin(int(x) & (2**64 - 1)).count("1") for x in v]
    np.testing.assert_array_equal(_counts(v), want)
    # Narrower and unsigned types count their own bits (cast to int64 keeps the value).
    for dtype in (np.uint8, np.uint16, np.int32, np.uint64):
        w = rng.integers(0, np.iinfo(dtype).max, 200, dtype=dtype, endpoint=True)
        np.testing.assert_array_equal(_counts(w), [bin(int(x)).count("1") for x in w])
