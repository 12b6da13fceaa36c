"""A fast path for plain PNG files: the camera frames a scan reads by the dozen.

In: the bytes of a PNG file (``(n,) uint8``).
Out: the pixels as OpenCV's ``imdecode(IMREAD_UNCHANGED)`` gives them — ``(H, W)`` grey or
``(H, W, 3)`` BGR, ``uint8`` or ``uint16`` — or None when the file is not one this path takes,
and the caller decodes it with OpenCV as before.

Taken: non-interlaced grey (colour type 0) and RGB (type 2) images of 8 or 16 bits with no
chunks but IHDR, IDAT, IEND and the purely textual or physical ones (tEXt, zTXt, iTXt, tIME,
pHYs), every chunk's CRC right and the image data inflating to exactly the size the header
gives. Anything else (palettes, transparency, gamma or colour profiles, interlacing, any
damage) goes to OpenCV, so errors read as before. PNG is lossless: the pixels are the same
values either way (the tests compare with OpenCV on every kind taken).

Why: reading a 2048x1536 capture's 42 frames cost about 1.1 s of CPU in OpenCV (libpng on
zlib, 22.5 ms a frame), three quarters of it zlib's inflate. libdeflate (through
imagecodecs, already a dependency) inflates the same stream 2.5x faster, and the filters
are undone by a small numba kernel; both release the GIL, so the reading threads overlap.
"""

from __future__ import annotations

import logging
import struct
import threading
import zlib

import numba
import numpy as np

from shared.core.jit import zeros

log = logging.getLogger(__name__)

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: Ancillary chunks that change nothing about the pixels OpenCV returns.
_INERT = frozenset((b"tEXt", b"zTXt", b"iTXt", b"tIME", b"pHYs"))


_SCRATCH = threading.local()


