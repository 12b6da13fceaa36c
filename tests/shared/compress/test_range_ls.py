"""The range codec's least-squares predictor (lossless mode, :mod:`shared.compress._ls`): taken
where it pays (oversampled detailed depth), not fitted or dropped where it does not (noise);
its streams decode exactly on hostile masks and shapes whatever the encoder would choose
(forced on), across the tree margins the encoder tries (rows starting with holes take their
fill from the tree's virtual row); damaged or misplaced headers are refused."""

from __future__ import annotations

import numpy as np
import pytest

from shared.compress import _band as band
from shared.compress import _lpred as lp
from shared.compress import _ls as ls
from shared.compress import _quadtree as qt
from shared.compress import expected_lossless
from shared.compress.range import _plan
from tests.shared.compress.test_range_orders import buffers, decoded, relief

Q = 0.02
#: Effort 1's options (the weighted predictor is effort 2's), with and without the predictor.
WITH = lp.OPT_ALL & ~lp.OPT_WP
WITHOUT = WITH & ~lp.OPT_LS


def bits(z: np.ndarray, opts: int) -> int:
    t, valid = qt.quantise(z, Q, True)
    tables, words, check = band.encode_band(t, valid, True, opts, Q)
    out = decoded(tables, words, check, z.shape, True, Q) if opts == WITH else None
    if out is not None:
        check_exact(z, out)
    return int(tables.size * 8 + words.size * 16)


def check_exact(z: np.ndarray, out: np.ndarray) -> None:
    mask = ~np.isnan(z)
    np.testing.assert_array_equal(np.isnan(out), ~mask)
    np.testing.assert_array_equal(out[mask], expected_lossless(z, Q)[mask])


def ls_leaves(z: np.ndarray, margin: float = qt.SPLIT_LOSSLESS[0]) -> float:
    """The share of the band's leaves that take the least-squares predictor (one tree margin)."""
    t, valid = qt.quantise(z, Q, True)
    tab, val, nb = buffers(z.size)
    n, signs = band._encode_events(t, valid, True, WITH, float(margin), 0.0, tab, val, nb)
    assert n > 0
    k = signs.leaves[:, 4][signs.leaves[:, 2] > 0]
    return float(np.mean(k == lp.K_LS)) if k.size else 0.0


