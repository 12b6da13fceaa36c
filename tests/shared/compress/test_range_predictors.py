"""The range codec's lossless raster order (``quadtree-lp-10``): a leaf may predict from its N or
its W neighbour alone, and error feedback is kept only where the band codes smaller with it.

Each band decodes exactly and passes its check. On depth whose columns (or rows) wander on
their own, as a 1:1 camera's misread columns do, some leaves take N (W); on the Cyberware
dragon, on smooth oversampled depth and on noise correlated along the rows, the band with
feedback allowed is never larger than without (a least-squares fit of the neighbours' errors,
``quadtree-lp-9``'s, coded the dragon 4 % larger)."""

from __future__ import annotations

import numpy as np
import pytest

from shared.compress import _band as band
from shared.compress import _lpred as lp
from shared.compress import _quadtree as qt
from shared.compress import expected_lossless
from shared.compress.range import BAND_ROWS, _plan
from shared.core.datapaths import shared_data_dir
from tests.shared.compress.test_range_orders import band_bits, buffers, decoded, relief
from tests.support.range_scenes import dragon_range

#: The lossless quantum (mm) and the encoder's options at effort 1 and 2.
Q = 0.02
EFFORT_1 = lp.OPT_ALL & ~lp.OPT_WP
EFFORT_2 = lp.OPT_ALL


def wandering(h: int, w: int, axis: int, seed: int = 3) -> np.ndarray:
    """(h, w) float32 depth about 800 mm whose columns (``axis`` 0) or rows (1) are random walks
    of 0.1 mm steps, each on its own: only the sample before along the walk predicts a sample."""
    rng = np.random.default_rng(seed)
    return (800.0 + np.cumsum(rng.normal(0.0, 0.1, (h, w)), axis=axis)).astype(np.float32)


def row_correlated(h: int = 256, w: int = 320, rho: float = 0.9, seed: int = 0) -> np.ndarray:
    """A smooth curved surface with noise (0.05 mm innovations) correlated along each row (AR(1),
    ``rho``): the neighbours' errors predict a sample's."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 900.0 + 0.03 * xx - 0.02 * yy + 0.5 * np.sin(xx / 9.0) * np.sin(yy / 13.0)
    e = rng.normal(0.0, 0.05, (h, w))
    for x in range(1, w):
        e[:, x] += rho * e[:, x - 1]
    return (z + e).astype(np.float32)


def leaf_predictors(z: np.ndarray, opts: int = EFFORT_1) -> np.ndarray:
    """Each leaf's predictor count (NK,) of a lossless band's tree (the first margin's)."""
    t, valid = qt.quantise(z, _plan(z, Q, None).scale, True)
    tab, val, nb = buffers(t.size)
    n, signs = band._encode_events(t, valid, True, opts, float(qt.SPLIT_LOSSLESS[0]), 0.0, tab, val, nb)
    assert n > 0 and signs is not None
    return np.bincount(signs.leaves[:, 4], minlength=lp.NK)


@pytest.mark.parametrize("axis, k", [(0, lp.K_N), (1, lp.K_W)], ids=["columns: N", "rows: W"])
def test_wandering_columns_take_the_n_neighbour_and_rows_the_w(axis: int, k: int) -> None:
    z = wandering(128, 160, axis)
    counts = leaf_predictors(z)
    assert counts[k] > 0, counts
    other = lp.K_W if k == lp.K_N else lp.K_N
    assert counts[other] == 0, counts
    plan = _plan(z, Q, None)
    t, valid = qt.quantise(z, plan.scale, True)
    out = decoded(*band.encode_band(t, valid, True, EFFORT_1, plan.scale), z.shape, True, plan.scale)
    np.testing.assert_array_equal(out, expected_lossless(z, Q))


def _bands(z: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float]]:
    plan = _plan(z, Q, None)
    out = []
    for y in range(0, z.shape[0], BAND_ROWS):
        t, valid = qt.quantise(np.ascontiguousarray(z[y : y + BAND_ROWS]), plan.scale, True)
        out.append((t, valid, plan.scale))
    return out


def _images() -> list[tuple[str, np.ndarray]]:
    out = [("relief 2x2", relief()), ("relief 1x3", relief(hold=(1, 3))), ("row-correlated", row_correlated()),
           ("wandering columns", wandering(256, 320, 0))]
    if (shared_data_dir() / "stanford-dragon-turntable").is_dir():
        out += [(f"dragon {k}", dragon_range(k)[1]) for k in (0, 5)]
    return out


@pytest.mark.parametrize("opts", [EFFORT_1, EFFORT_2], ids=["effort 1", "effort 2"])
def test_error_feedback_never_codes_a_band_larger(opts: int) -> None:
    # every band with feedback allowed against the same band coded without it: kept only where
    # the band's stream is smaller with it, so never larger (the estimate the choice is made
    # on is the residuals' before sign contexts: a few bytes of slack for what they change)
    larger = []
    for name, z in _images():
        for i, (t, valid, scale) in enumerate(_bands(z)):
            a = band.encode_band(t, valid, True, opts, scale)
            b = band.encode_band(t, valid, True, opts & ~lp.OPT_FEEDBACK, scale)
            if band_bits(*a) > band_bits(*b) + 64:
                larger.append((name, i, band_bits(*a), band_bits(*b)))
            decoded(*a, t.shape, True, scale)  # decodes, and passes its check
    assert not larger, larger
