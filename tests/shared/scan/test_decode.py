"""Gray-code decoding against analytic truth (a rendered plane), OpenCV, and real captures."""

from __future__ import annotations

import importlib
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.core.datapaths import shared_data_dir
from shared.core.errors import InputError
from shared.formats.capture import load_capture, numbered_frames, opencv_order_capture
from shared.scan.decode import Decoded, DecodeParams, decode_capture, decode_stack, load_decoded, save_decoded
from shared.scan.graycode import pattern_sequence
from tests.support.synthetic_plane import PlaneTruth, render_plane_capture

REAL = shared_data_dir() / "procam-kamino410"
CAM, PROJ = (480, 360), (128, 96)


@pytest.fixture(scope="module")
def plane(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, PlaneTruth]:
    out = tmp_path_factory.mktemp("plane") / "capture"
    return out, render_plane_capture(out, CAM, PROJ, seed=1)


def _column_errors(dec: Decoded, truth: PlaneTruth) -> tuple[float, np.ndarray]:
    ok = np.isfinite(dec.column) & truth.lit
    return ok.sum() / truth.lit.sum(), (dec.column - truth.proj_col)[ok]


def test_decodes_lit_pixels_and_subpixel_beats_integer(plane) -> None:
    root, truth = plane
    cap = load_capture(root)
    sub = decode_capture(cap)
    integer = decode_capture(cap, subpixel=False)
    share, e_sub = _column_errors(sub, truth)
    _, e_int = _column_errors(integer, truth)
    rms_sub, rms_int = float(np.sqrt(np.mean(e_sub**2))), float(np.sqrt(np.mean(e_int**2)))
    print(f"column RMS: sub-pixel {rms_sub:.4f}, integer {rms_int:.4f} projector pixels")
    assert share > 0.995
    assert np.all(np.abs(e_sub) < 1.5)
    assert 0.2 < rms_int < 0.4  # integer codes: uniform quantisation error, about 0.29
    assert rms_sub < 0.25 * rms_int
    # Rows are integer codes of the right row; shadowed pixels decode nothing.
    ok = np.isfinite(sub.row) & truth.lit
    assert np.sqrt(np.mean((sub.row - truth.proj_row)[ok] ** 2)) < 0.4
    assert not np.isfinite(sub.column[~sub.lit]).any()
    assert sub.confidence.min() >= 0 and sub.confidence.max() <= 1
    assert sub.confidence[ok].mean() > 0.3
    assert sub.colour.shape == (*CAM[::-1], 3)
    # The white frame was tinted (R > G > B): colour comes from it, in RGB order.
    c = sub.colour[truth.lit].astype(int).mean(axis=0)
    assert c[0] > c[1] > c[2]


def test_without_inverse_coarse_code_and_no_rows(tmp_path: Path, plane) -> None:
    root, truth = plane
    cap = load_capture(root)
    # Threshold against the white/black midpoint when inverses are absent.
    no_inv = replace(cap, columns=tuple(replace(e, inverse=None) for e in cap.columns), rows=())
    dec = decode_capture(no_inv)
    share, err = _column_errors(dec, truth)
    assert share > 0.98 and np.sqrt(np.mean(err**2)) < 0.1
    assert np.isnan(dec.row).all() and dec.stats["row_decoded"] == 0
    # Finest two bits left out: the code is 4 columns wide, sub-pixel recovers the rest.
    coarse = replace(cap, columns=cap.columns[:-2])
    dec_c = decode_capture(coarse)
    dec_ci = decode_capture(coarse, subpixel=False)
    share, err = _column_errors(dec_c, truth)
    _, err_i = _column_errors(dec_ci, truth)
    print(
        f"coarse code column RMS: sub-pixel {np.sqrt(np.mean(err**2)):.3f}, integer {np.sqrt(np.mean(err_i**2)):.3f}"
    )
    assert share > 0.99
    assert 0.9 < np.sqrt(np.mean(err_i**2)) < 1.4  # 4-column blocks: about 4/sqrt(12)
    assert np.sqrt(np.mean(err**2)) < 0.15