def smooth_relief(h: int = 256, w: int = 320, sigma: float = 1.0, seed: int = 0) -> np.ndarray:
    """Oversampled detailed depth as a sub-pixel decoder gives it: a tilted, curved surface with
    carved ridges and noise of 0.04 mm smoothed over ``sigma`` camera pixels (a projector pixel
    spans several), a small shadow hole."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 700.0 + 0.03 * xx - 0.02 * yy + 0.0002 * (xx - w / 2) ** 2 + 0.8 * np.sin(xx / 7.0) * np.sin(yy / 11.0)
    n = gaussian_filter(rng.normal(0.0, 1.0, (h, w)), sigma)
    z += 0.04 * n / n.std()
    z[(xx - 0.3 * w) ** 2 + (yy - 0.6 * h) ** 2 < 60] = np.nan
    return z.astype(np.float32)


@pytest.mark.parametrize("sigma, most", [(1.0, 0.9), (2.0, 0.75)])
def test_least_squares_pays_on_oversampled_depth(sigma: float, most: float) -> None:
    # most leaves take the predictor and the band codes smaller (measured: 0.818 and 0.628 of
    # the stream without it)
    z = smooth_relief(sigma=sigma)
    assert ls_leaves(z) > 0.5
    assert bits(z, WITH) < most * bits(z, WITHOUT)


def test_depth_held_over_pixels_is_not_coded_larger() -> None:
    # depth held constant over 2 x 2 pixels: the local predictors' errors are 0 at every other
    # pixel, the fit's smaller but never 0 (with the leaves choosing by absolute error and the
    # fit kept, 5 % larger): never larger than without it
    z = relief(256, 320, hold=(2, 2))
    assert bits(z, WITH) <= bits(z, WITHOUT)


def test_the_way_without_is_kept_where_it_codes_smaller(monkeypatch: pytest.MonkeyPatch) -> None:
    # the band is coded both ways where the leaves' costs do not say clearly (they are not the
    # code length): here made to, with the weights' bits counted as huge, the stream kept is
    # the one without the predictor, byte for byte, and it decodes
    z = smooth_relief()
    assert ls_leaves(z) > 0.5
    monkeypatch.setattr(band, "LS_SURE", 0.0)
    assert ls_leaves(z) > 0.5
    monkeypatch.setattr(band, "LS_HEAD_BITS", 1e12)
    assert ls_leaves(z) == 0.0
    assert bits(z, WITH) == bits(z, WITHOUT)


def test_noise_keeps_its_surface_models_and_the_same_stream() -> None:
    # white noise about a smooth surface: its leaves keep their fitted surfaces, the
    # predictor is not fitted (or dropped), the stream is the one coded without it
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:256, 0:300].astype(np.float64)
    z = (800.0 + 0.02 * xx + 0.0001 * yy**2 + rng.normal(0.0, 0.2, xx.shape)).astype(np.float32)
    assert ls_leaves(z) == 0.0
    assert bits(z, WITH) == bits(z, WITHOUT)


def _masks() -> list[tuple[str, np.ndarray]]:
    """Hostile masks and shapes over oversampled relief (so that leaves take the predictor)."""
    rng = np.random.default_rng(11)
    base = smooth_relief()
    base[np.isnan(base)] = 700.0
    out = []
    for h, w in [(1, 1), (1, 37), (37, 1), (3, 5), (17, 33), (64, 70), (256, 45), (256, 320)]:
        for share in (0.0, 0.3, 0.9):
            zz = base[:h, :w].copy()
            zz[rng.random(zz.shape) < share] = np.nan
            out.append((f"{h}x{w} {int(share * 100)} % holes", zz))
    # rows that start with holes take their fill from the row above, the first from the tree's
    # virtual row (a leaf's model where the 4 x 4 cell holds a sample): the predictions of every
    # row down to the second after the first that starts with a sample depend on the tree
    lead = base.copy()
    for y in range(256):
        lead[y, : 1 + (y * 7) % 3] = np.nan
    out.append(("leading holes", lead))
    top = base.copy()
    top[:40, :2] = np.nan
    out.append(("leading holes in the first rows", top))
    board = base[:48, :48].copy()
    board[np.indices((48, 48)).sum(0) % 2 == 1] = np.nan
    out.append(("checkerboard", board))
    grid = base[:80, :96].copy()
    grid[::16, :] = np.nan
    grid[:, ::16] = np.nan
    out.append(("holes on the coarse grid", grid))
    out.append(("all holes", np.full((20, 30), np.nan, np.float32)))
    wide = smooth_relief(64, 1100, seed=2)  # three tiles of weights, the last 76 columns
    out.append(("three tiles", wide))
    gap = wide.copy()
    gap[:, 512:1024] = np.nan  # a tile without samples: it takes the band's weights
    out.append(("a tile of holes", gap))
    jumps = base[:64, :64] + np.where(np.indices((64, 64))[1] % 5 < 2, 2000.0, -1500.0)
    out.append(("depth jumps of 3.5 m", jumps.astype(np.float32)))
    far = base[:64, :64].astype(np.float64) * 1e6  # about 7e8 units: 3.5e10 quanta
    far[::3, ::2] *= -1.0
    out.append(("jumps of 1.4e9 units", far.astype(np.float32)))
    return out


@pytest.mark.parametrize("name, z", _masks(), ids=[n for n, _ in _masks()])
def test_streams_with_the_predictor_forced_on_decode_exactly_on_hostile_masks(
        name: str, z: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> None:
    # fitted and kept in every band where a fit is possible, whatever it saves; both tree
    # margins are coded (the predictions of the second reuse the first's below the rows that
    # depend on the tree)
    monkeypatch.setattr(band, "LS_MODEL_MAX", 2.0)
    monkeypatch.setattr(band, "LS_MIN_GAIN", -1.0)
    monkeypatch.setattr(band, "LS_HEAD_BITS", -np.inf)
    t, valid = qt.quantise(z, Q, True)
    tables, words, check = band.encode_band(t, valid, True, WITH, Q)
    check_exact(z, decoded(tables, words, check, z.shape, True, Q))
    if name in ("256x320 0 % holes", "256x320 30 % holes", "leading holes", "leading holes in the first rows",
                "three tiles", "a tile of holes"):
        assert ls_leaves(z) > 0.3
        assert ls_leaves(z, qt.SPLIT_LOSSLESS[-1]) > 0.3


def interior_error(t: np.ndarray, w: np.ndarray) -> float:
    """Mean absolute error (fine units) of the weights ``w`` over the interior of a hole-free
    band ``t`` (numpy's own sum of the neighbours, not the kernel's)."""
    H, W = t.shape
    lo, hi = -int(ls.LS_DX.min()), int(ls.LS_DX.max())  # columns out to the left and right
    n = t[1:H - 1, lo:W - hi].astype(np.float64)  # N of the samples t[2:H, lo:W-hi]
    acc = np.zeros_like(n)
    for k in range(ls.NLS):
        dy, dx = int(ls.LS_DY[k]), int(ls.LS_DX[k])
        acc += w[k] * (t[2 - dy:H - dy, lo + dx:W - hi + dx] - n)
    pred = n + np.floor((acc + (1 << (ls.LS_SHIFT - 1))) / (1 << ls.LS_SHIFT))
    return float(np.abs(t[2:H, lo:W - hi] - pred).mean())


def _tree(t: np.ndarray, valid: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A band's quadtree: (cells, leaves, coefficients)."""
    tab, val, nb = buffers(t.size)
    leaves = np.zeros((t.size // 16 + 64, 5), np.int64)
    lcoef = np.zeros((t.size // 16 + 64, 6), np.int64)
    n, nleaf = band._encode_tree(t, valid, True, np.int64(WITH), float(margin), 0.0, tab, val, nb, leaves, lcoef,
                                 *band.tree_memo(t, valid, True, WITH), *band.mask_events(valid, band.MASK_RUNS))
    assert n > 0
    cells = band._leaf_cells(np.int64(t.shape[0]), np.int64(t.shape[1]), leaves, np.int64(nleaf))
    return cells, leaves, lcoef


@pytest.mark.parametrize("lead", ["none", "every row", "the first 40 rows", "a row in two"])
def test_predictions_made_again_for_another_tree_are_those_made_afresh(lead: str) -> None:
    # the encoder makes the predictions of its second tree margin from its first's, again only
    # where rows depend on the tree: rows that start with holes are filled from the row above,
    # the first from the tree's virtual row (a leaf's model at pixel 0, where the leaf holds
    # samples further right). Another tree (every leaf's surface 5 mm higher): the same
    # predictions as made afresh.
    z = smooth_relief()
    z[np.isnan(z)] = 700.0
    if lead == "every row":
        z[:, :5] = np.nan
    elif lead == "the first 40 rows":
        z[:40, :2] = np.nan
    elif lead == "a row in two":
        z[::2, :3] = np.nan
    t, valid = qt.quantise(z, Q, True)
    w = ls.ls_weights(t, valid)
    a = _tree(t, valid, qt.SPLIT_LOSSLESS[0])
    b = (a[0], a[1], a[2].copy())
    b[2][:, 0] += 250 * 32  # 250 quanta, in fine units
    first = ls.ls_band(t, valid, *a, w)
    afresh = ls.ls_band(t, valid, *b, w)
    np.testing.assert_array_equal(ls.ls_band(t, valid, *b, w, first), afresh)
    if lead != "none":
        assert not np.array_equal(first, afresh)  # the tree matters to these rows


def test_the_kernel_predicts_what_the_neighbour_list_says() -> None:
    # the decoder's written-out sum (the band's interior) and its loop over LS_DY, LS_DX (its
    # edges) are the same predictor: numpy's sum over the list gives the kernel's predictions
    # exactly, in every tile
    z = smooth_relief(64, 1100, seed=3)
    z[np.isnan(z)] = 700.0
    t, valid = qt.quantise(z, Q, True)
    w = ls.ls_weights(t, valid)
    pred = ls.ls_band(t, valid, *_tree(t, valid, qt.SPLIT_LOSSLESS[0]), w)
    H, W = t.shape
    lo, hi = -int(ls.LS_DX.min()), int(ls.LS_DX.max())
    n = t[1:H - 1].astype(np.int64)  # N of rows 2.. (the rows above are the band's own)
    for x in list(range(lo, lo + 8)) + list(range(505, 520)) + list(range(W - hi - 8, W - hi)):
        o = (x >> ls.TILE_SHIFT) * ls.NLS
        acc = sum(int(w[o + k]) * (t[2 - ls.LS_DY[k]:H - ls.LS_DY[k], x + ls.LS_DX[k]] - n[:, x]) for k in range(ls.NLS))
        np.testing.assert_array_equal(pred[2:, x], n[:, x] + ((acc + (1 << (ls.LS_SHIFT - 1))) >> ls.LS_SHIFT))
    # at the first column the loop clamps to the band: the neighbours in the rows above take the
    # row's first pixel, those to the left in its own row the W neighbour (the row above's first)
    acc = 0
    for k in range(ls.NLS):
        dy, dx = int(ls.LS_DY[k]), int(ls.LS_DX[k])
        v = t[2 - dy:H - dy, min(max(dx, 0), W - 1)] if dy else t[1:H - 1, 0]
        acc = acc + int(w[k]) * (v - n[:, 0])
    np.testing.assert_array_equal(pred[2:, 0], n[:, 0] + ((acc + (1 << (ls.LS_SHIFT - 1))) >> ls.LS_SHIFT))


def test_the_fit_samples_what_the_neighbour_list_says() -> None:
    # the fit's samples (written out in the band's interior, looped over the list at its edges)
    # are each neighbour's difference from N as LS_DY, LS_DX say: from every STEP-th row from the
    # third, every column of the tile
    z = smooth_relief(64, 300, seed=5)
    z[np.isnan(z)] = 700.0
    t, valid = qt.quantise(z, Q, True)
    F, e, n = ls.ls_samples(t, valid, np.int64(0), np.int64(300))
    H, W = t.shape
    rows = [y for y in range(2, H) if y % ls.STEP == 0]
    assert n == len(rows) * W
    for i, y in enumerate(rows):
        c = t[y - 1]
        np.testing.assert_array_equal(e[i * W:(i + 1) * W], t[y] - c)
        for k in range(ls.NLS):
            dy, dx = int(ls.LS_DY[k]), int(ls.LS_DX[k])
            cols = np.clip(np.arange(W) + dx, 0, W - 1)
            v = t[y - dy, cols]
            if dy == 0:  # off the row's start: its W neighbour, the row above's first pixel at x = 0
                left = np.arange(W) + dx < 0
                v = np.where(left, np.where(np.arange(W) > 0, t[y, np.maximum(np.arange(W) - 1, 0)], t[y - 1, 0]), v)
            np.testing.assert_array_equal(F[i * W:(i + 1) * W, k], v - c, err_msg=f"row {y}, neighbour {k}")


def test_the_fit_leaves_out_depth_jumps() -> None:
    # a silhouette's 3.5 m steps do not pull the fit: the weights fitted with them predict the
    # relief without them within 2 % of its own fit's error (with the steps' samples in the
    # squares, the weights would fit the steps)
    z = smooth_relief()
    z[np.isnan(z)] = 700.0
    t, valid = qt.quantise(z, Q, True)
    w0 = ls.ls_weights(t, valid)
    zj = z.copy()
    zj[:, 160:] += 3500.0
    zj[100:180, 40:80] -= 3500.0
    w1 = ls.ls_weights(*qt.quantise(zj, Q, True))
    assert w0 is not None and w1 is not None
    e0 = interior_error(t, w0)
    assert e0 < 0.5 * interior_error(t, np.zeros(ls.NLS))  # the fit predicts better than N alone
    assert interior_error(t, w1) < 1.02 * e0


def test_each_tile_fits_its_own_depth() -> None:
    # noise smoothed along rows in the first tile of 512 columns, along columns in the second:
    # each tile's weights predict its own samples better than the other tile's (and the
    # band's prior does not pull them together)
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(4)
    n = rng.normal(0.0, 1.0, (256, 1024))
    n[:, :512] = gaussian_filter(n[:, :512], (0.3, 2.5))
    n[:, 512:] = gaussian_filter(n[:, 512:], (2.5, 0.3))
    z = (700.0 + 0.02 * np.arange(1024)[None, :] + 0.05 * n / n.std()).astype(np.float32)
    t, valid = qt.quantise(z, Q, True)
    w = ls.ls_weights(t, valid).reshape(2, ls.NLS)
    left, right = t[:, :512], t[:, 512:]
    assert interior_error(left, w[0]) < 0.95 * interior_error(left, w[1])
    assert interior_error(right, w[1]) < 0.95 * interior_error(right, w[0])


def test_no_fit_on_too_few_samples() -> None:
    z = smooth_relief(4, 30)
    t, valid = qt.quantise(z, Q, True)
    assert ls.ls_weights(t, valid) is None


def _raster_events(z: np.ndarray, lossless: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    scale = Q if lossless else _plan(z, None, 0.1).scale
    t, valid = qt.quantise(z, scale, lossless)
    tab, val, nb = buffers(z.size)
    n, _ = band._encode_events(t, valid, lossless, WITH, float(qt.SPLIT_LOSSLESS[0]), 0.0, tab, val, nb)
    # after the mask's coder: the mode, the seven flags, the levels' tables, the weights' bytes,
    # the leaves'
    head = np.flatnonzero(tab[:n] == qt.T_PRED)[1:]
    assert val[head[0]] == qt.MODE_RASTER
    return tab, val, nb, n, head


def _decodes(z: np.ndarray, tab: np.ndarray, val: np.ndarray, nb: np.ndarray, n: int, lossless: bool) -> bool:
    """Whether the band's events decode (the decoder's answer 0, not -1)."""
    scale = Q if lossless else _plan(z, None, 0.1).scale
    out = np.empty(z.shape, np.float32)
    return band.decode_band(*band._pack(tab, val, nb, n), z.shape[0], z.shape[1], lossless, scale, out) == 0


LS_FLAG = qt.N_FLAGS  # the least-squares predictor's flag among the header's events (after the mode)


@pytest.mark.parametrize("what, at, value", [("flag 2", LS_FLAG, 2), ("a weight's byte beyond 255", qt.HEAD_N + 1, 256),
                                             ("the last weight's byte beyond 255", qt.HEAD_N + 2 * ls.NLS, 300),
                                             ("a level's table flag 2", qt.N_FLAGS + 3, 2)])
def test_a_damaged_least_squares_header_is_refused(what: str, at: int, value: int) -> None:
    z = smooth_relief(64, 64)
    tab, val, nb, n, head = _raster_events(z, True)
    assert val[head[LS_FLAG]] == 1 and _decodes(z, tab, val, nb, n, True)  # the band runs the predictor
    val[head[at]] = value
    assert not _decodes(z, tab, val, nb, n, True)


def test_a_leaf_taking_the_predictor_in_a_band_without_it_is_refused() -> None:
    z = smooth_relief(64, 64)
    tab, val, nb, n, head = _raster_events(z, True)
    leaves = head[qt.HEAD_N + 1 + 2 * ls.NLS:]
    assert np.any(val[leaves] == lp.K_LS)
    val[head[LS_FLAG]] = 0  # the flag off: the weights' bytes now read as leaves' predictors
    assert not _decodes(z, tab, val, nb, n, True)


def test_the_predictor_in_a_bounded_band_is_refused() -> None:
    z = smooth_relief(64, 64)
    tab, val, nb, n, head = _raster_events(z, False)
    assert val[head[LS_FLAG]] == 0 and _decodes(z, tab, val, nb, n, False)
    val[head[LS_FLAG]] = 1
    assert not _decodes(z, tab, val, nb, n, False)
