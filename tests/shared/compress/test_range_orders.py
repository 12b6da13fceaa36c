"""The range codec's per-band choices of ``quadtree-lp-7``: hierarchical interpolation (bounded
mode) with its feedback weights per spacing and pass and its sign contexts, and the raster
order's sign contexts (both modes): each is taken where it codes smaller, its streams decode
exactly (lossless) or within the bound (every sample), masks exact, on smooth oversampled depth
and on hostile masks and shapes; an interpolation stream is refused in a lossless band, and
so are its damaged headers."""

from __future__ import annotations

import numpy as np
import pytest

from shared.compress import _band as band
from shared.compress import _levels, expected_lossless
from shared.compress import _lpred as lp
from shared.compress import _quadtree as qt
from shared.compress._check import fold, output_check
from shared.compress.range import _plan


def relief(h: int = 256, w: int = 320, seed: int = 0, hold: tuple[int, int] = (2, 2)) -> np.ndarray:
    """Oversampled smooth detailed depth as a fine camera over a coarser projector sees it: a
    tilted, curved surface with carved ridges, sub-pixel noise about 0.04 mm held constant over
    blocks of ``hold`` (rows, columns) camera pixels (one projector pixel at 2:1), a small
    shadow hole."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 700.0 + 0.03 * xx - 0.02 * yy + 0.0002 * (xx - w / 2) ** 2 + 0.8 * np.sin(xx / 7.0) * np.sin(yy / 11.0)
    hy, hx = hold
    z += np.kron(rng.normal(0.0, 0.04, (h // hy + 1, w // hx + 1)), np.ones(hold))[:h, :w]
    z[(xx - 0.3 * w) ** 2 + (yy - 0.6 * h) ** 2 < 60] = np.nan
    return z.astype(np.float32)


def buffers(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Event buffers (tables, values, raw bit counts) for a band of ``size`` samples."""
    cap = 2 * size + 4096
    return np.empty(cap, np.int8), np.empty(cap, np.int16), np.empty(cap, np.int8)


def band_bits(tables: np.ndarray, words: np.ndarray, check: int = 0) -> int:
    """A band's stream's bits (``check``, stored beside it in every band alike, left out)."""
    return int(tables.size * 8 + words.size * 16)


def decoded(tables: np.ndarray, words: np.ndarray, check: int, shape: tuple[int, int], lossless: bool,
            scale: float) -> np.ndarray:
    """The band decoded, its samples passing the check the encoder gave them."""
    out = np.empty(shape, np.float32)
    assert band.decode_band(tables, words, shape[0], shape[1], lossless, scale, out) == 0
    assert output_check(out.view(np.uint32)) == check
    return out


def check_bound(z: np.ndarray, out: np.ndarray, e: float) -> None:
    mask = ~np.isnan(z)
    np.testing.assert_array_equal(np.isnan(out), ~mask)
    if mask.any():
        assert np.abs(out[mask].astype(np.float64) - z[mask]).max() <= e


def test_interpolation_is_taken_on_smooth_oversampled_depth_within_the_bound() -> None:
    z = relief()
    plan = _plan(z, None, 0.1)
    t, valid = qt.quantise(z, plan.scale, False)
    with_interp = band.encode_band(t, valid, False, lp.OPT_ALL, plan.scale)
    without = band.encode_band(t, valid, False, lp.OPT_ALL & ~lp.OPT_INTERP, plan.scale)
    # interpolation predicts each sample from both sides: smaller here by a clear margin
    assert band_bits(*with_interp) < 0.95 * band_bits(*without), (band_bits(*with_interp), band_bits(*without))
    check_bound(z, decoded(*with_interp, z.shape, False, plan.scale), 0.1)
    check_bound(z, decoded(*without, z.shape, False, plan.scale), 0.1)


