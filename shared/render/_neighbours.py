"""Per-point attributes from a cloud's own neighbourhoods, for clouds that other scanners made:
the splat ``size`` from the local point spacing, and unit normals by principal components.

In: positions (N, 3) float64 in world units (one tile chunk: a region of the cloud). Out:
(N,) float32 sizes, (N, 3) float32 unit normals. Neighbours come from a k-d tree
(``scipy.spatial.cKDTree``, all cores), and are processed in blocks so memory stays at a few
tens of MB whatever N.

Why these estimates: Graylight's ``size`` is the scanner's sample footprint Z / f_camera,
which on a surface facing the camera equals the distance between neighbouring samples. The
mean distance to the :data:`SIZE_NEIGHBOURS` nearest other points gives that same figure on
a regular grid (its four nearest neighbours all lie one spacing away) and a little more on an
irregular sampling, so splats drawn ``SPLAT_SCALE`` times that wide still close the surface.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.spatial import cKDTree

from shared.core.threads import cpu_budget

#: Neighbours whose mean distance is a point's size (4: a grid's edge-adjacent samples).
SIZE_NEIGHBOURS = 4
#: Neighbours (the point included) whose covariance gives a point's normal.
NORMAL_NEIGHBOURS = 12
BLOCK = 1 << 17


def kdtree(xyz: np.ndarray) -> cKDTree:
    """The k-d tree the estimates share (one build for both)."""
    return cKDTree(np.asarray(xyz, np.float64), balanced_tree=False, compact_nodes=False)


def spacing_size(xyz: np.ndarray, k: int = SIZE_NEIGHBOURS, tree: cKDTree | None = None) -> np.ndarray:
    """(N,) float32 mean distance of every point to its ``k`` nearest other points (world units).

    Coincident points count as neighbours at distance 0; a cloud of fewer than two points gets
    size 0 (one pixel when drawn).
    """
    n = xyz.shape[0]
    out = np.zeros(n, np.float32)
    if n < 2:
        return out
    k = min(k, n - 1)
    tree = tree or kdtree(xyz)
    for a in range(0, n, BLOCK):
        d, _ = tree.query(xyz[a : a + BLOCK], k=k + 1, workers=cpu_budget())
        out[a : a + BLOCK] = d[:, 1:].mean(axis=1)
    return out


@numba.njit(cache=True, inline="always")
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix: the eigenvalues
    in closed form (Smith 1961), then the longest cross product of two rows of A - l I."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if p2 <= 1e-300:  # a multiple of the identity: no preferred direction
        return 0.0, 0.0, 0.0
    p = math.sqrt(p2 / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    r = min(max(det / (2.0 * p * p * p), -1.0), 1.0)
    phi = math.acos(r) / 3.0
    lam = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)  # the smallest of the three
    r0 = (a00 - lam, a01, a02)
    r1 = (a01, a11 - lam, a12)
    r2 = (a02, a12, a22 - lam)
    best = -1.0
    vx = vy = vz = 0.0
    for u, w in ((r0, r1), (r0, r2), (r1, r2)):
        cx = u[1] * w[2] - u[2] * w[1]
        cy = u[2] * w[0] - u[0] * w[2]
        cz = u[0] * w[1] - u[1] * w[0]
        n = cx * cx + cy * cy + cz * cz
        if n > best:
            best, vx, vy, vz = n, cx, cy, cz
    if best <= 0.0:
        return 0.0, 0.0, 0.0
    inv = 1.0 / math.sqrt(best)
    return vx * inv, vy * inv, vz * inv


@numba.njit(parallel=True, cache=True, nogil=True)
def _normals_kernel(xyz, idx, viewpoint, out) -> None:
    """Normal of point ``i`` from its neighbours ``idx[i]`` (the points' covariance), facing
    ``viewpoint``."""
    k = idx.shape[1]
    for i in numba.prange(idx.shape[0]):
        mx = my = mz = 0.0
        for j in range(k):
            p = idx[i, j]
            mx += xyz[p, 0]
            my += xyz[p, 1]
            mz += xyz[p, 2]
        mx /= k
        my /= k
        mz /= k
        c00 = c01 = c02 = c11 = c12 = c22 = 0.0
        for j in range(k):
            p = idx[i, j]
            dx, dy, dz = xyz[p, 0] - mx, xyz[p, 1] - my, xyz[p, 2] - mz
            c00 += dx * dx
            c01 += dx * dy
            c02 += dx * dz
            c11 += dy * dy
            c12 += dy * dz
            c22 += dz * dz
        nx, ny, nz = _smallest_eigenvector(c00, c01, c02, c11, c12, c22)
        q = idx[i, 0]  # the point itself (its own nearest neighbour)
        if nx * (viewpoint[0] - xyz[q, 0]) + ny * (viewpoint[1] - xyz[q, 1]) + nz * (viewpoint[2] - xyz[q, 2]) < 0:
            nx, ny, nz = -nx, -ny, -nz
        out[i, 0] = nx
        out[i, 1] = ny
        out[i, 2] = nz


def pca_normals(
    xyz: np.ndarray,
    viewpoint: np.ndarray | None = None,
    k: int = NORMAL_NEIGHBOURS,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """(N, 3) float32 unit normals: the least-variance axis of each point's ``k`` nearest
    points, turned to face ``viewpoint`` (3,) (default the origin: a Graylight cloud's scanner).
    Points whose neighbourhood has no least-variance axis (fewer than three points, or all
    coincident) get a zero normal (unknown)."""
    xyz = np.ascontiguousarray(xyz, np.float64)
    n = xyz.shape[0]
    out = np.zeros((n, 3), np.float32)
    if n < 3:
        return out
    k = min(k, n)
    vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, np.float64)
    tree = tree or kdtree(xyz)
    for a in range(0, n, BLOCK):
        _, idx = tree.query(xyz[a : a + BLOCK], k=k, workers=cpu_budget())
        # The query lists each point first (distance 0) unless a coincident point ties with it.
        idx[:, 0] = np.arange(a, a + idx.shape[0])
        _normals_kernel(xyz, np.ascontiguousarray(idx, np.int64), vp, out[a : a + BLOCK])
    return out
