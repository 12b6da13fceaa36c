"""Kernel of :func:`shared.render.preview.shade_colours`: packed colours lit by a distant light."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(parallel=True, cache=True, nogil=True)
def shade_kernel(colour, normal, light, ambient, out) -> None:
    """``out[i]`` = ``colour[i]`` (0x00BBGGRR) times ``ambient + (1 - ambient) * |n . light|``;
    a normal shorter than 0.5 (unknown) leaves the colour as it is."""
    lx, ly, lz = light[0], light[1], light[2]
    for i in numba.prange(colour.shape[0]):
        nx, ny, nz = normal[i, 0], normal[i, 1], normal[i, 2]
        c = colour[i]
        if nx * nx + ny * ny + nz * nz < 0.25:
            out[i] = c
            continue
        f = ambient + (1.0 - ambient) * min(abs(nx * lx + ny * ly + nz * lz), 1.0)
        r = np.uint32((c & 0xFF) * f)
        g = np.uint32(((c >> 8) & 0xFF) * f)
        b = np.uint32(((c >> 16) & 0xFF) * f)
        out[i] = r | (g << 8) | (b << 16)
