"""Image reading: header probes agree with decoders; bad files raise InputError naming the file."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.images import probe_image, read_colour, read_grey, read_grey_and_colour


def _image(h: int, w: int, channels: int, dtype) -> np.ndarray:
    rng = np.random.default_rng(h * 31 + w + channels)
    top = 65535 if dtype == np.uint16 else 255
    shape = (h, w) if channels == 1 else (h, w, channels)
    return rng.integers(0, top, size=shape, endpoint=True).astype(dtype)


@pytest.mark.parametrize(
    ("suffix", "channels", "dtype"),
    [
        (".png", 1, np.uint8),
        (".png", 3, np.uint8),
        (".png", 4, np.uint8),
        (".png", 1, np.uint16),
        (".png", 3, np.uint16),
        (".jpg", 1, np.uint8),
        (".jpg", 3, np.uint8),
        (".tif", 1, np.uint8),
        (".tif", 1, np.uint16),
        (".tif", 3, np.uint16),
        (".bmp", 3, np.uint8),
        (".bmp", 1, np.uint8),
    ],
)
def test_probe_matches_decoder(tmp_path: Path, suffix: str, channels: int, dtype) -> None:
    img = _image(37, 53, channels, dtype)
    path = tmp_path / f"img{suffix}"
    assert cv2.imwrite(str(path), img)
    info = probe_image(path)
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert (info.width, info.height) == (decoded.shape[1], decoded.shape[0]) == (53, 37)
    assert info.bit_depth == decoded.dtype.itemsize * 8
    grey = read_grey(path, expect=(53, 37))
    assert grey.shape == (37, 53) and grey.dtype == decoded.dtype
    if channels == 1 and suffix != ".jpg":
        np.testing.assert_array_equal(grey, img)
    colour = read_colour(path)
    assert colour.shape == (37, 53, 3) and colour.dtype == np.uint8
    g2, c2 = read_grey_and_colour(path)
    np.testing.assert_array_equal(g2, grey)
    np.testing.assert_array_equal(c2, colour)


def test_colour_is_rgb_and_grey_is_luma(tmp_path: Path) -> None:
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 2] = 200  # red in OpenCV's BGR order
    path = tmp_path / "red.png"
    cv2.imwrite(str(path), bgr)
    rgb = read_colour(path)
    assert rgb[0, 0].tolist() == [200, 0, 0]
    grey = read_grey(path)
    assert abs(int(grey[0, 0]) - round(0.299 * 200)) <= 1


def test_missing_empty_corrupt_truncated(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="missing") as exc:
        read_grey(tmp_path / "nope.png")
    assert "nope.png" in str(exc.value)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        probe_image(empty)
    with pytest.raises(InputError, match="empty"):
        read_grey(empty)
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"this is not an image at all" * 10)
    with pytest.raises(InputError, match="not a PNG"):
        probe_image(junk)
    with pytest.raises(InputError, match="corrupt"):
        read_grey(junk)

    img = _image(64, 64, 1, np.uint8)
    full = tmp_path / "full.png"
    cv2.imwrite(str(full), img)
    cut = tmp_path / "cut.png"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    assert probe_image(cut).size == (64, 64)  # the header survives ...
    with pytest.raises(InputError, match="truncated PNG") as exc:
        read_grey(cut)  # ... the pixels do not
    assert "cut.png" in str(exc.value)

    jpg = tmp_path / "full.jpg"
    cv2.imwrite(str(jpg), img)
    cutj = tmp_path / "cut.jpg"
    cutj.write_bytes(jpg.read_bytes()[: jpg.stat().st_size // 2])
    with pytest.raises(InputError, match="truncated JPEG"):
        read_grey(cutj)

    # A PNG whose compressed pixel data is scrambled but whose end marker is intact.
    data = bytearray(full.read_bytes())
    idat = data.index(b"IDAT")
    data[idat + 8 : idat + 200] = bytes(192)
    bad = tmp_path / "bad.png"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match="corrupt") as exc:
        read_grey(bad)
    assert "bad.png" in str(exc.value)

    # A header claiming 65535 x 65535 pixels (its CRC mended): OpenCV asserts past 2^30 pixels,
    # an error whose text names OpenCV's source files; it is a corrupt image, by name.
    ihdr = struct.pack(">IIBBBBB", 65535, 65535, 8, 0, 0, 0, 0)
    huge = tmp_path / "huge.png"
    huge.write_bytes(data[:8] + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
                     + full.read_bytes()[33:])
    for read in (read_grey, read_colour):
        with pytest.raises(InputError, match=rf"^{huge}: corrupt or unsupported image"):
            read(huge)


def test_tiff_offsets_past_the_file_are_a_corrupt_header(tmp_path: Path) -> None:
    """A TIFF's directory offset past the file's end: 2^63 and more (BigTIFF's 64-bit offsets)
    made the header probe's seek raise a bare ValueError or OSError."""
    good = tmp_path / "good.tif"
    cv2.imwrite(str(good), _image(40, 50, 1, np.uint16))
    assert probe_image(good).size == (50, 40)
    raw = good.read_bytes()
    order = "<" if raw[:2] == b"II" else ">"
    for offset in (len(raw) + 10, 0xFFFFFFFF):
        bad = tmp_path / "bad.tif"
        bad.write_bytes(raw[:4] + struct.pack(order + "I", offset) + raw[8:])
        with pytest.raises(InputError, match=rf"^{bad}: corrupt TIFF header \(an offset of {offset} in a file of"):
            probe_image(bad)
    big = tmp_path / "big.tif"  # a BigTIFF header whose directory lies at 2^64 - 1
    big.write_bytes(b"II+\x00" + struct.pack("<HHQ", 8, 0, 2**64 - 1) + bytes(64))
    with pytest.raises(InputError, match=r"corrupt TIFF header \(an offset of 18446744073709551615"):
        probe_image(big)


def test_wrong_size(tmp_path: Path) -> None:
    path = tmp_path / "small.png"
    cv2.imwrite(str(path), _image(10, 20, 1, np.uint8))
    with pytest.raises(InputError, match="20x10, but the capture's images are 30x10"):
        read_grey(path, expect=(30, 10))
    with pytest.raises(InputError, match="20x10"):
        read_colour(path, expect=(30, 10))


def test_probe_reads_only_the_header(tmp_path: Path) -> None:
    # A PNG header that claims a 40000x30000 image followed by nothing: the probe must
    # report the size without trying to decode 1.2 G pixels.
    path = tmp_path / "huge.png"
    img = _image(8, 8, 1, np.uint8)
    cv2.imwrite(str(path), img)
    data = bytearray(path.read_bytes())
    data[16:24] = (40000).to_bytes(4, "big") + (30000).to_bytes(4, "big")
    path.write_bytes(bytes(data))
    info = probe_image(path)
    assert (info.width, info.height, info.channels, info.bit_depth) == (40000, 30000, 1, 8)
