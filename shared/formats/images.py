"""Reading camera images: header probes, validated grey and colour reads.

In: image files (PNG, JPEG, TIFF, BMP; 8- or 16-bit; grey, grey+alpha, colour or colour+alpha).
Out: numpy arrays — grey ``(H, W)`` ``uint8`` or ``uint16``, colour ``(H, W, 3)`` ``uint8`` in RGB
order — or an :class:`ImageInfo` read from the header alone.

Every failure on bad input (missing, empty, truncated, corrupt, unsupported, wrong size)
raises :class:`~shared.core.errors.InputError` naming the file, so a scan stops with one line
that says which image is at fault. :func:`probe_image` reads only the first few KiB of a
file, which lets the job service reject a huge image before decoding it.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from shared.core.errors import InputError
from shared.core.paths import open_regular, read_bounded

#: Bytes read by :func:`probe_image`; JPEG headers can sit behind large EXIF blocks.
_PROBE_BYTES = 1 << 16
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class ImageInfo:
    """What an image header says: size in pixels, channels per pixel, bits per channel."""

    width: int
    height: int
    channels: int
    bit_depth: int
    format: str = ""

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return (self.width, self.height)


def _probe_png(head: bytes, path: Path) -> ImageInfo:
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise InputError(path, "truncated PNG header (no IHDR chunk)")
    width, height, depth, colour_type = struct.unpack(">IIBB", head[16:26])
    channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour_type)
    if channels is None or depth not in (1, 2, 4, 8, 16):
        raise InputError(path, f"corrupt PNG header (colour type {colour_type}, bit depth {depth})")
    # Palette and sub-byte grey images decode to 8 bits per channel.
    return ImageInfo(width, height, channels, 8 if colour_type == 3 or depth < 8 else depth, "png")


def _probe_jpeg(head: bytes, path: Path) -> ImageInfo:
    i = 2
    n = len(head)
    while i + 4 <= n:
        if head[i] != 0xFF:
            raise InputError(path, f"corrupt JPEG header (no marker at byte {i})")
        marker = head[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        (seg_len,) = struct.unpack(">H", head[i + 2 : i + 4])
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 10 > n:
                break
            precision, height, width, comps = struct.unpack(">BHHB", head[i + 4 : i + 10])
            if width == 0 or height == 0:
                raise InputError(path, "JPEG header gives a zero image size")
            return ImageInfo(width, height, comps, precision, "jpeg")
        if marker == 0xDA:
            break
        i += 2 + seg_len
    raise InputError(path, "JPEG header has no frame size (truncated or corrupt)")


def _probe_bmp(head: bytes, path: Path) -> ImageInfo:
    if len(head) < 30:
        raise InputError(path, "truncated BMP header")
    (dib,) = struct.unpack("<I", head[14:18])
    if dib == 12:
        width, height, _planes, bpp = struct.unpack("<hhHH", head[18:26])
    elif dib >= 40:
        width, height, _planes, bpp = struct.unpack("<iiHH", head[18:30])
    else:
        raise InputError(path, f"corrupt BMP header (DIB header size {dib})")
    channels = {1: 3, 4: 3, 8: 3, 16: 3, 24: 3, 32: 4}.get(bpp)
    if channels is None or width <= 0 or height == 0:
        raise InputError(path, f"corrupt BMP header ({width}x{height}, {bpp} bits per pixel)")
    return ImageInfo(width, abs(height), channels, 8, "bmp")


def _probe_tiff(head: bytes, path: Path) -> ImageInfo:
    order = "<" if head[:2] == b"II" else ">"
    (version,) = struct.unpack(order + "H", head[2:4])
    big = version == 43
    try:
        if big:
            (ifd,) = struct.unpack(order + "Q", head[8:16])
            count_fmt, entry_size, count_size = "Q", 20, 8
        else:
            (ifd,) = struct.unpack(order + "I", head[4:8])
            count_fmt, entry_size, count_size = "H", 12, 2
        with open_regular(path, path, missing="image file is missing") as f:
            size = os.fstat(f.fileno()).st_size

            def seek(offset: int) -> None:
                # a directory or value offset past the file's end (BigTIFF's reach 2^64: seek
                # raised a bare ValueError or OSError)
                if not 0 <= offset < size:
                    raise InputError(path, f"corrupt TIFF header (an offset of {offset} in a file of {size} bytes)")
                f.seek(offset)

            seek(ifd)
            (count,) = struct.unpack(order + count_fmt, f.read(count_size))
            if count > 4096:
                raise InputError(path, f"corrupt TIFF header ({count} directory entries)")
            table = f.read(count * entry_size)
            tags: dict[int, tuple[int, int, bytes]] = {}
            for k in range(count):
                e = table[k * entry_size : (k + 1) * entry_size]
                if big:
                    tag, typ, n = struct.unpack(order + "HHQ", e[:12])
                    value = e[12:20]
                else:
                    tag, typ, n = struct.unpack(order + "HHI", e[:8])
                    value = e[8:12]
                tags[tag] = (typ, n, value)

            def scalar(tag: int, default: int | None = None) -> int:
                if tag not in tags:
                    if default is None:
                        raise InputError(path, f"TIFF header lacks tag {tag}")
                    return default
                typ, _n, value = tags[tag]
                fmt = {3: "H", 4: "I", 16: "Q"}.get(typ, "I")
                return int(struct.unpack(order + fmt, value[: struct.calcsize(fmt)])[0])

            width = scalar(256)
            height = scalar(257)
            channels = scalar(277, 1)
            bits = scalar(258, 1) if tags.get(258, (3, 1, b""))[1] == 1 else None
            if bits is None:
                typ, n, value = tags[258]
                if n * 2 <= (8 if big else 4):
                    bits = int(struct.unpack(order + "H", value[:2])[0])
                else:
                    seek(int(struct.unpack(order + ("Q" if big else "I"), value)[0]))
                    bits = int(struct.unpack(order + "H", f.read(2))[0])
    except struct.error:
        raise InputError(path, "truncated TIFF header") from None
    if width <= 0 or height <= 0:
        raise InputError(path, f"TIFF header gives image size {width}x{height}")
    return ImageInfo(width, height, channels, bits, "tiff")


#: Largest image file read: a 16-bit colour frame of 12000 x 9000 pixels is 648 MB uncompressed;
#: a file beyond this is refused before it is read, not decoded into the worker's memory.
MAX_IMAGE_BYTES = 1 << 30


def _open_head(path: Path) -> bytes:
    # Without blocking and regular files only: an image path may come from a client's capture.
    with open_regular(path, path, missing="image file is missing") as f:
        head = f.read(_PROBE_BYTES)
    if not head:
        raise InputError(path, "image file is empty")
    return head


def probe_image(path: str | os.PathLike[str]) -> ImageInfo:
    """Read an image's size, channels and bit depth from its header, without decoding pixels.

    Parameters
    ----------
    path : path of a PNG, JPEG, TIFF or BMP file.

    Returns
    -------
    ImageInfo with ``width``, ``height``, ``channels`` and ``bit_depth`` (bits per channel).

    Raises :class:`InputError` for missing, empty or unrecognised files.
    """
    path = Path(path)
    head = _open_head(path)
    if head.startswith(_PNG_MAGIC):
        return _probe_png(head, path)
    if head[:3] == b"\xff\xd8\xff":
        return _probe_jpeg(head, path)
    if head[:2] == b"BM":
        return _probe_bmp(head, path)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _probe_tiff(head, path)
    raise InputError(path, "not a PNG, JPEG, TIFF or BMP image")


def _read_bytes(path: Path) -> np.ndarray:
    data = np.frombuffer(read_bounded(path, path, MAX_IMAGE_BYTES, missing="image file is missing"), dtype=np.uint8)
    if data.size == 0:
        raise InputError(path, "image file is empty")
    # Decoders fill a cut-off image with grey and only warn, so check the end marker first.
    if data[:8].tobytes() == _PNG_MAGIC and data[-12:].tobytes()[4:8] != b"IEND":
        raise InputError(path, "truncated PNG (no IEND chunk at the end)")
    if data[:3].tobytes() == b"\xff\xd8\xff" and b"\xff\xd9" not in data[-64:].tobytes():
        raise InputError(path, "truncated JPEG (no end-of-image marker)")
    return data


def _check_size(img: np.ndarray, path: Path, expect: tuple[int, int] | None) -> None:
    if expect is not None and (img.shape[1], img.shape[0]) != tuple(expect):
        raise InputError(
            path, f"image is {img.shape[1]}x{img.shape[0]}, but the capture's images are {expect[0]}x{expect[1]}"
        )


def _decode_unchanged(path: Path, expect: tuple[int, int] | None) -> np.ndarray:
    data = _read_bytes(path)
    img = None
    if data[:8].tobytes() == _PNG_MAGIC:
        # Plain grey/RGB PNG frames decode on a faster path, the same pixels (see _png); the
        # module (numba) loads only when a PNG is read.
        from shared.formats._png import decode_png

        img = decode_png(data)
    if img is None:
        # No EXIF rotation: the header probe and the pattern geometry refer to the stored pixel grid.
        try:
            img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
        except cv2.error:  # an assertion (a header claiming over 2^30 pixels): its text names OpenCV's sources
            img = None
    if img is None:
        raise InputError(path, "corrupt or unsupported image (the decoder could not read it)")
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(path, f"unsupported pixel type {img.dtype} (need 8- or 16-bit integers)")
    _check_size(img, path, expect)
    return img


def _to_grey(img: np.ndarray) -> np.ndarray:
    # One conversion for every image of a capture (the decoders' own grey paths round
    # differently from cvtColor, and the white frame must match the patterns).
    if img.ndim == 2:
        return img
    c = img.shape[2]
    if c <= 2:
        return np.ascontiguousarray(img[..., 0])
    if c == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)


def prepare_png_reading() -> None:
    """Make the fast PNG path ready now (load its kernel: numba's first dispatch in a process,
    up to about a second), e.g. on a thread that would otherwise wait while others read
    frames; they decode with OpenCV until it is ready. Returns at once if another thread is
    loading it."""
    from shared.formats._png import _kernel_ready

    _kernel_ready()


def read_grey(path: str | os.PathLike[str], expect: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as grey levels.

    Parameters
    ----------
    path : image file; colour is converted to luma (ITU-R BT.601 weights), alpha dropped.
    expect : ``(width, height)`` the image must have, or None.

    Returns
    -------
    (H, W) ``uint8`` or ``uint16`` array (16-bit files stay 16-bit).
    """
    path = Path(path)
    return _to_grey(_decode_unchanged(path, expect))


def read_colour(path: str | os.PathLike[str], expect: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as 8-bit RGB.

    Returns
    -------
    (H, W, 3) ``uint8`` array in RGB order (grey images are repeated over the three channels,
    16-bit images scaled to 8 bits).
    """
    return read_grey_and_colour(path, expect)[1]


def read_grey_and_colour(
    path: str | os.PathLike[str], expect: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Decode an image once and return both its grey levels and its 8-bit RGB colour.

    Returns
    -------
    grey : (H, W) ``uint8`` or ``uint16``, as :func:`read_grey` gives.
    colour : (H, W, 3) ``uint8`` RGB, as :func:`read_colour` gives.
    """
    path = Path(path)
    img = _decode_unchanged(path, expect)
    grey = _to_grey(img)
    if img.ndim == 2 or img.shape[2] <= 2:
        bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 3:
        bgr = img
    else:
        bgr = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if bgr.dtype == np.uint16:
        bgr = (bgr >> 8).astype(np.uint8)
    return grey, np.ascontiguousarray(bgr[..., ::-1])
