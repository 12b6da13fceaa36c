"""Binary-reflected Gray codes and the stripe patterns a projector shows.

Projector column ``c`` is encoded by ``g = c ^ (c >> 1)``; pattern bit ``k`` lights
column ``c`` iff bit ``k`` of ``g`` is 1. Patterns are ``uint8`` images of the
projector's size (0 or 255), most significant bit first, each followed by its
inverse: the order of OpenCV's ``structured_light.GrayCodePattern``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.formats.capture import Capture, CodeImage, code_bits


def gray_encode(n: np.ndarray | int) -> np.ndarray:
    """Binary-reflected Gray code of non-negative integers (any integer dtype)."""
    n = np.asarray(n)
    return n ^ (n >> 1)


def gray_decode(g: np.ndarray | int, nbits: int = 32) -> np.ndarray:
    """Inverse of :func:`gray_encode` for codes of at most ``nbits`` bits."""
    g = np.array(g, copy=True)
    shift = 1
    while shift < nbits:
        g ^= g >> shift
        shift <<= 1
    return g


def stripe_bits(n: int, bit: int) -> np.ndarray:
    """Boolean (n,) array: whether pattern ``bit`` lights each of ``n`` projector columns (or rows)."""
    return ((gray_encode(np.arange(n, dtype=np.int64)) >> bit) & 1).astype(bool)


def pattern_image(width: int, height: int, axis: str, bit: int, inverse: bool = False) -> np.ndarray:
    """The ``(height, width)`` uint8 pattern for one bit; ``axis`` is ``"columns"`` or ``"rows"``."""
    if axis == "columns":
        on = stripe_bits(width, bit)[None, :]
    elif axis == "rows":
        on = stripe_bits(height, bit)[:, None]
    else:
        raise ValueError(f"axis must be 'columns' or 'rows', got {axis!r}")
    if inverse:
        on = ~on
    return np.broadcast_to(np.where(on, np.uint8(255), np.uint8(0)), (height, width)).copy()


def pattern_sequence(width: int, height: int, rows: bool = True) -> list[tuple[str, str, int, bool, np.ndarray]]:
    """Every pattern in OpenCV order: ``(name, axis, bit, inverse, image)``; then white and black.

    White and black come last with ``axis`` ``"white"`` / ``"black"`` and ``bit`` -1.
    """
    out: list[tuple[str, str, int, bool, np.ndarray]] = []
    axes = [("columns", "col", code_bits(width))]
    if rows:
        axes.append(("rows", "row", code_bits(height)))
    for axis, prefix, nbits in axes:
        for k in range(nbits):
            bit = nbits - 1 - k
            for inv in (False, True):
                name = f"{prefix}_{k:02d}{'_inv' if inv else ''}.png"
                out.append((name, axis, bit, inv, pattern_image(width, height, axis, bit, inv)))
    out.append(("white.png", "white", -1, False, np.full((height, width), 255, np.uint8)))
    out.append(("black.png", "black", -1, False, np.zeros((height, width), np.uint8)))
    return out


def capture_for_names(root: Path, width: int, height: int, rows: bool = True, rig: Path | None = None) -> Capture:
    """The capture description matching the file names of :func:`pattern_sequence`."""
    root = Path(root).absolute()
    cols: list[CodeImage] = []
    rws: list[CodeImage] = []
    for axis, prefix, nbits, dest in (("columns", "col", code_bits(width), cols), ("rows", "row", code_bits(height), rws)):
        if axis == "rows" and not rows:
            continue
        for k in range(nbits):
            dest.append(
                CodeImage(bit=nbits - 1 - k, pattern=root / f"{prefix}_{k:02d}.png", inverse=root / f"{prefix}_{k:02d}_inv.png")
            )
    return Capture(
        root=root,
        projector_width=width,
        projector_height=height,
        white=root / "white.png",
        black=root / "black.png",
        columns=tuple(cols),
        rows=tuple(rws),
        rig=rig,
    )
