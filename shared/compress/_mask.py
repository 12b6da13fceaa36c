"""A range band's validity mask (private kernels of :mod:`shared.compress._quadtree`), coded
either as runs row by row against the row above, or sample by sample in context.

A row is a sequence of runs, invalid first (possibly empty), then valid, and so on. Each run's
end -- where the next run starts -- is coded as one symbol of the table of the run's state
(``t_edge`` + state): like fax group 4's vertical mode, the distance (within
:data:`VERT` samples) to the first run of the same new state starting at or after the run's
start in the row above; else an explicit length (the symbol :data:`EXPLICIT`, then the length
in the run tables :data:`T_RUN` + state); or :data:`END`, the run goes to the end of the row.
The row above a band's first row has no runs (every end is explicit there). Scanned surfaces'
silhouettes and holes move little from row to row: on the Cyberware dragon scans (about 3.5 % and
5 % of their valid samples start or end a run) the mask cost 0.26 and 0.35 bits per valid sample
as plain run lengths per row, 0.14 and 0.19 so.

A real structured-light capture's holes are speckle, not silhouettes: where the stripes' contrast
is low, pixels fail to decode at random, in streaks along the stripes. There each sample is a
binary event with the adaptive probability of its context (as JBIG's generic region coding:
the 10 samples of a three-line template, above the band and past its sides holes), which the
encoder takes where it codes fewer bits than the runs. Measured per band
of 256 rows, bits per valid sample: the five kamino410 captures 0.203 / 0.349 / 0.276 / 0.419 /
0.410 as runs, 0.151 / 0.239 / 0.200 / 0.301 / 0.292 in context; the Cyberware dragons 0.148 /
0.193 and 0.115 / 0.149; the simulated relief and bunny (silhouettes) 0.001 and 0.006 as runs,
more in context.
"""

from __future__ import annotations

import numpy as np

from shared.compress._rans import (
    BIN,
    MODEL_INIT,
    get_bit,
    model_p,
    model_update,
    put,
    put_value,
    read_symbol,
    read_value,
)
from shared.core.jit import empty, full, helper, kernel, zeros

#: Tables (set by :mod:`shared.compress._quadtree`): the run lengths by state, the edges by state.
T_RUN = 8
L_RUN = 4
#: Edge symbols: 0 .. 2 VERT are the distances -VERT .. VERT; then explicit; then end of row.
VERT = 3
EXPLICIT = 2 * VERT + 1
END = EXPLICIT + 1
#: A band's mask coder (a symbol before its mask, in the callers' table): the runs above, or
#: every sample a binary event in the context of its template (:func:`encode_mask_ctx`).
MASK_RUNS = 0
MASK_CTX = 1
#: The context coder's models: JBIG's three-line template of 10 decoded samples.
NCTX_MASK = 1 << 10


@helper
def _start_above(ref, j, s, x):
    """The row above's first start of a run of state ``s`` at or after ``x`` (``ref[s]``, ended by
    W), its cursor ``j[s]`` moved on to it: the encoder and the decoder read the same one."""
    k = j[s]
    while ref[s, k] < x:
        k += 1
    j[s] = k
    return ref[s, k]


@helper(inline=False)
def encode_mask(valid, tab, val, nb, n, t_edge):
    """Append the events of the mask ``valid`` (H, W) bool after event ``n``; returns the count
    (or -1 when the buffers are full)."""
    H, W = valid.shape
    ref = empty((2, W + 2), np.int64)
    j = zeros(2, np.int64)  # cursors into ref[0] and ref[1]
    cur = empty((2, W + 2), np.int64)
    ref[0, 0] = W  # the row above the first: no runs
    ref[1, 0] = W
    for y in range(H):
        row = valid[y]
        j[0] = 0  # the first start in ref[0] / ref[1] at or after x
        j[1] = 0
        n0 = 0
        n1 = 0
        x = 0
        state = False
        while x < W:
            e = x
            while e < W and row[e] == state:
                e += 1
            s = 1 if state else 0
            if e >= W:
                n = put(tab, val, nb, n, t_edge + s, END, 0)
                break
            # a run of the new state starts at e: the row above's first such start from x on
            b = _start_above(ref, j, s, x)
            if b < W and abs(e - b) <= VERT:
                n = put(tab, val, nb, n, t_edge + s, e - b + VERT, 0)
            else:
                n = put(tab, val, nb, n, t_edge + s, EXPLICIT, 0)
                n = put_value(tab, val, nb, n, T_RUN + s, e - x, L_RUN, 0)
            if s == 0:
                cur[0, n0] = e  # the row's runs' starts, for the next row
                n0 += 1
            else:
                cur[1, n1] = e
                n1 += 1
            x = e
            state = not state
        cur[0, n0] = W
        cur[1, n1] = W
        ref, cur = cur, ref
    return n


