"""Triangulation: decoded projector coordinates + calibrated rig -> coloured, oriented 3D points.

In: a :class:`~shared.scan.decode.Decoded` (per camera pixel: sub-pixel projector column, projector
row, colour) and a :class:`~shared.formats.rig.Rig` (OpenCV pinhole + five-parameter distortion on
both devices; ``X_projector = R @ X_camera + T``).
Out: a :class:`Triangulated`: points in the camera frame in the rig's units, their colours,
camera-facing unit normals, sample sizes ``Z / f_camera``, the (H, W) range image of Z and
the camera pixel of every point.

Each camera pixel's ray (undistorted with the camera's model) is intersected with the
plane through the projector's centre that contains its decoded column. A distorted projector
column is a curve, not a line, so the plane is the one tangent to the undistorted column
curve at the projector row where the ray meets it; that row is found by iterating
(start from the decoded row, intersect, project the point into the projector, repeat).
The decoded row then checks the result: a correspondence whose decoded row disagrees with
the row the point projects to (beyond the row code's own precision plus
``row_tolerance``) is rejected. Points with no support from their neighbours in the range
image (isolated spikes of a wrong code) are rejected too. Normals come from the range image
(cross product of neighbouring points' differences), turned to face the camera.
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numba
import numpy as np

from shared.core.files import atomic_file
from shared.core.jit import empty, kernel, zeros
from shared.core.threads import cpu_budget
from shared.formats.rig import Device, Rig
from shared.scan._bands import next_item, run_bands
from shared.scan.decode import Decoded, kernel_thread_scope

log = logging.getLogger(__name__)

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)
#: Margin in pixels around a device's image covered by its undistortion table.
_MARGIN = 8


@dataclass
class Triangulated:
    """Points of one scan, N of them; arrays row-aligned.

    xyz : (N, 3) float32, camera frame, rig units.
    rgb : (N, 3) uint8.
    normals : (N, 3) float32 unit vectors facing the camera.
    size : (N,) float32 world-space sample size ``Z / f_camera``.
    pixel : (N, 2) int32 camera pixel (x, y) of each point.
    range_image : (H, W) float32 Z, NaN where no point.
    stats : counts (JSON-ready).
    """

    xyz: np.ndarray
    rgb: np.ndarray
    normals: np.ndarray
    size: np.ndarray
    pixel: np.ndarray
    range_image: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def flat_index(self) -> np.ndarray:
        """(N,) int64 index of each point's pixel in the flattened (H, W) image."""
        return self.pixel[:, 1].astype(np.int64) * self.range_image.shape[1] + self.pixel[:, 0]


#: Points per cv2.undistortPoints call of a table: a few blocks a thread, so that the
#: iterative undistortion (the bulk of a table's cost) runs on every core.
_UNDISTORT_BLOCK = 1 << 16