def _scratch(name: str, size: int) -> np.ndarray:
    """This thread's reusable uint8 buffer ``name`` of at least ``size`` bytes: the compressed
    stream and the filtered rows of a frame are read and written in memory that is already
    mapped (a fresh 15 MB bytes object a frame cost a page fault per 4 KB)."""
    buf = getattr(_SCRATCH, name, None)
    if buf is None or buf.size < size:
        buf = np.empty(size + size // 4, np.uint8)
        setattr(_SCRATCH, name, buf)
    return buf


def _inflate(stream: np.ndarray, size: int) -> np.ndarray | None:
    """The zlib ``stream`` ((n,) uint8) inflated to exactly ``size`` bytes (adler32 checked)
    into this thread's scratch buffer, or None."""
    out = _scratch("raw", size)[:size]
    try:
        import imagecodecs

        if imagecodecs.DEFLATE.available:
            got = imagecodecs.deflate_decode(stream, out=out)
            return out if len(got) == size else None
    except ImportError:  # pragma: no cover - imagecodecs is a dependency
        pass
    except Exception:  # noqa: BLE001 - any decoder failure: OpenCV decodes (and reports) it
        return None
    try:  # pragma: no cover - without libdeflate
        data = zlib.decompress(stream, bufsize=size)
    except zlib.error:  # pragma: no cover
        return None
    if len(data) != size:  # pragma: no cover
        return None
    out[:] = np.frombuffer(data, np.uint8)  # pragma: no cover
    return out  # pragma: no cover


@numba.njit(inline="always")
def _paeth(a, b, c):  # pragma: no cover
    """The Paeth predictor of left ``a``, above ``b`` and upper-left ``c`` (int32), ties to a, then b."""
    pa = abs(b - c)
    pb = abs(a - c)
    pc = abs(a + b - 2 * c)
    # Selections by masks, not branches: the choice is data-dependent, hard to predict.
    ma = -np.int32((pa <= pb) & (pa <= pc))
    mb = -np.int32(pb <= pc)
    return (a & ma) | (~ma & ((b & mb) | (~mb & c)))


@numba.njit(nogil=True, cache=True)
def _unfilter(raw, h, rb, bpp, out):  # pragma: no cover
    """Undo the PNG row filters. raw: (h * (rb + 1),) uint8, each row's filter byte then its
    rb bytes; bpp: bytes per pixel (filter distance); out: (h, rb) uint8. Returns False on an
    unknown filter type."""
    zero = zeros(rb, np.uint8)
    for y in range(h):
        f = raw[y * (rb + 1)]
        src = raw[y * (rb + 1) + 1 : (y + 1) * (rb + 1)]
        cur = out[y]
        prev = out[y - 1] if y > 0 else zero
        if f == 0:
            for x in range(rb):
                cur[x] = src[x]
        elif f == 1:  # Sub
            for x in range(bpp):
                cur[x] = src[x]
            if bpp == 1:  # the left byte carried in a register, not reloaded from the row
                a = np.int32(cur[0])
                for x in range(1, rb):
                    a = (np.int32(src[x]) + a) & 0xFF
                    cur[x] = np.uint8(a)
            else:
                for x in range(bpp, rb):
                    cur[x] = np.uint8((np.int32(src[x]) + np.int32(cur[x - bpp])) & 0xFF)
        elif f == 2:  # Up
            for x in range(rb):
                cur[x] = np.uint8((np.int32(src[x]) + np.int32(prev[x])) & 0xFF)
        elif f == 3:  # Average
            for x in range(bpp):
                cur[x] = np.uint8((np.int32(src[x]) + (np.int32(prev[x]) >> 1)) & 0xFF)
            if bpp == 1:
                a = np.int32(cur[0])
                for x in range(1, rb):
                    a = (np.int32(src[x]) + ((a + np.int32(prev[x])) >> 1)) & 0xFF
                    cur[x] = np.uint8(a)
            else:
                for x in range(bpp, rb):
                    cur[x] = np.uint8((np.int32(src[x]) + ((np.int32(cur[x - bpp]) + np.int32(prev[x])) >> 1)) & 0xFF)
        elif f == 4:  # Paeth
            for x in range(bpp):
                cur[x] = np.uint8((np.int32(src[x]) + np.int32(prev[x])) & 0xFF)
            if bpp == 1:
                a = np.int32(cur[0])
                c = np.int32(prev[0])
                for x in range(1, rb):
                    b = np.int32(prev[x])
                    a = (np.int32(src[x]) + _paeth(a, b, c)) & 0xFF
                    cur[x] = np.uint8(a)
                    c = b
            else:
                for x in range(bpp, rb):
                    pred = _paeth(np.int32(cur[x - bpp]), np.int32(prev[x]), np.int32(prev[x - bpp]))
                    cur[x] = np.uint8((np.int32(src[x]) + pred) & 0xFF)
        else:
            return False
    return True


_READY = threading.Event()
_BROKEN = threading.Event()
_LOADING = threading.Lock()


def _kernel_ready() -> bool:
    """Whether :func:`_unfilter` can run now. The first caller loads it (numba's first
    dispatch in a process, about 0.3-0.9 s: its target, then the cached machine code) while
    other threads asking meanwhile get False and decode their frames with OpenCV instead of
    waiting on numba's compiler lock: a scan's reading threads keep going from the start."""
    if _READY.is_set():
        return True
    if _BROKEN.is_set() or not _LOADING.acquire(blocking=False):
        return False
    try:
        if not _READY.is_set():
            # The signature of the real calls (a scratch buffer), on one row of one pixel.
            _unfilter(np.zeros(2, np.uint8), 1, 1, 1, np.empty((1, 1), np.uint8))
            _READY.set()
    except Exception:  # noqa: BLE001 - the kernel would not load: OpenCV reads every frame
        log.warning("fast PNG path unavailable, frames decode with OpenCV", exc_info=True)
        _BROKEN.set()
        return False
    finally:
        _LOADING.release()
    return True


#: Frames larger than this (pixels) go to OpenCV: the fast path allocates from the header before
#: inflating, and OpenCV's own limit refuses an absurd header with an error the reader reports.
MAX_PIXELS = 64_000_000


def decode_png(data: np.ndarray) -> np.ndarray | None:
    """Decode a plain PNG (see the module docstring) from its bytes ``data`` ((n,) uint8), or
    return None for OpenCV to decode it."""
    if not _kernel_ready():
        return None
    arr = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
    view = memoryview(arr)
    if view[: len(_PNG_MAGIC)] != _PNG_MAGIC:
        return None
    pos = len(_PNG_MAGIC)
    end = len(view)
    header: tuple[int, ...] | None = None
    idat: list[tuple[int, int]] = []  # (offset, length) of each IDAT chunk's data
    done = False
    while pos + 12 <= end:
        (length,) = struct.unpack_from(">I", view, pos)
        kind = bytes(view[pos + 4 : pos + 8])
        if pos + 12 + length > end:
            return None
        (crc,) = struct.unpack_from(">I", view, pos + 8 + length)
        if zlib.crc32(view[pos + 4 : pos + 8 + length]) != crc:  # type and data
            return None
        body = pos + 8
        pos += 12 + length
        if header is None and kind != b"IHDR":  # IHDR comes first (libpng refuses anything else)
            return None
        if kind == b"IHDR":
            if header is not None or length != 13:
                return None
            header = struct.unpack_from(">IIBBBBB", view, body)
        elif kind == b"IDAT":
            if header is None:
                return None
            idat.append((body, length))
        elif kind == b"IEND":
            done = True
            break
        elif kind not in _INERT:
            return None
    if header is None or not done or not idat:
        return None
    width, height, depth, colour, compression, filtering, interlace = header
    if (depth not in (8, 16) or colour not in (0, 2) or compression or filtering or interlace
            or width == 0 or height == 0 or width * height > MAX_PIXELS):  # fmt: skip
        return None
    channels = 3 if colour == 2 else 1
    bpp = channels * depth // 8
    rb = width * bpp
    total = sum(n for _, n in idat)
    stream = _scratch("stream", total)[:total]
    k = 0
    for off, n in idat:
        stream[k : k + n] = arr[off : off + n]
        k += n
    raw = _inflate(stream, height * (rb + 1))
    if raw is None:
        return None
    rows = np.empty((height, rb), np.uint8)
    if not _unfilter(raw, height, rb, bpp, rows):
        return None
    if depth == 16:
        img = rows.view(">u2").astype(np.uint16)  # big-endian samples to native order
    else:
        img = rows
    if channels == 1:
        return img.reshape(height, width)
    return np.ascontiguousarray(img.reshape(height, width, 3)[..., ::-1])  # RGB -> OpenCV's BGR
