"""Image bytes for tests that need only a header."""

from __future__ import annotations

import struct
import zlib


def png_bytes(w: int, h: int) -> bytes:
    """A valid PNG header claiming ``w`` x ``h`` (8-bit grey) with a tiny IDAT: no pixels needed."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0")) + chunk(b"IEND", b""))  # fmt: skip