def test_noise_keeps_the_raster_order() -> None:
    # white noise of 0.5 mm within 0.1 mm: interpolation's two-sided mean does not pay, the
    # encoder keeps the raster order (the stream is the one coded without the option)
    rng = np.random.default_rng(1)
    z = (800.0 + rng.normal(0.0, 0.5, (128, 200))).astype(np.float32)
    plan = _plan(z, None, 0.1)
    t, valid = qt.quantise(z, plan.scale, False)
    a = band.encode_band(t, valid, False, lp.OPT_ALL, plan.scale)
    b = band.encode_band(t, valid, False, lp.OPT_ALL & ~lp.OPT_INTERP, plan.scale)
    assert band_bits(*a) == band_bits(*b)
    check_bound(z, decoded(*a, z.shape, False, plan.scale), 0.1)


def _masks() -> list[tuple[str, np.ndarray]]:
    rng = np.random.default_rng(7)
    out = []
    for h, w in [(1, 1), (1, 37), (37, 1), (17, 33), (64, 70), (256, 45)]:
        z = (500.0 + 0.1 * np.arange(w)[None, :] + rng.normal(0, 0.05, (h, w))).astype(np.float32)
        for share in (0.0, 0.3, 0.9):
            zz = z.copy()
            zz[rng.random(z.shape) < share] = np.nan
            out.append((f"{h}x{w} {int(share * 100)} % holes", zz))
    board = np.where(np.indices((48, 48)).sum(0) % 2 == 0, 640.0, np.nan).astype(np.float32)
    out.append(("checkerboard", board))
    grid = np.full((80, 96), 300.0, np.float32)
    grid[::16, :] = np.nan  # every coarse grid row a hole: predictions fall back
    grid[:, ::16] = np.nan
    out.append(("holes on the coarse grid", grid))
    out.append(("all holes", np.full((20, 30), np.nan, np.float32)))
    jumps = np.where(np.indices((64, 64))[1] % 5 < 2, 2000.0, -1500.0).astype(np.float32)
    out.append(("depth jumps of 3.5 m", jumps))
    return out


@pytest.mark.parametrize("name, z", _masks(), ids=[n for n, _ in _masks()])
@pytest.mark.parametrize("e", [0.1, 2.0])
@pytest.mark.parametrize("way", [1, 0])
def test_interpolation_streams_decode_within_the_bound_on_hostile_masks(name: str, z: np.ndarray, e: float,
                                                                       way: int) -> None:
    # the interpolation order's stream itself (whatever the encoder would choose), in sign
    # contexts (1) and in level tables (0)
    plan = _plan(np.nan_to_num(z, nan=0.0) if np.isnan(z).all() else z, None, e)
    t, valid = qt.quantise(z, plan.scale, False)
    tab, val, nb = buffers(z.size)
    n, _, h = band._interp_band(t, valid, tab, val, nb, force=way, scale=plan.scale)
    assert n >= 0
    check_bound(z, decoded(*band._pack(tab, val, nb, n), int(fold(np.uint64(h))), z.shape, False, plan.scale), e)