@kernel
def decode_mask(xa, xb, pos, words, nw, sym, fb, valid, t_edge):
    """Inverse of :func:`encode_mask` into ``valid`` (H, W) bool (all False on entry); returns
    (ok, xa, xb, pos), ok False for a corrupt stream."""
    H, W = valid.shape
    ref = empty((2, W + 2), np.int64)
    j = zeros(2, np.int64)  # cursors into ref[0] and ref[1]
    cur = empty((2, W + 2), np.int64)
    ref[0, 0] = W
    ref[1, 0] = W
    for y in range(H):
        row = valid[y]
        j[0] = 0
        j[1] = 0
        n0 = 0
        n1 = 0
        x = 0
        state = False
        while True:
            s = 1 if state else 0
            c, xa, xb, pos = read_symbol(xa, xb, pos, words, nw, sym, fb, t_edge + s)
            if pos > nw or c > END:
                return False, xa, xb, pos
            if c == END:
                e = W
            elif c == EXPLICIT:
                u, xa, xb, pos = read_value(xa, xb, pos, words, nw, sym, fb, T_RUN + s, L_RUN, 0)
                if u >= np.uint64(W):
                    return False, xa, xb, pos
                e = x + np.int64(u)
            else:
                b = _start_above(ref, j, s, x)
                if b >= W:
                    return False, xa, xb, pos
                e = b + c - VERT
            # a run is empty only at the row's start, and an edge inside the row ends it
            if e < x or (e == x and x > 0) or e > W or (e == W and c != END):
                return False, xa, xb, pos
            if state:
                for i in range(x, e):
                    row[i] = True
            elif e < W:
                cur[0, n0] = e  # the row's runs' starts, for the next row
                n0 += 1
            if state and e < W:
                cur[1, n1] = e
                n1 += 1
            x = e
            state = not state
            if e >= W:
                break
        cur[0, n0] = W
        cur[1, n1] = W
        ref, cur = cur, ref
    return True, xa, xb, pos


@helper
def _template(r0, r1, r2, i):
    """The context of padded index ``i`` (sample i - 2) from the padded rows (W + 4,) int64 of
    0/1: W, WW in its row ``r0``; NWW, NW, N, NE, NEE in ``r1``; NNW, NN, NNE in ``r2``."""
    return (r0[i - 1] | (r0[i - 2] << 1) | (r1[i - 2] << 2) | (r1[i - 1] << 3) | (r1[i] << 4) | (r1[i + 1] << 5)
            | (r1[i + 2] << 6) | (r2[i - 1] << 7) | (r2[i] << 8) | (r2[i + 1] << 9))


@helper
def _ctx_state(W):
    """The context coder's state at a band's start: its models, and its three padded rows
    (W + 4,) int64 (the current one and the two above; holes above the band and past its sides)."""
    return (full(NCTX_MASK, MODEL_INIT, np.uint32), zeros(W + 4, np.int64), zeros(W + 4, np.int64),
            zeros(W + 4, np.int64))


@kernel
def encode_mask_ctx(valid, tab, val, nb, n):
    """Append the mask ``valid`` (H, W) bool as a binary event a sample, in the context of its
    template (:func:`_template`), after event ``n``; returns the count (or -1 when the buffers
    are full)."""
    H, W = valid.shape
    models, r0, r1, r2 = _ctx_state(W)
    for y in range(H):
        for x in range(W):
            i = x + 2
            c = _template(r0, r1, r2, i)
            bit = 1 if valid[y, x] else 0
            n = put(tab, val, nb, n, BIN, (model_p(models, c) << 1) | bit, 0)
            model_update(models, c, bit)
            r0[i] = bit
        r0, r1, r2 = r2, r0, r1
    return n


@kernel
def decode_mask_ctx(xa, xb, pos, words, nw, valid):
    """Inverse of :func:`encode_mask_ctx` into ``valid`` (H, W) bool; returns (ok, xa, xb, pos)."""
    H, W = valid.shape
    models, r0, r1, r2 = _ctx_state(W)
    for y in range(H):
        row = valid[y]
        for x in range(W):
            i = x + 2
            c = _template(r0, r1, r2, i)
            bit, xa, xb, pos = get_bit(xa, xb, pos, words, nw, model_p(models, c))
            model_update(models, c, bit)
            r0[i] = bit
            row[x] = bit == 1
        r0, r1, r2 = r2, r0, r1
        if pos > nw:
            return False, xa, xb, pos
    return True, xa, xb, pos