def test_unreliable_finest_bits_fall_back_to_a_coarser_code(plane) -> None:
    root, truth = plane
    cap = load_capture(root)
    white = cv2.imread(str(cap.white), cv2.IMREAD_GRAYSCALE)
    black = cv2.imread(str(cap.black), cv2.IMREAD_GRAYSCALE)
    grey = ((white.astype(int) + black) // 2).astype(np.uint8)
    planes = []
    for e in cap.columns:
        p = cv2.imread(str(e.pattern), cv2.IMREAD_GRAYSCALE)
        i = cv2.imread(str(e.inverse), cv2.IMREAD_GRAYSCALE)
        if e.bit <= 1:
            # Blur has washed out the two finest bits: pattern and inverse read the same grey.
            p, i = grey, grey
        planes.append((e.bit, p, i))
    dec = decode_stack(white, black, planes, projector_size=PROJ, subpixel=False)
    share, err = _column_errors(dec, truth)
    assert share > 0.99
    # Level 2 (finest two bits dropped, 4-column blocks) or 3 on bit-2 edges; never a wrong block
    levels = dec.column_level[np.isfinite(dec.column) & truth.lit]
    assert set(np.unique(levels)) <= {2, 3} and np.mean(levels == 2) > 0.8
    # (a camera pixel spans about 0.3 projector columns, hence the margin)
    assert np.all(np.abs(err) <= 2.0**levels / 2 + 0.5)


def test_all_dark_capture_is_an_input_error(tmp_path: Path, plane) -> None:
    root, _ = plane
    dark = tmp_path / "dark"
    shutil.copytree(root, dark)
    black = cv2.imread(str(dark / "black.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(dark / "white.png"), black)
    with pytest.raises(InputError, match="nothing is lit") as exc:
        decode_capture(load_capture(dark))
    assert "white.png" in str(exc.value)


def test_save_and_load_round_trip(tmp_path: Path, plane) -> None:
    root, _ = plane
    dec = decode_capture(load_capture(root))
    path = save_decoded(dec, tmp_path / "out" / "decoded.npz")
    assert [p.name for p in path.parent.iterdir()] == ["decoded.npz"]
    back = load_decoded(path)
    np.testing.assert_array_equal(back.column, dec.column)
    np.testing.assert_array_equal(back.row, dec.row)
    np.testing.assert_array_equal(back.colour, dec.colour)
    np.testing.assert_array_equal(back.column_level, dec.column_level)
    assert back.stats == dec.stats and back.projector_size == PROJ
    bad = tmp_path / "bad.npz"
    np.savez(bad, column=np.zeros((2, 2)))
    with pytest.raises(InputError, match="not a decoded capture"):
        load_decoded(bad)


@pytest.mark.parametrize(
    "kw",
    [{}, {"inverses": False}, {"bits": 16, "colour": True}, {"bits": 16, "inverses": False}],
    ids=["inverses", "midpoint", "16-bit", "16-bit-midpoint"],
)
def test_streaming_path_equals_one_pass(sim_capture_factory, monkeypatch, kw) -> None:
    """Axes too large for one pass stream through whole-frame code planes with the int8 ``q``;
    the one-pass kernel keeps raw differences and scales them only where they are read. Both
    must give the same decode, bit for bit."""
    import shared.scan.decode as decode

    cap = load_capture(sim_capture_factory("corner", size=(400, 300), projector=(256, 192), seed=3, **kw))
    one = decode_capture(cap)
    monkeypatch.setattr(decode, "_ONE_PASS_BYTES", 0)
    streamed = decode_capture(cap)
    assert one.stats["subpixel_interpolated"] > 0.5 * one.stats["column_decoded"] > 0
    for name in ("column", "row", "confidence", "lit", "column_level", "row_level"):
        np.testing.assert_array_equal(getattr(streamed, name), getattr(one, name), err_msg=name)
    assert {k: v for k, v in streamed.stats.items() if not k.startswith("seconds")} == {
        k: v for k, v in one.stats.items() if not k.startswith("seconds")
    }


@pytest.mark.parametrize("camera", ["srgb", "linear"])
def test_without_inverses_bits_are_read_at_the_midpoint_of_linear_light(sim_capture_factory, camera: str) -> None:
    """Without inverses a bit is read against the white/black midpoint: the projector's half-way
    light is the midpoint of linear light, which a non-linear camera stores off the midpoint of
    stored values. The capture's rig states the response (the virtual rig writes its own), and
    reading through another response moves every stripe edge."""
    from shared.scan.albedo import CameraResponse

    root = sim_capture_factory("corner", size=(400, 300), projector=(256, 192), seed=3, inverses=False,
                               response=camera)
    cap = load_capture(root)
    with np.load(root / "truth.npz") as t:
        lit, proj_col = t["lit"], t["proj_col"]

    def median_error(dec: Decoded) -> float:
        ok = np.isfinite(dec.column) & lit & np.isfinite(proj_col)
        return float(np.median(np.abs(dec.column - proj_col)[ok]))

    own = decode_capture(cap)  # the response the capture's rig states
    assert np.count_nonzero(np.isfinite(own.column) & lit) > 0.97 * lit.sum()
    assert own.stats["midpoint"] == ("linear light, srgb response" if camera == "srgb" else "stored values")
    other = decode_capture(cap, params=DecodeParams(response=CameraResponse("linear" if camera == "srgb" else "srgb")))
    e_own, e_other = median_error(own), median_error(other)
    assert e_own < 0.05 and e_other > 3 * e_own, (e_own, e_other)


def test_patterns_equal_opencv_generate() -> None:
    for w, h in ((1024, 768), (1000, 700), (37, 23)):
        ok, cv_patterns = cv2.structured_light.GrayCodePattern.create(w, h).generate()
        ours = pattern_sequence(w, h)
        assert ok and len(cv_patterns) == len(ours) - 2
        for (name, *_rest, image), cv_image in zip(ours, cv_patterns, strict=False):
            np.testing.assert_array_equal(image, cv_image, err_msg=f"{w}x{h} {name}")


def test_opencv_order_capture_matches_getprojpixel(tmp_path: Path) -> None:
    """OpenCV's own patterns, seen by a tilted camera, fed through opencv_order_capture."""
    pw, ph = 128, 96
    gp = cv2.structured_light.GrayCodePattern.create(pw, ph)
    _, patterns = gp.generate()
    black, white = gp.getImagesForShadowMasks(np.zeros((ph, pw), np.uint8), np.zeros((ph, pw), np.uint8))
    A = np.array([[2.6, 0.15, 10.0], [-0.1, 2.7, 8.0]])  # projector -> camera pixels
    frames, cams = [], []
    for k, img in enumerate([*patterns, white, black]):
        cam = cv2.warpAffine(img.astype(np.float32), A, (400, 300), flags=cv2.INTER_LINEAR)
        cam = np.clip(cam * 0.7 + 20, 0, 255).astype(np.uint8)
        path = tmp_path / f"frame_{k:02d}.png"
        cv2.imwrite(str(path), cam)
        frames.append(path)
        cams.append(cam)
    cap = opencv_order_capture(tmp_path, numbered_frames(tmp_path), pw, ph)
    dec = decode_capture(cap, subpixel=False)
    ys, xs = np.nonzero(np.isfinite(dec.column) & np.isfinite(dec.row))
    pick = np.random.default_rng(0).choice(len(xs), 60, replace=False)
    compared = 0
    for i in pick:
        err, (px, py) = gp.getProjPixel(cams[:-2], int(xs[i]), int(ys[i]))
        if err:
            continue  # OpenCV gives up on low-contrast stripe edges
        compared += 1
        assert (px, py) == (int(dec.column[ys[i], xs[i]]), int(dec.row[ys[i], xs[i]])), (xs[i], ys[i])
    assert compared >= 45
    # And the sub-pixel columns follow the true (affine) mapping.
    Ai = cv2.invertAffineTransform(A)
    true_col = Ai[0, 0] * xs + Ai[0, 1] * ys + Ai[0, 2]
    sub = decode_capture(cap)
    assert np.sqrt(np.mean((sub.column[ys, xs] - true_col) ** 2)) < 0.08


@pytest.mark.skipif(not (REAL / "capture_0").is_dir(), reason="real captures not available")
def test_real_capture_decodes_at_least_90_percent_of_lit_pixels() -> None:
    """Projector-lit: white - black > 40 (OpenCV's blackThreshold), the definition the bench uses."""
    folder = REAL / "capture_1"
    cap = opencv_order_capture(folder, numbered_frames(folder), 1024, 768)
    dec = decode_capture(cap)
    white = cv2.imread(str(cap.white), cv2.IMREAD_GRAYSCALE).astype(int)
    black = cv2.imread(str(cap.black), cv2.IMREAD_GRAYSCALE).astype(int)
    lit = white - black > 40
    decoded = np.isfinite(dec.column) & np.isfinite(dec.row)
    share = decoded[lit].mean()
    print(f"real capture_1: {100 * share:.1f} % of {lit.sum()} lit pixels decode (column and row)")
    assert share >= 0.90
    # Neighbouring pixels on the flat board decode to neighbouring projector columns.
    both = decoded[:, 1:] & decoded[:, :-1] & lit[:, 1:] & lit[:, :-1]
    step = np.abs(np.diff(dec.column, axis=1))[both]
    assert np.median(step) < 1.5 and np.mean(step > 8) < 0.01


def test_kernel_threads_count_free_cores_not_our_own_threads() -> None:
    """kernel_threads() takes the cores that other processes leave free right now: two busy
    processes take two cores away (at least one thread stays); this process's own running
    threads (image readers, kernel workers) are not counted against it."""
    import subprocess
    import sys
    import threading
    import time

    import numba

    from shared.core.threads import cpu_budget
    from shared.scan._kernel_threads import _others_running, _own_running, kernel_threads

    @numba.njit(nogil=True)
    def spin(n: int) -> int:  # pragma: no cover
        x = np.uint64(88172645463325252)  # xorshift: a loop the compiler cannot shorten
        for _ in range(n):
            x ^= x << np.uint64(13)
            x ^= x >> np.uint64(7)
            x ^= x << np.uint64(17)
        return x

    spin(1)
    busy = threading.Thread(target=spin, args=(1_000_000_000,))
    busy.start()
    try:
        time.sleep(0.3)
        assert busy.is_alive() and _own_running() >= 2  # the caller and the spinning thread
        others = _others_running()
        assert others is not None
        assert kernel_threads() >= 1
    finally:
        busy.join()
    burners = [subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 10: pass"])
               for _ in range(2)]  # fmt: skip
    try:
        time.sleep(0.5)
        others = _others_running()
        assert others is not None and others >= 2
        assert kernel_threads() <= max(1, cpu_budget() - 2)
        assert 1 <= kernel_threads() <= numba.config.NUMBA_NUM_THREADS
    finally:
        for b in burners:
            b.kill()
            b.wait()


def test_bands_are_handed_out_once_each(monkeypatch: pytest.MonkeyPatch) -> None:
    """next_item gives every band to exactly one thread, however many threads take part
    (one thread may take all of them), and the decode is the same on one thread as on all."""
    import numba

    kernel_threads_module = importlib.import_module("shared.scan._kernel_threads")
    from shared.scan._bands import next_item

    @numba.njit(parallel=True)
    def claim(n_items, n_threads, hits, owner):  # pragma: no cover
        counter = np.zeros(1, np.int64)  # as in the kernels: one counter for all threads
        for t in numba.prange(n_threads):
            while True:
                i = next_item(counter)
                if i >= n_items:
                    break
                acc = 0.0
                for r in range(2000):  # work enough that the threads overlap
                    acc += np.sin(r * 0.001 + i)
                hits[i] += 1 + (acc > 1e30)
                owner[i] = t

    for n_threads in (1, numba.config.NUMBA_NUM_THREADS, 7):
        hits = np.zeros(3000, np.int64)
        owner = np.full(3000, -1, np.int64)
        claim(3000, n_threads, hits, owner)
        assert np.all(hits == 1), n_threads  # a counter per thread would give each band twice
        assert owner.min() >= 0 and owner.max() < n_threads

    rng = np.random.default_rng(4)
    white = rng.integers(150, 255, (70, 90), dtype=np.uint8)
    black = rng.integers(0, 40, (70, 90), dtype=np.uint8)
    cols = [(5 - k, rng.integers(0, 255, (70, 90), dtype=np.uint8), rng.integers(0, 255, (70, 90), dtype=np.uint8))
            for k in range(6)]  # fmt: skip
    every = decode_stack(white, black, cols, [], (64, 48))
    monkeypatch.setattr(kernel_threads_module, "kernel_threads", lambda: 1)
    one = decode_stack(white, black, cols, [], (64, 48))
    for name in ("column", "confidence", "lit", "column_level"):
        assert np.array_equal(getattr(one, name), getattr(every, name), equal_nan=True), name