def _interp_stream(z: np.ndarray, opts: int = lp.OPT_ALL, force: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    plan = _plan(z, None, 0.1)
    t, valid = qt.quantise(z, plan.scale, False)
    tab, val, nb = buffers(z.size)
    n, _, h = band._interp_band(t, valid, tab, val, nb, opts=opts, force=force, scale=plan.scale)
    assert n >= 0
    tables, words = band._pack(tab, val, nb, n)
    check_bound(z, decoded(tables, words, int(fold(np.uint64(h))), z.shape, False, plan.scale), 0.1)
    return tables, words


def test_interpolation_feedback_pays_on_errors_held_along_rows() -> None:
    # an oversampling camera's sub-pixel errors held over 3 columns of a row: the error of the
    # sample before in a pass-row predicts the next; the weights chosen per spacing and pass
    # code smaller than none
    z = relief(384, 320, hold=(1, 3))
    with_fb = _interp_stream(z)
    without = _interp_stream(z, lp.OPT_ALL & ~lp.OPT_FEEDBACK)
    assert band_bits(*with_fb) < 0.95 * band_bits(*without), (band_bits(*with_fb), band_bits(*without))


def test_interpolation_sign_contexts_pay_on_errors_held_along_rows() -> None:
    z = relief(384, 320, hold=(1, 3))
    with_signs = _interp_stream(z)
    without = _interp_stream(z, lp.OPT_ALL & ~lp.OPT_SIGN)
    assert band_bits(*with_signs) < 0.98 * band_bits(*without), (band_bits(*with_signs), band_bits(*without))


def test_feedback_choice_takes_the_candidate_of_fewest_bits() -> None:
    from shared.compress._interp import FB_CAND, HB, HG, NCAND, NLV

    rng = np.random.default_rng(3)
    hist = np.zeros((NLV, 2, NCAND, HG, HB), np.int64)
    best = rng.integers(0, NCAND, (NLV, 2))
    best[0, 0] = NCAND - 1  # one at least away from the first pass's weights
    for lv in range(NLV):
        for k in range(2):
            for c in range(NCAND):
                # the same symbols spread wider the farther a candidate is from the best one
                spread = 1 + 2 * abs(c - best[lv, k])
                sym = np.minimum(np.abs(rng.normal(0, spread, 4000)).astype(np.int64), HB - 1)
                np.add.at(hist[lv, k, c, lv % HG], sym, 1)
    chosen, share = band.feedback_choice(hist)
    np.testing.assert_array_equal(chosen, FB_CAND[best])
    # the share of the first pass's bits: below 1 unless every best weight is the first's
    assert 0.0 < share < 1.0
    # large residuals weigh by their size: 100 residuals of about 11 bits cost more than 1000
    # zeros and 1000 ones
    # (in entropy alone the first candidate's 2100 symbols would cost 2579 bits, the others'
    # 3328)
    wide = np.zeros((NLV, 2, NCAND, HG, HB), np.int64)
    wide[:, :, 0, 0, :2] = 1000
    wide[:, :, 0, 0, HB - 1] = 100
    wide[:, :, 1:, 0, :3] = 700
    assert (band.feedback_choice(wide)[0] == FB_CAND[1]).all()


@pytest.mark.parametrize("at", range(12))
def test_a_damaged_interpolation_header_is_refused(at: int) -> None:
    # each symbol of the band's header after its mode (offset, merging, sign flag, the eight
    # weights) set out of range: the band is refused, never read outside its arrays
    z = relief(64, 64)
    plan = _plan(z, None, 0.1)
    t, valid = qt.quantise(z, plan.scale, False)
    tab, val, nb = buffers(z.size)
    n, _, _ = band._interp_band(t, valid, tab, val, nb)
    head = np.flatnonzero(tab[:n] == qt.T_PRED)[1:]  # after the mask's coder: the mode, then the header
    assert head.shape[0] == 12 and val[head[0]] == qt.MODE_INTERP
    val[head[at]] = 200
    out = np.empty(z.shape, np.float32)
    tables, words = band._pack(tab, val, nb, n)
    assert band.decode_band(tables, words, 64, 64, False, plan.scale, out) == -1


def test_an_interpolation_stream_in_a_lossless_band_is_refused() -> None:
    z = relief(64, 64)
    t, valid = qt.quantise(z, 0.02, True)
    tab, val, nb = buffers(z.size)
    n, _, _ = band._interp_band(t, valid, tab, val, nb)
    tables, words = band._pack(tab, val, nb, n)
    out = np.empty(z.shape, np.float32)
    assert band.decode_band(tables, words, 64, 64, True, 0.02, out) == -1


@pytest.mark.parametrize("lossless", [True, False])
def test_sign_contexts_are_taken_where_smaller_and_round_trip(lossless: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    # sub-pixel errors held along a stripe (4 rows) leave the N neighbour's residual sign
    # telling: lossless, the band takes sign contexts and codes smaller; within 0.1 mm the
    # levels' tables partitioned code smaller than sign contexts (measured 54048 against 54128
    # bits), and the band keeps them
    z = relief(hold=(4, 1))
    scale = 0.02 if lossless else _plan(z, None, 0.1).scale
    t, valid = qt.quantise(z, scale, lossless)
    keep = lp.OPT_ALL & ~lp.OPT_INTERP  # the raster order, with and without sign contexts
    a = band.encode_band(t, valid, lossless, keep, scale)
    b = band.encode_band(t, valid, lossless, keep & ~lp.OPT_SIGN, scale)
    with monkeypatch.context() as mp:
        mp.setattr(_levels, "sign_bits", lambda *args: 0.0)  # sign contexts estimated free: taken
        forced = band.encode_band(t, valid, lossless, keep, scale)
    assert band_bits(*a) == min(band_bits(*b), band_bits(*forced))
    if lossless:
        assert band_bits(*a) < band_bits(*b), (band_bits(*a), band_bits(*b))
    out = decoded(*a, z.shape, lossless, scale)
    if lossless:
        mask = ~np.isnan(z)
        np.testing.assert_array_equal(np.isnan(out), ~mask)
        np.testing.assert_array_equal(out[mask], expected_lossless(z, 0.02)[mask])
    else:
        check_bound(z, out, 0.1)


def test_interpolation_is_given_up_early_against_a_much_smaller_raster_stream() -> None:
    # the encoder passes the raster order's bits: far fewer than the interpolation's first
    # pass takes, the order is given up (-2) before its feedback weights are tried
    z = relief(64, 96)
    plan = _plan(z, None, 0.1)
    t, valid = qt.quantise(z, plan.scale, False)
    tab, val, nb = buffers(z.size)
    full, stream, _ = band._interp_band(t, valid, tab, val, nb)
    assert full >= 0
    bits = float(band._stream_bits(tab, val, nb, np.int64(full)))
    assert stream == bits  # the bits it answers are its stream's, header included
    assert band._interp_band(t, valid, tab, val, nb, bits / 2)[0] == -2
    assert band._interp_band(t, valid, tab, val, nb, bits)[0] >= 0


def test_interpolation_is_not_tried_where_surface_models_predict_the_band() -> None:
    # white noise about a plane: the raster order's leaves predict from their fitted models
    # alone over most of the band, and the interpolation order is not tried there; smooth
    # detailed depth takes local predictors
    def share(z: np.ndarray) -> float:
        plan = _plan(z, None, 0.1)
        t, valid = qt.quantise(z, plan.scale, False)
        tab, val, nb = buffers(z.size)
        n, signs = band._encode_events(t, valid, False, lp.OPT_ALL, float(qt.SPLIT_BOUNDED[0]),
                                       float(qt.SPLIT_BOUNDED[1]), tab, val, nb)
        assert n > 0
        return band._model_share(signs.leaves)

    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:256, 0:320]
    noise = (800.0 + 0.02 * xx + 0.01 * yy + rng.normal(0.0, 0.2, (256, 320))).astype(np.float32)
    assert share(noise) >= band.INTERP_MODEL_MAX
    assert share(relief(hold=(1, 3))) < 0.5


def _tree_events(t: np.ndarray, valid: np.ndarray, lossless: bool, margin: float, share: float,
                 memo: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """A band's mask and tree events, leaves and models, the blocks' fits from ``memo``."""
    tab, val, nb = buffers(t.size)
    leaves = np.zeros((t.size // 16 + 64, 5), np.int64)
    lcoef = np.zeros((t.size // 16 + 64, 6), np.int64)
    n, nleaf = band._encode_tree(t, valid, lossless, np.int64(lp.OPT_ALL), float(margin), float(share), tab, val, nb,
                                 leaves, lcoef, *memo, *band.mask_events(valid, band.MASK_RUNS))
    assert n > 0
    return tab[:n], val[:n], nb[:n], leaves[:nleaf], lcoef[:nleaf]


@pytest.mark.parametrize("lossless", [True, False])
def test_a_tree_built_on_another_margins_fits_is_the_tree_built_afresh(lossless: bool) -> None:
    # a band's margins share every block's fit (qt.tree_memo: the fit does not depend on the
    # margin): each margin's tree, built after the other's, is the tree built on its own. A band
    # whose height and width are not multiples of any block size, with holes, so that every
    # level's blocks are indexed at the edges.
    z = relief(250, 333, hold=(1, 1))
    z[100:140, 200:333] = np.nan
    z[::7, ::5] = np.nan
    t, valid = qt.quantise(z, _plan(z, 0.02, None).scale if lossless else _plan(z, None, 0.05).scale, lossless)
    if lossless:
        (m0, s0), (m1, s1) = [(m, 0.0) for m in qt.SPLIT_LOSSLESS]
    else:
        (m0, s0), (m1, s1) = (0.0, 0.0), qt.SPLIT_BOUNDED
    for first, second in (((m0, s0), (m1, s1)), ((m1, s1), (m0, s0))):
        memo = qt.tree_memo(t, valid, lossless, lp.OPT_ALL)
        a = _tree_events(t, valid, lossless, *first, memo)
        shared = _tree_events(t, valid, lossless, *second, memo)
        fresh = _tree_events(t, valid, lossless, *second, qt.tree_memo(t, valid, lossless, lp.OPT_ALL))
        # an empty memo: every block fitted as it is met
        unmemo = _tree_events(t, valid, lossless, *second, (memo[0], np.zeros((0, 8), np.int64), np.zeros(0)))
        for x, y, u in zip(shared, fresh, unmemo, strict=True):
            np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(x, u)
        assert a[3].shape != fresh[3].shape  # the margins' trees differ: the memo was part-filled


def test_a_margin_that_builds_a_tree_built_already_is_not_coded_again(monkeypatch: pytest.MonkeyPatch) -> None:
    # white noise about a plane: both lossless margins keep the 64-sample blocks, and the second
    # is skipped; the band's stream is the one coded without the skip
    rng = np.random.default_rng(3)
    z = (700.0 + 0.01 * np.arange(256)[None, :] + rng.normal(0.0, 0.2, (256, 256))).astype(np.float32)
    t, valid = qt.quantise(z, _plan(z, 0.02, None).scale, True)
    shared = band._Margins()
    tab, val, nb = buffers(t.size)
    n0, _ = band._encode_events(t, valid, True, lp.OPT_ALL, qt.SPLIT_LOSSLESS[0], 0.0, tab, val, nb, shared)
    assert n0 > 0
    n1, _ = band._encode_events(t, valid, True, lp.OPT_ALL, qt.SPLIT_LOSSLESS[1], 0.0, tab, val, nb, shared)
    assert n1 == band.SAME_TREE
    skipped = band.encode_band(t, valid, True, lp.OPT_ALL, 0.02)
    monkeypatch.setattr(band._Margins, "seen", lambda self, leaves, lcoef: False)
    coded = band.encode_band(t, valid, True, lp.OPT_ALL, 0.02)
    for x, y in zip(skipped, coded, strict=True):
        np.testing.assert_array_equal(x, y)


def test_a_margin_retried_in_larger_buffers_is_not_taken_for_one_coded() -> None:
    # a margin whose event buffers were too small builds its tree again in larger ones: it was
    # not coded, so it must not be skipped as a tree coded already
    z = relief()
    t, valid = qt.quantise(z, _plan(z, 0.02, None).scale, True)
    shared = band._Margins()
    small = tuple(b[:5000] for b in buffers(t.size))
    n, _ = band._encode_events(t, valid, True, lp.OPT_ALL, qt.SPLIT_LOSSLESS[0], 0.0, *small, shared)
    assert n == -1
    n, _ = band._encode_events(t, valid, True, lp.OPT_ALL, qt.SPLIT_LOSSLESS[0], 0.0, *buffers(t.size), shared)
    assert n > 0


def _grad_ways(z: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> tuple[int, int, int]:
    """A lossless band's bits as chosen, with the curvature in the activity and without; the
    chosen stream decodes exactly."""
    t, valid = qt.quantise(z, 0.02, True)
    chosen = band.encode_band(t, valid, True, lp.OPT_ALL, 0.02)
    ways = []
    for gain in (np.inf, -np.inf):  # never, always left out
        with monkeypatch.context() as mp:
            mp.setattr(band, "GRAD_MIN_GAIN", gain)
            ways.append(band_bits(*band.encode_band(t, valid, True, lp.OPT_ALL, 0.02)))
    out = decoded(*chosen, z.shape, True, 0.02)
    np.testing.assert_array_equal(np.isnan(out), ~valid)
    np.testing.assert_array_equal(out[valid], expected_lossless(z, 0.02)[valid])
    return band_bits(*chosen), ways[0], ways[1]


def test_the_curvature_is_kept_unless_leaving_it_out_pays(monkeypatch: pytest.MonkeyPatch) -> None:
    # sub-pixel noise held over 2 x 2 pixels: the curvature of the row above is mostly noise,
    # and leaving it out codes 3.5 % smaller (measured); noise per pixel: within 0.01 % either
    # way, under GRAD_MIN_GAIN, and the curvature is kept
    chosen, with_it, without = _grad_ways(relief(), monkeypatch)
    assert chosen == without < 0.98 * with_it
    chosen, with_it, without = _grad_ways(relief(hold=(1, 1)), monkeypatch)
    assert chosen == with_it and abs(without - with_it) < band.GRAD_MIN_GAIN * with_it


@pytest.mark.slow
def test_a_real_captures_activity_leaves_the_curvature_out(real_range_files: dict, monkeypatch: pytest.MonkeyPatch
                                                           ) -> None:
    # a real capture's depth is noisy (kamino410, about 5 mm): the row above's curvature is
    # noise, and the neighbours' errors alone make the better context (measured on its first
    # band: 0.5 % smaller)
    from shared.compress import load_range_npz

    z = load_range_npz(real_range_files["capture_0"]).z[:256]
    chosen, with_it, without = _grad_ways(z, monkeypatch)
    assert chosen == without < 0.997 * with_it


@pytest.mark.parametrize("lead", ["none", "the first 40 rows"])
def test_a_margins_costs_taken_from_another_are_the_costs_counted_afresh(lead: str) -> None:
    # the second tree margin takes the first's costs of the leaves both trees hold, below the
    # rows whose neighbours depend on the tree (rows starting with holes are filled from the
    # row above, the first from the tree's virtual row): the costs and the predictors chosen
    # are the ones counted afresh
    z = relief(250, 333, hold=(1, 1))
    if lead == "the first 40 rows":
        z[:40, :3] = np.nan
    t, valid = qt.quantise(z, 0.02, True)
    memo = qt.tree_memo(t, valid, True, lp.OPT_ALL)
    shared = band._Margins()
    none = np.zeros((1, t.shape[1]), np.int64)
    out = []
    for margin in qt.SPLIT_LOSSLESS:
        _, _, _, lv, cf = _tree_events(t, valid, True, margin, 0.0, memo)
        leaves = np.zeros((lv.shape[0], 5), np.int64)
        leaves[:, :4] = lv[:, :4]
        cells = band._leaf_cells(np.int64(t.shape[0]), np.int64(t.shape[1]), leaves, np.int64(lv.shape[0]))
        runs = []
        for reuse in (False, True):
            cost = np.zeros((lv.shape[0], lp.NK), np.int64)
            known = shared.known_costs(leaves, cost, valid, t.shape[1]) if reuse else band.NO_KNOWN
            lp.choose_predictors(t, valid, cells, leaves, cf, np.int64(lv.shape[0]), True, np.int64(lp.OPT_ALL), none,
                                 band.ZERO, none, band.ZERO, cost, band.ONE, known)
            runs.append((cost.copy(), leaves[:, 4].copy(), int(np.count_nonzero(known))))
        np.testing.assert_array_equal(runs[0][0], runs[1][0])
        np.testing.assert_array_equal(runs[0][1], runs[1][1])
        out.append(runs[1][2])
        shared.keep_costs(leaves, runs[0][0], t.shape[1])
    assert out[0] == 0 and out[1] > 0  # the second margin took some of the first's


def test_no_leaf_above_the_first_row_starting_with_a_sample_takes_anothers_costs() -> None:
    # their neighbours are filled from the tree's virtual row: another tree's costs are not theirs
    valid = np.ones((256, 256), bool)
    valid[:70, 0] = False  # rows 0-69 start with holes
    leaves = np.array([[x, y, 32, 0, 0] for y in range(0, 256, 32) for x in range(0, 256, 32)], np.int64)
    shared = band._Margins()
    shared.keep_costs(leaves, np.ones((leaves.shape[0], lp.NK), np.int64), 256)
    known = shared.known_costs(leaves, np.zeros((leaves.shape[0], lp.NK), np.int64), valid, 256)
    np.testing.assert_array_equal(known, leaves[:, 1] >= 96)  # rows 0-70 depend on the tree: leaves from y 96 on
