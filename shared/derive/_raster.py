"""numba kernel of the texture baker: which face, at which barycentric coordinates, covers each texel."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def rasterise_uv(uv: np.ndarray, faces: np.ndarray, size: int, face_id: np.ndarray, bary: np.ndarray) -> int:
    """Rasterise the triangles of a UV atlas into a ``size`` x ``size`` texel grid.

    uv : (V, 2) float32 in [0, 1], glTF convention (v down the image); faces : (F, 3) int32.
    face_id : (size, size) int32, filled with the covering face (-1 stays where none); bary :
    (size, size, 3) float32 barycentric coordinates of the texel's centre in that face. A texel
    is covered when its centre is inside the triangle (with a tolerance of a hundredth of a texel,
    so that shared edges leave no crack). Returns the number of texels covered.
    """
    covered = 0
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay = uv[a, 0] * size, uv[a, 1] * size
        bx, by = uv[b, 0] * size, uv[b, 1] * size
        cx, cy = uv[c, 0] * size, uv[c, 1] * size
        den = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
        if abs(den) < 1e-12:
            continue
        x0 = max(int(np.floor(min(ax, bx, cx) - 0.5)), 0)
        x1 = min(int(np.ceil(max(ax, bx, cx) + 0.5)), size - 1)
        y0 = max(int(np.floor(min(ay, by, cy) - 0.5)), 0)
        y1 = min(int(np.ceil(max(ay, by, cy) + 0.5)), size - 1)
        # Tolerance in barycentric units: about 0.01 texel along the triangle's shortest height.
        tol = 0.01 * max(abs(ax - bx) + abs(bx - cx) + abs(cx - ax) + abs(ay - by) + abs(by - cy) + abs(cy - ay), 1.0)
        tol = tol / abs(den) * 0.5
        for y in range(y0, y1 + 1):
            py = y + 0.5
            for x in range(x0, x1 + 1):
                px = x + 0.5
                l0 = ((by - cy) * (px - cx) + (cx - bx) * (py - cy)) / den
                l1 = ((cy - ay) * (px - cx) + (ax - cx) * (py - cy)) / den
                l2 = 1.0 - l0 - l1
                if l0 >= -tol and l1 >= -tol and l2 >= -tol:
                    if face_id[y, x] < 0:
                        covered += 1
                    face_id[y, x] = f
                    bary[y, x, 0] = l0
                    bary[y, x, 1] = l1
                    bary[y, x, 2] = l2
    return covered
