"""A range band's rows as the raster-order kernels see them (private; shared by
:mod:`shared.compress._lpred` and :mod:`shared.compress._ls`): the leaves' model predictions along
a row, and the reconstructed rows' padding and hole filling.

A reconstructed row is kept padded, pixel x at index x + 1 of a (W + 3,) int64 buffer: a hole
takes the value before it in its row (at the row's start, the one above), the pads repeat the
ends, and the virtual row above a band's first row is its own model predictions."""

from __future__ import annotations

from shared.core.jit import helper

MINB = 4
F_SHIFT = 5
FINE = 1 << F_SHIFT
A_SHIFT = 3  # slope coefficients in 2**-A_SHIFT fine units per half pixel
Q_SHIFT = 9  # curvature coefficients in 2**-Q_SHIFT fine units per half pixel squared


@helper(inline=False)
def row_prediction(y, W, cells, leaves, lcoef, row, krow):
    """Every leaf's model prediction (fine units) along row y into ``row`` (W,) int64 and its
    residual predictor into ``krow`` (W,) int64: the integers of the model's polynomial, with the
    linear and quadratic sums stepped along the row (adds only). ``leaves`` (n, 5): x0, y0, B,
    model, predictor; ``lcoef`` (n, 6)."""
    cy = y // MINB
    x = 0
    while x < W:
        i = cells[cy, x // MINB]
        if i < 0:
            x = (x // MINB + 1) * MINB
            continue
        x0 = leaves[i, 0]
        y0 = leaves[i, 1]
        B = leaves[i, 2]
        m = leaves[i, 3]
        k = leaves[i, 4]
        c0, c1, c2, c3, c4, c5 = lcoef[i, 0], lcoef[i, 1], lcoef[i, 2], lcoef[i, 3], lcoef[i, 4], lcoef[i, 5]
        if m < 2:
            c3 = 0
        if m < 3:
            c4 = 0
            c5 = 0
        if m < 1:
            c1 = 0
            c2 = 0
        X = 2 * (x - x0) - (B - 1)
        Y = 2 * (y - y0) - (B - 1)
        lin = c1 * X + c2 * Y
        quad = c3 * X * Y + c4 * X * X + c5 * Y * Y
        dq = c3 * 2 * Y + c4 * (4 * X + 4)
        end = min(x0 + B, W)
        for j in range(x, end):
            row[j] = c0 + (lin >> A_SHIFT) + (quad >> Q_SHIFT)
            krow[j] = k
            lin += 2 * c1
            quad += dq
            dq += 8 * c4
        x = end


@helper
def fill_row(ra, rb, valid, y, W):
    """Holes of the reconstructed row ``rb`` (padded, pixel x at x + 1) take the value before
    them in the row (at the row's start, the one above in ``ra``); the pads repeat the ends."""
    if not valid[y, 0]:
        rb[1] = ra[1]
    for x in range(1, W):
        if not valid[y, x]:
            rb[x + 1] = rb[x]
    rb[0] = rb[1]
    rb[W + 1] = rb[W]
    rb[W + 2] = rb[W]


@helper
def first_row(ra, pf, valid, W):
    """The virtual row above a band's first row: its own model predictions, holes filled."""
    for x in range(W):
        ra[x + 1] = pf[x]
    ra[1] = pf[0]
    for x in range(1, W):
        if not valid[0, x]:
            ra[x + 1] = ra[x]
    ra[0] = ra[1]
    ra[W + 1] = ra[W]
    ra[W + 2] = ra[W]


@helper(inline=False)
def target_row(y, t, valid, cells, leaves, lcoef, pf, kr, ra, rb):
    """Row y of a band's targets ``t`` (H, W) int64 into the padded row ``rb``, holes filled (the
    reconstruction in lossless mode, the open-loop estimate in bounded mode), and its leaves'
    model predictions and predictors into ``pf``, ``kr`` (:func:`row_prediction`); at the band's
    first row, the virtual row above into ``ra``."""
    W = t.shape[1]
    row_prediction(y, W, cells, leaves, lcoef, pf, kr)
    if y == 0:
        first_row(ra, pf, valid, W)
    for x in range(W):
        rb[x + 1] = t[y, x]
    fill_row(ra, rb, valid, y, W)
