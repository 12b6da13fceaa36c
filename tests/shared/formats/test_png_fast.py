"""The fast PNG path (shared.formats._png) gives exactly OpenCV's pixels for every kind of file
it takes, every row filter included, and hands everything else back to OpenCV."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.formats._png import decode_png
from shared.formats.images import read_grey, read_grey_and_colour


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))


def _filtered(rows: np.ndarray, bpp: int, filters: list[int]) -> bytes:
    """PNG scanlines of ``rows`` ((h, rb) uint8), row y filtered with ``filters[y % len]``."""
    out = bytearray()
    prev = np.zeros(rows.shape[1], np.int32)
    for y, row in enumerate(rows.astype(np.int32)):
        f = filters[y % len(filters)]
        left = np.concatenate([np.zeros(bpp, np.int32), row[:-bpp]])
        upleft = np.concatenate([np.zeros(bpp, np.int32), prev[:-bpp]])
        if f == 0:
            enc = row
        elif f == 1:
            enc = row - left
        elif f == 2:
            enc = row - prev
        elif f == 3:
            enc = row - (left + prev) // 2
        else:
            pa, pb, pc = np.abs(prev - upleft), np.abs(left - upleft), np.abs(left + prev - 2 * upleft)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, prev, upleft))
            enc = row - pred
        out.append(f)
        out += (enc & 0xFF).astype(np.uint8).tobytes()
        prev = row
    return bytes(out)


def _png(img: np.ndarray, filters: list[int], *, extra: bytes = b"", interlace: int = 0, level: int = 6) -> bytes:
    """A PNG of a grey (H, W) or RGB (H, W, 3) uint8/uint16 image, written by hand."""
    h, w = img.shape[:2]
    channels = 1 if img.ndim == 2 else 3
    depth = 16 if img.dtype == np.uint16 else 8
    samples = img.astype(">u2") if depth == 16 else img
    rows = np.frombuffer(samples.tobytes(), np.uint8).reshape(h, -1)
    ihdr = struct.pack(">IIBBBBB", w, h, depth, 2 if channels == 3 else 0, 0, 0, interlace)
    data = zlib.compress(_filtered(rows, channels * depth // 8, filters), level)
    # The image data split over several IDAT chunks, as encoders do.
    parts = [data[i : i + 997] for i in range(0, len(data), 997)] or [b""]
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + extra + b"".join(_chunk(b"IDAT", p) for p in parts)
            + _chunk(b"IEND", b""))  # fmt: skip


def _image(shape: tuple[int, ...], dtype: type, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    top = np.iinfo(dtype).max
    ramp = np.linspace(0, top, shape[1], dtype=np.float64)[None, :]
    if len(shape) == 3:
        ramp = ramp[..., None]
    noise = rng.normal(0, top / 20, shape)
    return np.clip(ramp + noise, 0, top).astype(dtype)


def _cv(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("filters", [[0], [1], [2], [3], [4], [0, 1, 2, 3, 4, 4, 3, 1]])
def test_every_filter_gives_opencvs_pixels(dtype: type, channels: int, filters: list[int]) -> None:
    for k, size in enumerate(((1, 1), (5, 7), (33, 64), (17, 301))):
        shape = size if channels == 1 else (*size, 3)
        data = _png(_image(shape, dtype, k), filters)
        ours, theirs = decode_png(np.frombuffer(data, np.uint8)), _cv(data)
        assert ours is not None, size
        assert ours.dtype == theirs.dtype and ours.shape == theirs.shape, size
        assert np.array_equal(ours, theirs), (size, filters)


@pytest.mark.parametrize("level", [0, 1, 9])
@pytest.mark.parametrize("channels", [1, 3])
def test_opencv_written_files(tmp_path: Path, level: int, channels: int) -> None:
    """Files as cv2.imwrite makes them (its own filter choice), read through read_grey."""
    for dtype in (np.uint8, np.uint16):
        img = _image((40, 90) if channels == 1 else (40, 90, 3), dtype, level)
        path = tmp_path / f"f{level}_{channels}_{np.dtype(dtype).itemsize}.png"
        cv2.imwrite(str(path), img, [cv2.IMWRITE_PNG_COMPRESSION, level])
        data = np.fromfile(path, np.uint8)
        ours = decode_png(data)
        assert ours is not None and np.array_equal(ours, _cv(data.tobytes()))
        grey, colour = read_grey_and_colour(path)
        ref = img if channels == 1 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        assert np.array_equal(read_grey(path), ref) and np.array_equal(grey, ref)
        assert colour.shape == (40, 90, 3)


def test_everything_else_goes_to_opencv(tmp_path: Path) -> None:
    grey = _image((20, 30), np.uint8, 1)
    good = _png(grey, [4])
    assert decode_png(np.frombuffer(good, np.uint8)) is not None
    # An inert chunk changes nothing; one that may change the pixels (gamma) sends the file on.
    text = _png(grey, [4], extra=_chunk(b"tEXt", b"Comment\x00graylight"))
    assert np.array_equal(decode_png(np.frombuffer(text, np.uint8)), grey)
    gamma = _png(grey, [4], extra=_chunk(b"gAMA", struct.pack(">I", 45455)))
    assert decode_png(np.frombuffer(gamma, np.uint8)) is None
    # A chunk before IHDR, and a header past the fast path's size limit (allocated before inflating).
    first = bytes(text)
    ihdr_end = 8 + 25
    before = first[:8] + _chunk(b"tEXt", b"Comment\x00x") + first[8:ihdr_end] + first[ihdr_end:]
    assert decode_png(np.frombuffer(before, np.uint8)) is None
    huge = (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", 100_000, 100_000, 8, 0, 0, 0, 0))
            + _chunk(b"IDAT", zlib.compress(b"\x00" * 100)) + _chunk(b"IEND", b""))  # fmt: skip
    assert decode_png(np.frombuffer(huge, np.uint8)) is None
    # Interlacing, a bad CRC, a short or long image stream, a missing IEND, an unknown filter.
    assert decode_png(np.frombuffer(_png(grey, [4], interlace=1), np.uint8)) is None
    bad_crc = bytearray(good)
    bad_crc[40] ^= 0xFF  # inside the first IDAT
    assert decode_png(np.frombuffer(bytes(bad_crc), np.uint8)) is None
    ihdr = _chunk(b"IHDR", struct.pack(">IIBBBBB", 30, 20, 8, 0, 0, 0, 0))  # 30x20, every CRC right
    for rows in (20, 19, 21):  # the right image stream, then one row short and one row long
        more = np.vstack([grey, grey[:1]])[:rows]
        stream = zlib.compress(_filtered(more, 1, [4] * rows))
        file = b"\x89PNG\r\n\x1a\n" + ihdr + _chunk(b"IDAT", stream) + _chunk(b"IEND", b"")
        got = decode_png(np.frombuffer(file, np.uint8))
        assert np.array_equal(got, grey) if rows == 20 else got is None, rows
    assert decode_png(np.frombuffer(good[:-12], np.uint8)) is None
    raw = bytearray(_filtered(grey, 1, [4]))
    raw[0] = 7
    bad_filter = (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", 30, 20, 8, 0, 0, 0, 0))
                  + _chunk(b"IDAT", zlib.compress(bytes(raw))) + _chunk(b"IEND", b""))  # fmt: skip
    assert decode_png(np.frombuffer(bad_filter, np.uint8)) is None
    # Palette, grey + alpha and RGBA files: OpenCV's, through read_grey as before.
    from PIL import Image

    for mode in ("P", "LA", "RGBA"):
        path = tmp_path / f"{mode}.png"
        Image.fromarray(grey).convert(mode).save(path)
        assert decode_png(np.fromfile(path, np.uint8)) is None, mode
        assert read_grey(path).shape == (20, 30)
