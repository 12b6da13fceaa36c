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

import numpy as np
from scipy.spatial import cKDTree

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
        d, _ = tree.query(xyz[a : a + BLOCK], k=k + 1, workers=-1)
        out[a : a + BLOCK] = d[:, 1:].mean(axis=1)
    return out


def pca_normals(
    xyz: np.ndarray,
    viewpoint: np.ndarray | None = None,
    k: int = NORMAL_NEIGHBOURS,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """(N, 3) float32 unit normals: the least-variance axis of each point's ``k`` nearest
    points, turned to face ``viewpoint`` (3,) (default the origin: a Graylight cloud's scanner).
    Points with fewer than three neighbours get a zero normal (unknown)."""
    n = xyz.shape[0]
    out = np.zeros((n, 3), np.float32)
    if n < 3:
        return out
    k = min(k, n)
    vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, np.float64)
    tree = tree or kdtree(xyz)
    for a in range(0, n, BLOCK):
        p = np.asarray(xyz[a : a + BLOCK], np.float64)
        _, idx = tree.query(p, k=k, workers=-1)
        nb = np.asarray(xyz, np.float64)[idx]  # (B, k, 3)
        nb -= nb.mean(axis=1, keepdims=True)
        cov = np.einsum("bki,bkj->bij", nb, nb)
        _w, v = np.linalg.eigh(cov)  # eigenvalues ascending: column 0 is the normal
        normal = v[:, :, 0]
        flip = np.einsum("bi,bi->b", normal, vp - p) < 0
        normal[flip] *= -1
        out[a : a + BLOCK] = normal
    return out
