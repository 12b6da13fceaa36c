"""A self-correcting weighted predictor for range bands (private kernels of :mod:`shared.compress._lpred`).

After the weighted predictor of JPEG-XL's modular mode (Alakuijala et al., "JPEG XL next-generation
image compression architecture", 2019; the "self-correcting predictor" of ISO/IEC 18181-1 H.5),
written from its public description: four sub-predictors of a sample from its reconstructed
neighbours W, N, NW, NE (fine units) and the signed errors ``te`` of the weighted prediction at
W, N, NW, NE --

- ``W + NE - N`` (the plane along the row above's slope),
- N, W and N again, each corrected by a share of the neighbours' errors (the image's recent
  bias: 16/32 of teW + teN + teNE, 10/32 of teW + teN + teNW, 7/32 of teNW + teN + teNE) --

averaged with weights that fall as 1 / (the sub-predictor's absolute errors at N, NW, NE, W
and WW), so each pixel follows whichever sub-predictor has lately been right. Where the
neighbours' errors disagree in sign the average is clamped to the range of W, N, NE. The
largest of the neighbours' errors (:func:`wp_predict`'s second value) measures how well the
predictor is doing here: the coding context of a band that uses it.

Everything is integers (the decoder runs the same arithmetic): sub-predictor errors are kept
in quanta (fine units >> :data:`ERR_SHIFT`; shifts of 2 and 3 coded within 0.05 % of it), and
the weights' reciprocals and the average's division come from one table of 64 entries.

State: two rows (above, current) of the four sub-predictors' absolute errors ``err`` (4, W + 4)
int64 and of the signed errors ``te`` (W + 4,) int64, pixel x at index x + 2 (zero padding at
both ends). Holes have zero errors.
"""

from __future__ import annotations

import numpy as np
from numba.cpython.unsafe.numbers import leading_zeros

from shared.compress._rans import at
from shared.core.jit import helper

#: Sub-predictor errors in fine units >> ERR_SHIFT (quanta).
ERR_SHIFT = 5
#: (1 << 24) // (v + 1) for the weights' reciprocals (v < 64 after the shift).
RECIP24 = np.array([(1 << 24) // (v + 1) for v in range(64)], np.int64)
#: Differences from N are clamped to this many fine units before they are weighed (hostile
#: inputs: products with the weights and the reciprocal stay inside int64).
D_LIM = 1 << 30
#: Signed errors are clamped to this many fine units.
TE_LIM = 1 << 40


@helper(inline=False)
def _floor_log2(v):
    """floor(log2(v)) of an integer v >= 1 (one count-leading-zeros instruction)."""
    return 63 - np.int64(leading_zeros(np.uint64(v)))


@helper(inline=False)
def _weight(s, mw):
    """The weight of a sub-predictor of summed recent errors ``s`` >= 0 and largest weight ``mw``."""
    sh = max(_floor_log2(s + 1) - 5, 0)
    return 4 + ((mw * at(RECIP24, s >> sh)) >> sh)


@helper(inline=False)
def _err_sum(err_a, err_b, k, i):
    """Sub-predictor k's errors at N, NW, NE, W and WW of pixel index i."""
    return err_a[k, i] + err_a[k, i - 1] + err_a[k, i + 1] + err_b[k, i - 1] + err_b[k, i - 2]


@helper(inline=False)
def wp_predict(x, a, b, c, d, err_a, err_b, te_a, te_b, sub):
    """The weighted prediction (fine units) of pixel x from its neighbours W ``a``, N ``b``, NW
    ``c``, NE ``d`` and the error rows (above ``*_a``, current ``*_b``); ``sub`` (4,) int64
    receives the sub-predictions for :func:`wp_update`. Returns (prediction, the largest
    |signed error| at W, N, NW, NE)."""
    i = x + 2
    tw = at(te_b, i - 1)
    tn = at(te_a, i)
    tnw = at(te_a, i - 1)
    tne = at(te_a, i + 1)
    sub[0] = a + d - b
    sub[1] = b - (((tw + tn + tne) * 16) >> 5)
    sub[2] = a - (((tw + tn + tnw) * 10) >> 5)
    sub[3] = b - (((tnw + tn + tne) * 7) >> 5)
    # int64 values, not literals: the helpers are compiled once, not once a literal value
    w0 = _weight(_err_sum(err_a, err_b, np.int64(0), i), np.int64(13))  # JPEG-XL's default largest weights
    w1 = _weight(_err_sum(err_a, err_b, np.int64(1), i), np.int64(12))
    w2 = _weight(_err_sum(err_a, err_b, np.int64(2), i), np.int64(12))
    w3 = _weight(_err_sum(err_a, err_b, np.int64(3), i), np.int64(12))
    sh = _floor_log2(w0 + w1 + w2 + w3) - 4
    w0 >>= sh
    w1 >>= sh
    w2 >>= sh
    w3 >>= sh
    ws = w0 + w1 + w2 + w3
    acc = ((ws >> 1) - 1 + w0 * min(max(sub[0] - b, -D_LIM), D_LIM) + w1 * min(max(sub[1] - b, -D_LIM), D_LIM)
           + w2 * min(max(sub[2] - b, -D_LIM), D_LIM) + w3 * min(max(sub[3] - b, -D_LIM), D_LIM))
    p = b + ((acc * at(RECIP24, ws - 1)) >> 24)
    if not ((tn ^ tw) >= 0 and (tn ^ tnw) >= 0):
        # the neighbours' errors disagree: stay within W, N, NE
        p = min(max(p, min(a, min(b, d))), max(a, max(b, d)))
    m = max(max(abs(tw), abs(tn)), max(abs(tnw), abs(tne)))
    return p, m


@helper(inline=False)
def wp_update(x, v, p, sub, err_b, te_b):
    """Record pixel x's reconstructed value ``v`` against its weighted prediction ``p`` and
    sub-predictions ``sub``."""
    i = x + 2
    r = 1 << (ERR_SHIFT - 1)
    for k in range(4):
        e = min(abs(sub[k] - v), TE_LIM)
        err_b[k, i] = (e + r) >> ERR_SHIFT
    te_b[i] = min(max(p - v, -TE_LIM), TE_LIM)


@helper(inline=False)
def wp_hole(x, err_b, te_b):
    """A hole at pixel x: no errors."""
    i = x + 2
    for k in range(4):
        err_b[k, i] = 0
    te_b[i] = 0