def _undistort_points(pts: np.ndarray, dev: Device) -> np.ndarray:
    """cv2.undistortPoints of (N, 1, 2) float64 pixels, in blocks on a thread pool (OpenCV
    releases the GIL; each point is undistorted on its own, so blocks give the same values)."""
    blocks = [pts[i : i + _UNDISTORT_BLOCK] for i in range(0, len(pts), _UNDISTORT_BLOCK)]
    if len(blocks) == 1:
        return cv2.undistortPoints(pts, dev.K, dev.dist, criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
    with ThreadPoolExecutor(max_workers=cpu_budget()) as pool:
        parts = pool.map(lambda b: cv2.undistortPoints(b, dev.K, dev.dist, criteria=_UNDISTORT_CRITERIA), blocks)
        return np.concatenate([p.reshape(-1, 2) for p in parts])


def _undistort_table(dev: Device, stride: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Normalised undistorted coordinates of a grid over the device image (and a margin).

    Returns (a, b) maps of shape (gh, gw) float64 sampled at pixel (x0 + i*stride, y0 + j*stride)
    with x0 = y0 = -_MARGIN, and the origin offset.
    """
    xs = np.arange(-_MARGIN, dev.width + _MARGIN + stride, stride, dtype=np.float64)
    ys = np.arange(-_MARGIN, dev.height + _MARGIN + stride, stride, dtype=np.float64)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1).reshape(-1, 1, 2)
    if np.any(dev.dist != 0):
        und = _undistort_points(pts, dev)
    else:
        # A skew-free pinhole: invert K directly.
        Kinv = np.linalg.inv(dev.K)
        und = (pts.reshape(-1, 2) @ Kinv[:2, :2].T) + Kinv[:2, 2]
    return und[:, 0].reshape(gx.shape), und[:, 1].reshape(gx.shape), float(-_MARGIN)


@dataclass(frozen=True)
class RigTables:
    """What triangulation precomputes from a rig alone (cost: about a second of CPU for a
    1024x768 projector, mostly OpenCV's iterative undistortion): normalised undistorted
    coordinates of the camera on a 4-pixel grid and of the projector on every pixel, with
    the tangent of each undistorted projector column. All (gh, gw) float64."""

    cam_a: np.ndarray
    cam_b: np.ndarray
    cam_stride: float
    cam_org: float
    pa: np.ndarray
    pb: np.ndarray
    pta: np.ndarray
    ptb: np.ndarray
    p_org: float
    #: The same values interleaved for the kernels, one cache line a lookup instead of one per
    #: table: (gh, gw, 2) [cam_a, cam_b] and (gh, gw, 4) [pa, pb, pta, ptb], float64.
    cam_ab: np.ndarray = field(repr=False, compare=False, default_factory=lambda: np.empty((0, 0, 2)))
    p4: np.ndarray = field(repr=False, compare=False, default_factory=lambda: np.empty((0, 0, 4)))


def _packed(t: RigTables) -> RigTables:
    """``t`` with its interleaved copies (:attr:`RigTables.cam_ab`, :attr:`RigTables.p4`) filled."""
    return replace(t, cam_ab=np.ascontiguousarray(np.stack([t.cam_a, t.cam_b], axis=-1)),
                   p4=np.ascontiguousarray(np.stack([t.pa, t.pb, t.pta, t.ptb], axis=-1)))  # fmt: skip


def _rig_key(rig: Rig) -> tuple:
    return tuple((d.width, d.height, np.asarray(d.K, np.float64).tobytes(), np.asarray(d.dist, np.float64).tobytes())
                 for d in (rig.camera, rig.projector))  # fmt: skip


_TABLES: dict[tuple, RigTables] = {}
_TABLES_LOCK = threading.Lock()
_TABLE_FIELDS = ("cam_a", "cam_b", "pa", "pb", "pta", "ptb")
#: Rigs whose tables the cache folder keeps (about 30 MB each for a 1024x768 projector).
_TABLES_KEPT = 8


def _tables_file(key: tuple) -> Path | None:
    """Where the tables of a rig are kept between processes: ``$GRAYLIGHT_CACHE_DIR`` (default
    ``$XDG_CACHE_HOME/graylight``, ``~/.cache/graylight``), named by a hash of everything they
    depend on (devices, the undistortion criteria and OpenCV's version); None without a home."""
    root = os.environ.get("GRAYLIGHT_CACHE_DIR")
    if not root:
        base = os.environ.get("XDG_CACHE_HOME") or (str(Path.home() / ".cache") if Path.home().is_dir() else "")
        if not base:
            return None
        root = str(Path(base) / "graylight")
    h = hashlib.sha256(repr((key, _UNDISTORT_CRITERIA, _MARGIN, cv2.__version__)).encode())
    return Path(root) / "rig-tables" / f"{h.hexdigest()[:32]}.npz"


def _load_tables(path: Path | None) -> RigTables | None:
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in _TABLE_FIELDS}
            scalars = z["scalars"]
    except (OSError, ValueError, KeyError):
        return None  # unreadable (another version, a cut-off write): computed again
    return RigTables(arrays["cam_a"], arrays["cam_b"], float(scalars[0]), float(scalars[1]), arrays["pa"],
                     arrays["pb"], arrays["pta"], arrays["ptb"], float(scalars[2]))  # fmt: skip


def _save_tables(path: Path | None, t: RigTables) -> None:
    if path is None:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(path, suffix=".tmp.npz") as tmp:
            np.savez(tmp, **{k: getattr(t, k) for k in _TABLE_FIELDS},
                     scalars=np.array([t.cam_stride, t.cam_org, t.p_org], np.float64))  # fmt: skip
        # Tens of MB a rig: only the most recently written few are kept.
        for old in sorted(path.parent.glob("*.npz"), key=lambda f: f.stat().st_mtime)[:-_TABLES_KEPT]:
            old.unlink(missing_ok=True)
    except OSError as exc:  # a read-only home: the tables are only not kept
        log.debug("rig tables not cached at %s: %s", path, exc)


def rig_tables(rig: Rig) -> RigTables:
    """The :class:`RigTables` of ``rig``, computed once per rig: kept in this process (the
    last few rigs: a job-service worker triangulates many scans of one calibration) and in a
    file of the user's cache folder (:func:`_tables_file`), so that the next ``graylight scan``
    with the same calibration reads them (the same values, bit for bit) instead of computing.

    Thread-safe: :func:`shared.scan.pipeline.scan` computes them on a thread while the
    images are decoded."""
    key = _rig_key(rig)
    with _TABLES_LOCK:
        if key in _TABLES:
            return _TABLES[key]
    path = _tables_file(key)
    tables = _load_tables(path)
    if tables is None:
        stride = 4
        cam_a, cam_b, cam_org = _undistort_table(rig.camera, stride)
        pa, pb, p_org = _undistort_table(rig.projector, 1)
        # Tangent of the undistorted column curve along the projector row (per projector pixel).
        # C order throughout (the same as tables read from the cache): one kernel signature.
        c = np.ascontiguousarray
        tables = RigTables(c(cam_a), c(cam_b), float(stride), cam_org, c(pa), c(pb), c(np.gradient(pa, axis=0)),
                           c(np.gradient(pb, axis=0)), p_org)  # fmt: skip
        _save_tables(path, tables)
    tables = _packed(tables)
    with _TABLES_LOCK:
        while len(_TABLES) >= 4:
            _TABLES.pop(next(iter(_TABLES)))
        _TABLES[key] = tables
    return tables


@numba.njit(inline="always")
def _cell(gh, gw, u, v):  # pragma: no cover
    """Bilinear cell of table coordinates (u, v) on a (gh, gw) grid, clamped inside it: the
    corner (i, j) and the fractions (fu, fv)."""
    if u < 0.0:
        u = 0.0
    if v < 0.0:
        v = 0.0
    if u > gw - 1.001:
        u = gw - 1.001
    if v > gh - 1.001:
        v = gh - 1.001
    i = int(u)
    j = int(v)
    return i, j, u - i, v - j


@numba.njit(inline="always")
def _lerp(tab, i, j, fu, fv, c):  # pragma: no cover
    """Channel ``c`` of an interleaved (gh, gw, k) table at the cell of :func:`_cell`; the
    products and sums in one fixed order (the same values whichever tables share the cell)."""
    return (tab[j, i, c] * (1 - fu) * (1 - fv) + tab[j, i + 1, c] * fu * (1 - fv)
            + tab[j + 1, i, c] * (1 - fu) * fv + tab[j + 1, i + 1, c] * fu * fv)


#: Camera rows per parallel work item of the triangulation kernels.
_TRI_BAND = 8


# numba's parallel loop, not a plain kernel on run_bands' threads as the others: numba compiles
# a parallel loop's body with its arrays marked as not aliasing each other (none here does),
# which this long loop's code needs: as a plain kernel it ran 200 ms against 126 ms (one
# thread, the bench's 2048x1536 capture). It costs 4-5 s more to compile.
@numba.njit(parallel=True, cache=True)
def _intersect_grid(column, row, row_span, has_row, row_tol, cam_ab, cam_stride, cam_org,
                    p4, p_org, R, T, Kp, distp, iters, P, valid, reasons, n_threads):  # pragma: no cover
    """Ray-plane intersection for every decoded pixel of the (H, W) image.

    cam_ab: (gh, gw, 2) camera table [a, b]; p4: (gh, gw, 4) projector table [a, b, ta, tb]
    (:class:`RigTables`), float64. Writes P (H, W, 3) float32 points (NaN where none) and
    valid (H, W); counts rejections in reasons (H, 2): [geometry, row mismatch] per image row.
    ``n_threads``: numba's threads now (bands of rows are handed out dynamically, :mod:`._bands`).

    One camera row at a time in passes over the row: the rays first, then each iteration of
    the intersection for every pixel still going, then the checks. One pixel's iteration is a
    long chain of dependent operations (table lookup, plane, division, projection); a pass
    keeps many pixels' chains in flight at once, where a whole pixel at a time left the core
    waiting on each chain. Every pixel gets the same operations in the same order as before.
    """
    H, W = column.shape
    cgh, cgw = cam_ab.shape[0], cam_ab.shape[1]
    pgh, pgw = p4.shape[0], p4.shape[1]
    fyp = Kp[1, 1]
    cyp = Kp[1, 2]
    k1 = distp[0]
    k2 = distp[1]
    p1 = distp[2]
    p2 = distp[3]
    k3 = distp[4]
    n_bands = (H + _TRI_BAND - 1) // _TRI_BAND
    counter = zeros(1, np.int64)
    for _thread in numba.prange(n_threads):  # bands handed out by next_item (see _bands)
        # Row buffers: ray (rx, ry), projector column and current row, the point, the state
        # (0 not decoded, 1 going, 2 geometry failed) and the last projected row.
        rxb = empty(W, np.float64)
        ryb = empty(W, np.float64)
        pcb = empty(W, np.float64)
        qb = empty(W, np.float64)
        Xb = empty(W, np.float64)
        Yb = empty(W, np.float64)
        Zb = empty(W, np.float64)
        st = empty(W, np.uint8)
        while True:
            band = next_item(counter)
            if band >= n_bands:
                break
            for yu in range(band * _TRI_BAND, min(H, band * _TRI_BAND + _TRI_BAND)):
                y = np.int64(yu)
                v = (y - cam_org) / cam_stride
                for x in range(W):
                    P[y, x, 0] = np.nan
                    P[y, x, 1] = np.nan
                    P[y, x, 2] = np.nan
                    valid[y, x] = False
                    st[x] = 0
                    pcol = column[y, x]
                    if not (pcol == pcol):
                        continue
                    r0 = row[y, x]
                    if has_row and not (r0 == r0):
                        continue
                    u = (x - cam_org) / cam_stride
                    ci, cj, cfu, cfv = _cell(cgh, cgw, u, v)
                    rxb[x] = _lerp(cam_ab, ci, cj, cfu, cfv, 0)
                    ryb[x] = _lerp(cam_ab, ci, cj, cfu, cfv, 1)
                    pcb[x] = pcol - p_org
                    qb[x] = r0 if has_row else cyp
                    Xb[x] = np.nan
                    st[x] = 1
                for _ in range(iters):
                    for x in range(W):
                        if st[x] != 1:
                            continue
                        rx = rxb[x]
                        ry = ryb[x]
                        qc = qb[x] - p_org
                        pi, pj, pfu, pfv = _cell(pgh, pgw, pcb[x], qc)
                        a = _lerp(p4, pi, pj, pfu, pfv, 0)
                        b = _lerp(p4, pi, pj, pfu, pfv, 1)
                        ta = _lerp(p4, pi, pj, pfu, pfv, 2)
                        tb = _lerp(p4, pi, pj, pfu, pfv, 3)
                        # Plane through the projector centre containing (a, b, 1) and the column tangent (ta, tb, 0).
                        n0 = -tb
                        n1 = ta
                        n2 = a * tb - b * ta
                        # In the camera frame: (R^T n) . X = -n . T
                        m0 = R[0, 0] * n0 + R[1, 0] * n1 + R[2, 0] * n2
                        m1 = R[0, 1] * n0 + R[1, 1] * n1 + R[2, 1] * n2
                        m2 = R[0, 2] * n0 + R[1, 2] * n1 + R[2, 2] * n2
                        den = m0 * rx + m1 * ry + m2
                        num = -(n0 * T[0] + n1 * T[1] + n2 * T[2])
                        if den == 0.0:
                            st[x] = 2
                            continue
                        lam = num / den
                        if lam <= 0.0:
                            st[x] = 2
                            continue
                        X = lam * rx
                        Y = lam * ry
                        Z = lam
                        xp = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + T[0]
                        yp = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + T[1]
                        zp = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + T[2]
                        if zp <= 0.0:
                            st[x] = 2
                            continue
                        xn = xp / zp
                        yn = yp / zp
                        r2 = xn * xn + yn * yn
                        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
                        qb[x] = fyp * yd + cyp
                        Xb[x] = X
                        Yb[x] = Y
                        Zb[x] = Z
                n_geom = 0
                n_row = 0
                for x in range(W):
                    s = st[x]
                    if s == 0:
                        continue
                    X = Xb[x]
                    if s == 2 or not (X == X):
                        n_geom += 1
                        continue
                    if has_row and abs(qb[x] - row[y, x]) > 0.5 * row_span[y, x] + row_tol:
                        n_row += 1
                        continue
                    P[y, x, 0] = X
                    P[y, x, 1] = Yb[x]
                    P[y, x, 2] = Zb[x]
                    valid[y, x] = True
                reasons[y, 0] = n_geom
                reasons[y, 1] = n_row


@kernel(error_model="numpy")  # what numba's parallel loops compiled with
def _gather(keep, P, normals, colour, offsets, inv_f, xyz, nrm, rgb, size, pixel, counter):  # pragma: no cover
    """Compact the kept pixels of the images into point arrays, row by row (offsets: per-row
    start). One thread's share (:func:`shared.scan._bands.run_bands`)."""
    H, W = keep.shape
    n_bands = (H + _TRI_BAND - 1) // _TRI_BAND
    while True:
        band = next_item(counter)
        if band >= n_bands:
            break
        for yu in range(band * _TRI_BAND, min(H, band * _TRI_BAND + _TRI_BAND)):
            y = np.int64(yu)
            k = offsets[y]
            for x in range(W):
                if not keep[y, x]:
                    continue
                for c in range(3):
                    xyz[k, c] = P[y, x, c]
                    nrm[k, c] = normals[y, x, c]
                    rgb[k, c] = colour[y, x, c]
                size[k] = P[y, x, 2] * inv_f
                pixel[k, 0] = x
                pixel[k, 1] = y
                k += 1


@kernel(error_model="numpy")  # what numba's parallel loops compiled with
def _support(P, valid, rel_tol, min_support, keep, counter):  # pragma: no cover
    """Reject points without ``min_support`` neighbours (8-neighbourhood) within ``rel_tol * Z``
    of their depth: ``keep`` (H, W) bool. One thread's share (:func:`shared.scan._bands.run_bands`)."""
    H, W = valid.shape
    n_bands = (H + _TRI_BAND - 1) // _TRI_BAND
    while True:
        band = next_item(counter)
        if band >= n_bands:
            break
        for y in range(band * _TRI_BAND, min(H, band * _TRI_BAND + _TRI_BAND)):
            for x in range(W):
                keep[y, x] = False
                if not valid[y, x]:
                    continue
                z = P[y, x, 2]
                tol = rel_tol * z
                cnt = 0
                for dy in range(-1, 2):
                    yy = y + dy
                    if yy < 0 or yy >= H:
                        continue
                    for dx in range(-1, 2):
                        xx = x + dx
                        if (dx == 0 and dy == 0) or xx < 0 or xx >= W:
                            continue
                        if valid[yy, xx] and abs(P[yy, xx, 2] - z) <= tol:
                            cnt += 1
                keep[y, x] = cnt >= min_support


@kernel(error_model="numpy")  # what numba's parallel loops compiled with
def _normals(P, rel_tol, keep, normals, counter):  # pragma: no cover
    """Normals of the kept points from their kept neighbours' differences, after :func:`_support`
    (which every row's neighbours must have finished): ``normals`` (H, W, 3). One thread's share."""
    H, W = keep.shape
    n_bands = (H + _TRI_BAND - 1) // _TRI_BAND
    while True:
        band = next_item(counter)
        if band >= n_bands:
            break
        for yu in range(band * _TRI_BAND, min(H, band * _TRI_BAND + _TRI_BAND)):
            y = np.int64(yu)
            for x in range(W):
                if not keep[y, x]:
                    continue
                z = P[y, x, 2]
                tol = rel_tol * z
                # Horizontal and vertical differences: central where both sides agree, else one-sided.
                hx0 = x - 1 if x > 0 and keep[y, x - 1] and abs(P[y, x - 1, 2] - z) <= tol else x
                hx1 = x + 1 if x + 1 < W and keep[y, x + 1] and abs(P[y, x + 1, 2] - z) <= tol else x
                vy0 = y - 1 if y > 0 and keep[y - 1, x] and abs(P[y - 1, x, 2] - z) <= tol else y
                vy1 = y + 1 if y + 1 < H and keep[y + 1, x] and abs(P[y + 1, x, 2] - z) <= tol else y
                X0 = P[y, x, 0]
                Y0 = P[y, x, 1]
                if hx0 == hx1 or vy0 == vy1:
                    # No tangent estimate: face the camera.
                    nrm = np.sqrt(X0 * X0 + Y0 * Y0 + z * z)
                    normals[y, x, 0] = -X0 / nrm
                    normals[y, x, 1] = -Y0 / nrm
                    normals[y, x, 2] = -z / nrm
                    continue
                ax = P[y, hx1, 0] - P[y, hx0, 0]
                ay = P[y, hx1, 1] - P[y, hx0, 1]
                az = P[y, hx1, 2] - P[y, hx0, 2]
                bx = P[vy1, x, 0] - P[vy0, x, 0]
                by = P[vy1, x, 1] - P[vy0, x, 1]
                bz = P[vy1, x, 2] - P[vy0, x, 2]
                nx = ay * bz - az * by
                ny = az * bx - ax * bz
                nz = ax * by - ay * bx
                nrm = np.sqrt(nx * nx + ny * ny + nz * nz)
                if nrm == 0.0:
                    nrm = np.sqrt(X0 * X0 + Y0 * Y0 + z * z)
                    nx = -X0
                    ny = -Y0
                    nz = -z
                if nx * X0 + ny * Y0 + nz * z > 0.0:
                    nx = -nx
                    ny = -ny
                    nz = -nz
                normals[y, x, 0] = nx / nrm
                normals[y, x, 1] = ny / nrm
                normals[y, x, 2] = nz / nrm


def load_kernels(rig: Rig, tables: RigTables | None = None) -> RigTables:
    """Load the triangulation kernels into this process (from numba's cache; compiled if it
    lacks them) by triangulating a 4x4 image with nothing decoded, and return the rig's
    tables: :func:`shared.scan.pipeline.scan` runs this on a thread while the images are read
    and decoded, so the first real triangulation does not wait for the loading. The calls
    have the real ones' signatures (a decode's arrays are C-ordered float32 and int8)."""
    tb = tables if tables is not None else rig_tables(rig)
    nan = np.full((4, 4), np.nan, np.float32)
    blank = Decoded(column=nan, row=nan.copy(), confidence=np.zeros((4, 4), np.float32),
                    colour=np.zeros((4, 4, 3), np.uint8), lit=np.zeros((4, 4), np.bool_),
                    column_level=np.full((4, 4), -1, np.int8), row_level=np.full((4, 4), -1, np.int8))  # fmt: skip
    triangulate(blank, rig, tables=tb)
    return tb


def triangulate(
    decoded: Decoded,
    rig: Rig,
    *,
    row_tolerance: float = 3.0,
    support_tolerance: float = 0.01,
    min_support: int = 2,
    iterations: int = 2,
    tables: RigTables | None = None,
) -> Triangulated:
    """Triangulate every decoded camera pixel against its projector column plane.

    Parameters
    ----------
    decoded : per-pixel projector coordinates; (H, W) must equal the rig camera's size.
    rig : calibrated camera-projector pair.
    row_tolerance : projector rows allowed between the decoded row (its code's centre) and
        the row the point projects to, beyond half the row code's span.
    support_tolerance : relative depth difference within which a neighbour supports a point.
    min_support : neighbours (of 8) a point needs to be kept; 0 keeps isolated points.
    iterations : ray-plane intersections per point (the plane depends on the row).
    tables : ``rig_tables(rig)``, when the caller computed them ahead (None: looked up here).

    Returns
    -------
    Triangulated (see there).
    """
    with kernel_thread_scope():
        return _triangulate(decoded, rig, row_tolerance, support_tolerance, min_support, iterations, tables)


def _triangulate(
    decoded: Decoded, rig: Rig, row_tolerance: float, support_tolerance: float, min_support: int, iterations: int,
    tables: RigTables | None,
) -> Triangulated:
    t0 = time.perf_counter()
    h, w = decoded.shape
    cam, proj = rig.camera, rig.projector
    has_row = bool(np.isfinite(decoded.row).any())
    if has_row and decoded.row_level is not None:
        row_span = np.exp2(np.maximum(decoded.row_level, 0).astype(np.float32))
    else:
        row_span = np.ones((1, 1), np.float32) if not has_row else np.ones((h, w), np.float32)
    tb = tables if tables is not None else rig_tables(rig)
    if tb.p4.size == 0:  # tables made without rig_tables()
        tb = _packed(tb)
    P = np.empty((h, w, 3), np.float32)
    vmask = np.empty((h, w), bool)
    reasons = np.zeros((h, 2), np.int64)
    _intersect_grid(np.ascontiguousarray(decoded.column, np.float32), np.ascontiguousarray(decoded.row, np.float32),
                    row_span, has_row, float(row_tolerance), tb.cam_ab, tb.cam_stride, tb.cam_org,
                    tb.p4, tb.p_org, np.ascontiguousarray(rig.R, np.float64),
                    np.ascontiguousarray(rig.T, np.float64).ravel(), np.ascontiguousarray(proj.K, np.float64),
                    np.ascontiguousarray(proj.dist[:5], np.float64), iterations, P, vmask, reasons, numba.get_num_threads())
    del row_span
    t_int = time.perf_counter()
    n_geom, n_row_reject = (int(v) for v in reasons.sum(axis=0))
    keep = np.empty((h, w), bool)
    normals_img = np.zeros((h, w, 3), np.float32)
    run_bands(_support, P, vmask, np.float32(support_tolerance), min_support, keep)
    run_bands(_normals, P, np.float32(support_tolerance), keep, normals_img)
    n_valid = int(np.count_nonzero(vmask))
    del vmask
    counts = np.count_nonzero(keep, axis=1)
    offsets = np.zeros(h, np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    n_pts = int(counts.sum())
    xyz = np.empty((n_pts, 3), np.float32)
    normals = np.empty((n_pts, 3), np.float32)
    rgb = np.empty((n_pts, 3), np.uint8)
    size = np.empty(n_pts, np.float32)
    pixel = np.empty((n_pts, 2), np.int32)
    f_cam = 0.5 * (cam.fx + cam.fy)
    run_bands(_gather, keep, P, normals_img, np.ascontiguousarray(decoded.colour), offsets, np.float32(1.0 / f_cam),
              xyz, normals, rgb, size, pixel)
    del normals_img
    # The range image: Z where a point was kept (P is reused in place to save memory).
    range_image = np.ascontiguousarray(P[..., 2])
    range_image[~keep] = np.nan
    del P
    n_unsupported = n_valid - n_pts
    n = n_valid + n_geom + n_row_reject
    kx = pixel[:, 0]
    t_end = time.perf_counter()
    stats = {
        "decoded_pixels": int(n),
        "points": int(len(kx)),
        "rejected_geometry": n_geom,
        "rejected_row_mismatch": n_row_reject,
        "rejected_unsupported": n_unsupported,
        "row_check": has_row,
        "seconds_intersect": round(t_int - t0, 4),
        "seconds_total": round(t_end - t0, 4),
    }
    log.info("triangulated %d points from %d decoded pixels", len(kx), n)
    return Triangulated(
        xyz=xyz,
        rgb=rgb,
        normals=normals,
        size=size,
        pixel=pixel,
        range_image=range_image,
        stats=stats,
    )
