"""Synthetic range images for codec tests and benches: piecewise smooth surfaces like a scan's.

:func:`synthetic_range` renders, per pixel of an (h, w) camera with focal length ``f``, the depth
of a scene of a tilted back wall, three spheres standing in front of it (depth jumps at their
rims) and a box, with Gaussian depth noise ``sigma`` (mm) and NaN where nothing is seen: a hole in the
wall and the spheres' shadows (the projector's light does not reach them). About 82 % of the
pixels are valid at every size (the scene scales with the image).
"""

from __future__ import annotations

import numpy as np


def synthetic_range(h: int = 1536, w: int = 2048, sigma: float = 0.2, seed: int = 0) -> np.ndarray:
    """(h, w) float32 depth in mm, NaN holes; rows processed in bands to keep memory small."""
    rng = np.random.default_rng(seed)
    f = 1.4 * w
    z = np.empty((h, w), np.float32)
    cx, cy = w / 2, h / 2
    spheres = [(-120.0, -40.0, 720.0, 90.0), (150.0, 60.0, 760.0, 120.0), (10.0, 150.0, 650.0, 60.0)]
    xs = (np.arange(w) - cx) / f
    for y0 in range(0, h, 256):
        y1 = min(h, y0 + 256)
        ys = ((np.arange(y0, y1) - cy) / f)[:, None]
        rx, ry = np.broadcast_to(xs[None, :], (y1 - y0, w)), np.broadcast_to(ys, (y1 - y0, w))
        # back wall: the plane z = 900 + 0.25 x - 0.1 y (in mm), seen along the rays (x, y, 1) t
        depth = 900.0 / (1.0 - 0.25 * rx + 0.1 * ry)
        # a box face (a plane closer to the camera) in the lower left
        box = (rx < -0.2) & (ry > 0.15)
        depth = np.where(box, 600.0 / (1.0 + 0.3 * rx), depth)
        for sx, sy, sz, r in spheres:
            # ray-sphere intersection: |t d - c|^2 = r^2 with d = (rx, ry, 1)
            dd = rx * rx + ry * ry + 1.0
            b = rx * sx + ry * sy + sz
            disc = b * b - dd * (sx * sx + sy * sy + sz * sz - r * r)
            hit = disc > 0
            t = (b - np.sqrt(np.where(hit, disc, 0.0))) / dd
            depth = np.where(hit & (t < depth), t, depth)
        band = depth + rng.normal(0.0, sigma, depth.shape)
        band[(rx - 0.3) ** 2 + (ry + 0.05) ** 2 < 0.004] = np.nan  # a hole in the wall
        for sx, sy, sz, r in spheres:  # each sphere's shadow on its right
            u, v = sx / sz, sy / sz
            rr = r / sz
            band[((rx - u - 1.15 * rr) ** 2 + (ry - v) ** 2 < (1.05 * rr) ** 2) & ((rx - u) ** 2 + (ry - v) ** 2 > rr * rr)] = np.nan
        z[y0:y1] = band
    return z
