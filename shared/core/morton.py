"""Morton (Z-order) bit interleaving of 21-bit integer coordinates, for numba kernels.

The tile builder (``shared.render.octree``), the octree cloud codec
(``shared.compress._octree``) and the tiles' octree-coded nodes (``shared.compress.tilenode``)
all order points by 3-D Morton codes; each puts x, y and z at its own bit of a triple, so
they share only the spreading and compaction here. ``inline="always"``: compiled into the
calling kernel, with no call and no cache entry of its own.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["compact21", "spread21"]


@numba.njit(cache=True, nogil=True, inline="always")
def spread21(v: np.int64) -> np.int64:
    """The low 21 bits of ``v`` (int64) moved to bits 0, 3, 6, ... 60 (int64, non-negative):
    a 3-D Morton code is ``spread21(a) << 2 | spread21(b) << 1 | spread21(c)`` (below 2**63)."""
    v &= 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


@numba.njit(cache=True, nogil=True, inline="always")
def compact21(v: np.int64) -> np.int64:
    """Inverse of :func:`spread21`: bits 0, 3, 6, ... 60 of ``v`` (int64) gathered into 21 bits."""
    v &= 0x1249249249249249
    v = (v | (v >> 2)) & 0x10C30C30C30C30C3
    v = (v | (v >> 4)) & 0x100F00F00F00F00F
    v = (v | (v >> 8)) & 0x1F0000FF0000FF
    v = (v | (v >> 16)) & 0x1F00000000FFFF
    v = (v | (v >> 32)) & 0x1FFFFF
    return v
