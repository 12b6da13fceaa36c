"""Gray codes and pattern images: the binary-reflected code, OpenCV's pattern order and images."""

from __future__ import annotations

import cv2
import numpy as np

from shared.formats.capture import code_bits
from shared.scan.graycode import gray_decode, gray_encode, pattern_image, pattern_sequence, stripe_bits


def test_gray_code_round_trip_and_one_bit_steps() -> None:
    n = np.arange(4096)
    g = gray_encode(n)
    assert np.array_equal(gray_decode(g, 12), n)
    steps = np.bitwise_xor(g[1:], g[:-1])
    assert np.all(steps & (steps - 1) == 0) and np.all(steps > 0)  # neighbours differ in exactly one bit


def test_stripes_light_columns_whose_code_has_the_bit() -> None:
    cols = np.arange(1024)
    for bit in range(10):
        assert np.array_equal(stripe_bits(1024, bit).astype(bool), (gray_encode(cols) >> bit) & 1 == 1)


def test_patterns_equal_opencv_generate() -> None:
    w, h = 64, 32
    ok, ours = True, pattern_sequence(w, h)
    gp = cv2.structured_light.GrayCodePattern.create(w, h)
    _, theirs = gp.generate()
    assert ok and len(ours) == len(theirs) + 2  # plus white and black
    for (name, _axis, _bit, _inv, img), ref in zip(ours, theirs, strict=False):
        assert np.array_equal(img, ref), name
    assert [n for n, *_ in ours[-2:]] == ["white.png", "black.png"]
    assert len([1 for _n, axis, *_ in ours if axis == "columns"]) == 2 * code_bits(w)


def test_inverse_is_the_complement() -> None:
    a = pattern_image(40, 20, "rows", 2)
    b = pattern_image(40, 20, "rows", 2, inverse=True)
    assert a.dtype == np.uint8 and np.array_equal(a.astype(int) + b, np.full_like(a, 255, dtype=int))
