"""Compiled per-pixel kernels of the virtual rig (numba): lens models, ray casting of planes, spheres and
meshes, filtered textures, projector lighting (shadow map, falloff, blur, specular), projected-pattern
composition and sensor noise.

Conventions: OpenCV pinhole + five-parameter distortion (k1, k2, p1, p2, k3); pixel centres at
integer coordinates. A *ray map* holds, per pixel, the undistorted normalised coordinates
``(x, y)`` of the pixel's ray ``(x, y, 1)`` in the device frame, so a surface point is
``t * (x, y, 1)`` with ``t`` its depth (device Z), in mm.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_NJIT = {"cache": True, "nogil": True, "fastmath": False}


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's forward distortion of normalised coordinates (same formula as ``cv2.projectPoints``).

    Parameters
    ----------
    x, y : (...) float arrays, undistorted normalised coordinates
    dist : (5,) k1, k2, p1, p2, k3

    Returns
    -------
    xd, yd : (...) distorted normalised coordinates, same dtype as the input
    """
    k1, k2, p1, p2, k3 = (float(v) for v in np.asarray(dist, float).ravel()[:5])
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def project_points(points: np.ndarray, K: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) of device-frame points (..., 3); NaN where Z <= 0. float64."""
    p = np.asarray(points, dtype=np.float64)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(z > 0, p[..., 0] / z, np.nan)
        y = np.where(z > 0, p[..., 1] / z, np.nan)
    xd, yd = distort_normalized(x, y, dist)
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    return u, v


@numba.njit(**_NJIT)
def _undistort_grid(fx, fy, cx, cy, skew, k1, k2, p1, p2, k3, width, height, rx, ry):
    for v in range(height):
        yd = (v - cy) / fy
        for u in range(width):
            xd = (u - cx - skew * yd) / fx
            x = xd
            y = yd
            # Newton on the 2x2 distortion map: converges to machine precision in a few steps
            # for any lens a real device uses, unlike OpenCV's default 5 fixed-point steps.
            for _ in range(30):
                r2 = x * x + y * y
                rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d rad / d r2
                fxv = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
                fyv = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
                j11 = rad + x * drad * 2.0 * x + 2.0 * p1 * y + p2 * 6.0 * x
                j12 = x * drad * 2.0 * y + 2.0 * p1 * x + p2 * 2.0 * y
                j21 = y * drad * 2.0 * x + p1 * 2.0 * x + 2.0 * p2 * y
                j22 = rad + y * drad * 2.0 * y + p1 * 6.0 * y + 2.0 * p2 * x
                det = j11 * j22 - j12 * j21
                if det == 0.0:
                    break
                dx = (j22 * fxv - j12 * fyv) / det
                dy = (-j21 * fxv + j11 * fyv) / det
                x -= dx
                y -= dy
                if abs(dx) < 1e-15 and abs(dy) < 1e-15:
                    break
            rx[v, u] = x
            ry[v, u] = y


def undistort_grid(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray map of a distorted device: undistorted normalised (x, y) of every pixel centre.

    Returns
    -------
    rx, ry : (height, width) float64
    """
    rx = np.empty((height, width), np.float64)
    ry = np.empty((height, width), np.float64)
    d = np.zeros(5)
    dd = np.asarray(dist, float).ravel()[:5]
    d[: dd.size] = dd
    _undistort_grid(
        float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(K[0, 1]),
        d[0], d[1], d[2], d[3], d[4], width, height, rx, ry,
    )
    return rx, ry


@numba.njit(**_NJIT)
def _to_pixel(x, y, fx, fy, cx, cy, skew, k1, k2, p1, p2, k3):
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return fx * xd + skew * yd + cx, fy * yd + cy


@numba.njit(**_NJIT)
def _raster_mesh(verts, faces, rx, ry, fx, fy, cx, cy, skew, k1, k2, p1, p2, k3, near, zbuf, tid, tid_offset):
    height, width = zbuf.shape
    for f in range(faces.shape[0]):
        ia = faces[f, 0]
        ib = faces[f, 1]
        ic = faces[f, 2]
        az = verts[ia, 2]
        bz = verts[ib, 2]
        cz = verts[ic, 2]
        if az < near or bz < near or cz < near:
            continue
        ax = verts[ia, 0] / az
        ay = verts[ia, 1] / az
        bx = verts[ib, 0] / bz
        by = verts[ib, 1] / bz
        cxn = verts[ic, 0] / cz
        cyn = verts[ic, 1] / cz
        area = (bx - ax) * (cyn - ay) - (by - ay) * (cxn - ax)
        if area == 0.0:
            continue
        ua, va = _to_pixel(ax, ay, fx, fy, cx, cy, skew, k1, k2, p1, p2, k3)
        ub, vb = _to_pixel(bx, by, fx, fy, cx, cy, skew, k1, k2, p1, p2, k3)
        uc, vc = _to_pixel(cxn, cyn, fx, fy, cx, cy, skew, k1, k2, p1, p2, k3)
        umin = min(ua, ub, uc)
        umax = max(ua, ub, uc)
        vmin = min(va, vb, vc)
        vmax = max(va, vb, vc)
        # Distortion bends a triangle's straight edges in pixel space: widen the box by a
        # margin growing with the triangle's size (mesh triangles span only a few pixels).
        margin = 1.5 + 0.02 * max(umax - umin, vmax - vmin)
        u0 = max(int(math.floor(umin - margin)), 0)
        u1 = min(int(math.ceil(umax + margin)), width - 1)
        v0 = max(int(math.floor(vmin - margin)), 0)
        v1 = min(int(math.ceil(vmax + margin)), height - 1)
        if u0 > u1 or v0 > v1:
            continue
        # Plane of the triangle in the device frame: n . X = d.
        e1x = verts[ib, 0] - verts[ia, 0]
        e1y = verts[ib, 1] - verts[ia, 1]
        e1z = bz - az
        e2x = verts[ic, 0] - verts[ia, 0]
        e2y = verts[ic, 1] - verts[ia, 1]
        e2z = cz - az
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        dpl = nx * verts[ia, 0] + ny * verts[ia, 1] + nz * az
        inv_area = 1.0 / area
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                x = rx[v, u]
                y = ry[v, u]
                # Barycentric coordinates in normalised space: perspective maps the triangle to a
                # triangle there, so this inside test is exact.
                w0 = ((bx - x) * (cyn - y) - (by - y) * (cxn - x)) * inv_area
                w1 = ((cxn - x) * (ay - y) - (cyn - y) * (ax - x)) * inv_area
                w2 = 1.0 - w0 - w1
                if w0 < -1e-12 or w1 < -1e-12 or w2 < -1e-12:
                    continue
                den = nx * x + ny * y + nz
                if den == 0.0:
                    continue
                t = dpl / den
                if t > near and t < zbuf[v, u]:
                    zbuf[v, u] = t
                    tid[v, u] = f + tid_offset


def raster_mesh(
    vertices_dev: np.ndarray,
    faces: np.ndarray,
    rx: np.ndarray,
    ry: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    zbuf: np.ndarray,
    tid: np.ndarray,
    tid_offset: int = 0,
    near: float = 1.0,
) -> None:
    """Ray-cast a triangle mesh into a device's depth buffer, in place (z-buffer).

    Each pixel's ray ``(rx, ry, 1)`` is intersected exactly with the triangles whose projected
    bounding box covers the pixel, so depths are exact for distorted devices as well.

    Parameters
    ----------
    vertices_dev : (V, 3) float64, vertices in the device frame (mm)
    faces : (F, 3) int32
    rx, ry : (H, W) float64 ray map of the device (:func:`undistort_grid`)
    K, dist : the device's camera matrix and distortion (used only to find each triangle's pixels)
    zbuf : (H, W) float64, depth buffer (inf = empty); updated where a triangle is nearer
    tid : (H, W) int32, receives ``face index + tid_offset`` where a triangle wins
    """
    d = np.zeros(5)
    dd = np.asarray(dist, float).ravel()[:5]
    d[: dd.size] = dd
    _raster_mesh(
        np.ascontiguousarray(vertices_dev, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int32),
        rx, ry, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(K[0, 1]),
        d[0], d[1], d[2], d[3], d[4], float(near), zbuf, tid, int(tid_offset),
    )


@numba.njit(**_NJIT)
def _texture_filtered(tex, x, y, sx, sy, out):
    h, w, nc = tex.shape
    inv_sqrt2 = 1.0 / math.sqrt(2.0)
    for i in range(x.shape[0]):
        xi = x[i]
        yi = y[i]
        sxi = max(sx[i], 1e-3)
        syi = max(sy[i], 1e-3)
        j0 = int(math.floor(xi - 3.5 * sxi))
        j1 = int(math.floor(xi + 3.5 * sxi))
        r0 = int(math.floor(yi - 3.5 * syi))
        r1 = int(math.floor(yi + 3.5 * syi))
        for c in range(nc):
            out[i, c] = 0.0
        for r in range(r0, r1 + 1):
            # Texel r covers [r, r + 1): its Gaussian-footprint weight is a difference of erfs.
            wy = 0.5 * (math.erf((r + 1 - yi) * inv_sqrt2 / syi) - math.erf((r - yi) * inv_sqrt2 / syi))
            if wy <= 0.0:
                continue
            rr = min(max(r, 0), h - 1)
            for j in range(j0, j1 + 1):
                wx = 0.5 * (math.erf((j + 1 - xi) * inv_sqrt2 / sxi) - math.erf((j - xi) * inv_sqrt2 / sxi))
                if wx <= 0.0:
                    continue
                jj = min(max(j, 0), w - 1)
                wgt = wx * wy
                for c in range(nc):
                    out[i, c] += wgt * tex[rr, jj, c]


def texture_filtered(tex: np.ndarray, x: np.ndarray, y: np.ndarray, sx: np.ndarray, sy: np.ndarray) -> np.ndarray:
    """Area-filtered lookup of a piecewise-constant texture (texel (r, c) covers [c, c+1) x [r, r+1)).

    Each sample integrates the texture under a Gaussian footprint (std ``sx``, ``sy`` texels), so
    sharp printed edges keep their sub-pixel position in the rendered image (pixel integration).

    Parameters
    ----------
    tex : (h, w, C) float32
    x, y : (N,) float64 texel coordinates
    sx, sy : (N,) float64 footprint standard deviations in texels (keep them below ~2: use a
        downsampled texture for minification)

    Returns
    -------
    (N, C) float32
    """
    out = np.empty((x.shape[0], tex.shape[2]), np.float32)
    _texture_filtered(np.ascontiguousarray(tex, np.float32), x, y, sx, sy, out)
    return out


@numba.njit(**_NJIT)
def _cast_plane(rx, ry, Rdc, C, p0, ex, ey, n, w, h, tbest, surf, sid):
    height, width = rx.shape
    num = n[0] * (p0[0] - C[0]) + n[1] * (p0[1] - C[1]) + n[2] * (p0[2] - C[2])
    for r in range(height):
        for c in range(width):
            x = rx[r, c]
            y = ry[r, c]
            d0 = Rdc[0, 0] * x + Rdc[1, 0] * y + Rdc[2, 0]
            d1 = Rdc[0, 1] * x + Rdc[1, 1] * y + Rdc[2, 1]
            d2 = Rdc[0, 2] * x + Rdc[1, 2] * y + Rdc[2, 2]
            den = n[0] * d0 + n[1] * d1 + n[2] * d2
            if den == 0.0:
                continue
            t = num / den
            if t <= 0.0 or t >= tbest[r, c]:
                continue
            q0 = C[0] + t * d0 - p0[0]
            q1 = C[1] + t * d1 - p0[1]
            q2 = C[2] + t * d2 - p0[2]
            px = q0 * ex[0] + q1 * ex[1] + q2 * ex[2]
            py = q0 * ey[0] + q1 * ey[1] + q2 * ey[2]
            if 0.0 <= px < w and 0.0 <= py < h:
                tbest[r, c] = t
                surf[r, c] = sid


@numba.njit(**_NJIT)
def _cast_sphere(rx, ry, Rdc, C, centre, radius, tbest, surf, sid):
    height, width = rx.shape
    o0 = C[0] - centre[0]
    o1 = C[1] - centre[1]
    o2 = C[2] - centre[2]
    cc = o0 * o0 + o1 * o1 + o2 * o2 - radius * radius
    for r in range(height):
        for c in range(width):
            x = rx[r, c]
            y = ry[r, c]
            d0 = Rdc[0, 0] * x + Rdc[1, 0] * y + Rdc[2, 0]
            d1 = Rdc[0, 1] * x + Rdc[1, 1] * y + Rdc[2, 1]
            d2 = Rdc[0, 2] * x + Rdc[1, 2] * y + Rdc[2, 2]
            a = d0 * d0 + d1 * d1 + d2 * d2
            b = d0 * o0 + d1 * o1 + d2 * o2
            disc = b * b - a * cc
            if disc < 0.0:
                continue
            sq = math.sqrt(disc)
            t = (-b - sq) / a
            if t <= 1e-6:
                t = (-b + sq) / a
                if t <= 1e-6:
                    continue
            if t < tbest[r, c]:
                tbest[r, c] = t
                surf[r, c] = sid


def cast_plane(rx: np.ndarray, ry: np.ndarray, R_dc: np.ndarray, C: np.ndarray, origin: np.ndarray,
               ex: np.ndarray, ey: np.ndarray, size: tuple[float, float], tbest: np.ndarray, surf: np.ndarray,
               sid: int) -> None:
    """Z-buffer a rectangle ``origin + x * ex + y * ey`` (0 <= x < w, 0 <= y < h) into ``tbest``/``surf``, in place.

    Rays are ``R_dc.T @ (rx, ry, 1)`` from the device centre ``C`` (camera frame); ``t`` is device depth.
    """
    n = np.cross(ex, ey)
    _cast_plane(rx, ry, np.ascontiguousarray(R_dc, np.float64), np.asarray(C, np.float64), np.asarray(origin, np.float64),
                np.asarray(ex, np.float64), np.asarray(ey, np.float64), n, float(size[0]), float(size[1]), tbest, surf, sid)


def cast_sphere(rx: np.ndarray, ry: np.ndarray, R_dc: np.ndarray, C: np.ndarray, centre: np.ndarray, radius: float,
                tbest: np.ndarray, surf: np.ndarray, sid: int) -> None:
    """Z-buffer a sphere into ``tbest``/``surf``, in place (see :func:`cast_plane`)."""
    _cast_sphere(rx, ry, np.ascontiguousarray(R_dc, np.float64), np.asarray(C, np.float64),
                 np.asarray(centre, np.float64), float(radius), tbest, surf, sid)


@numba.njit(**_NJIT)
def _plane_pixels(rx, ry, index, p0, ex, ey, xy, foot):
    height, width = rx.shape
    n0 = ex[1] * ey[2] - ex[2] * ey[1]
    n1 = ex[2] * ey[0] - ex[0] * ey[2]
    n2 = ex[0] * ey[1] - ex[1] * ey[0]
    num = n0 * p0[0] + n1 * p0[1] + n2 * p0[2]
    for i in range(index.shape[0]):
        r = index[i] // width
        c = index[i] % width
        px = 0.0
        py = 0.0
        f0 = 0.0
        f1 = 0.0
        for k in range(3):
            rr = r
            cc = c
            if k == 1:
                cc = c + 1 if c + 1 < width else c - 1
            elif k == 2:
                rr = r + 1 if r + 1 < height else r - 1
            x = rx[rr, cc]
            y = ry[rr, cc]
            t = num / (n0 * x + n1 * y + n2)
            q0 = t * x - p0[0]
            q1 = t * y - p0[1]
            q2 = t - p0[2]
            qx = q0 * ex[0] + q1 * ex[1] + q2 * ex[2]
            qy = q0 * ey[0] + q1 * ey[1] + q2 * ey[2]
            if k == 0:
                px = qx
                py = qy
            else:
                f0 += (qx - px) ** 2
                f1 += (qy - py) ** 2
        xy[i, 0] = px
        xy[i, 1] = py
        foot[i, 0] = math.sqrt(f0)
        foot[i, 1] = math.sqrt(f1)


def plane_pixels(rx: np.ndarray, ry: np.ndarray, index: np.ndarray, origin: np.ndarray, ex: np.ndarray,
                 ey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plane coordinates (N, 2) mm of camera pixels ``index`` (flat) on the plane ``origin + x ex + y ey``,
    and the size (N, 2) mm of one pixel step there along the plane's x and y axes."""
    xy = np.empty((index.shape[0], 2), np.float64)
    foot = np.empty((index.shape[0], 2), np.float64)
    _plane_pixels(rx, ry, np.ascontiguousarray(index, np.int64), np.asarray(origin, np.float64),
                  np.asarray(ex, np.float64), np.asarray(ey, np.float64), xy, foot)
    return xy, foot


@numba.njit(**_NJIT)
def _compose(index, A, B, off, frac, table, other, img):
    nc = A.shape[1]
    for i in range(index.shape[0]):
        o = off[i]
        p = (table[o] + frac[i] * (table[o + 1] - table[o])) * other[i]
        j = index[i]
        for c in range(nc):
            img[j, c] = p * A[i, c] + B[i, c]


def compose_image(index: np.ndarray, A: np.ndarray, B: np.ndarray, off: np.ndarray, frac: np.ndarray,
                  table: np.ndarray, other: np.ndarray, img: np.ndarray) -> None:
    """``img[index] = P * A + B``, in place, with ``P = lerp(table, off, frac) * other`` the projected pattern.

    Parameters
    ----------
    index : (N,) int64 flat pixel indices
    A, B : (N, C) float32 per-pixel coefficient of the pattern value and constant term
    off : (N,) int32 index into the flattened (blur level, fine position) profile ``table``
    frac : (N,) float32 linear-interpolation weight between ``off`` and ``off + 1``
    table : flattened (L * n,) float32 profile along the pattern's varying axis
    other : (N,) float32 the profile factor along the other axis (the projector frame's edge)
    img : (H * W, C) float32 output
    """
    _compose(index, A, B, off, frac, np.ascontiguousarray(table, np.float32).ravel(), other, img)


@numba.njit(**_NJIT)
def _gauss(seed, i):
    # Counter-based normal deviate: splitmix64 of (seed, i) gives four 16-bit uniforms whose sum
    # (Irwin-Hall) is Gaussian to within a few per cent inside +-3.4 sigma - ample for sensor noise,
    # and it needs no generator state, so every pixel's noise is fixed by (seed, index).
    z = (seed * np.uint64(0x9E3779B97F4A7C15)) ^ (i * np.uint64(0xBF58476D1CE4E5B9) + np.uint64(0x94D049BB133111EB))
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    m = np.uint64(0xFFFF)
    acc = float(z & m) + float((z >> np.uint64(16)) & m) + float((z >> np.uint64(32)) & m) + float(z >> np.uint64(48))
    return (acc + 2.0 - 2.0 * 65536.0) * (1.7320508075688772 / 65536.0)


@numba.njit(**_NJIT)
def _sensor(img, seed, full_well, read_noise, maxval, codes, noise, out):
    scale = 1.0 / full_well
    useed = np.uint64(seed)
    nl = codes.shape[0] - 1
    for i in range(img.shape[0]):
        e = img[i] * full_well
        if e < 0.0:
            e = 0.0
        if noise:
            # Shot noise (Poisson, Gaussian approximation) plus read noise, in electrons.
            e = e + math.sqrt(e + read_noise * read_noise) * _gauss(useed, np.uint64(i))
        x = e * scale
        if x < 0.0:
            x = 0.0
        elif x > 1.0:
            x = 1.0  # full well: the response curve sees a clipped signal
        if nl > 0:
            # The camera's response curve: the stored code of the nearest fine linear step.
            out[i] = codes[int(x * nl + 0.5)]
        else:
            out[i] = math.floor(x * maxval + 0.5)


def sensor_readout(img: np.ndarray, full_well: float, read_noise: float, bits: int, seed: int,
                   response_codes: np.ndarray | None = None, noise: bool = True) -> np.ndarray:
    """Expose an image: shot and read noise, full-well clipping, the camera's response, quantisation.

    Parameters
    ----------
    img : (...) float32, irradiance as a fraction of full scale (1.0 = full well)
    full_well : electrons at full scale
    read_noise : electrons RMS
    bits : 8 or 16
    seed : noise seed (deterministic)
    response_codes : (K,) uint16 stored value of each of K even steps of the linear signal over 0..1
        for these ``bits`` (:func:`shared.sim.response.response_codes`); None or empty: linear
    noise : add shot and read noise

    Returns
    -------
    (...) uint8 or uint16, same shape as ``img``
    """
    maxval = float((1 << bits) - 1)
    flat = np.ascontiguousarray(img, np.float32).ravel()
    out = np.empty(flat.shape[0], np.uint8 if bits == 8 else np.uint16)
    codes = np.zeros(0, np.uint16) if response_codes is None else np.ascontiguousarray(response_codes, np.uint16)
    _sensor(flat, int(seed) & 0x7FFFFFFFFFFFFFFF, float(full_well), float(read_noise), maxval, codes, bool(noise), out)
    return out.reshape(img.shape)


@numba.njit(**_NJIT)
def _shade_points(P, n, R, T, kp, dp, pw, ph, sm_depth, smk, power, blur0, aperture_px, zf, pix_scale,
                  vignetting, sid, ks_by_surface, shin_by_surface, sss_by_surface, u_out, v_out, lit_out, G_out,
                  sigma_out, spec_out):
    fx, fy, cx, cy, skew = kp[0], kp[1], kp[2], kp[3], kp[4]
    k1, k2, p1, p2, k3 = dp[0], dp[1], dp[2], dp[3], dp[4]
    # Projector centre in the camera frame: C = -R^T T.
    C0 = -(R[0, 0] * T[0] + R[1, 0] * T[1] + R[2, 0] * T[2])
    C1 = -(R[0, 1] * T[0] + R[1, 1] * T[1] + R[2, 1] * T[2])
    C2 = -(R[0, 2] * T[0] + R[1, 2] * T[1] + R[2, 2] * T[2])
    Hs, Ws = sm_depth.shape
    for i in range(P.shape[0]):
        x = P[i, 0]
        y = P[i, 1]
        z = P[i, 2]
        px = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + T[0]
        py = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + T[1]
        pz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + T[2]
        lx = C0 - x
        ly = C1 - y
        lz = C2 - z
        d = math.sqrt(lx * lx + ly * ly + lz * lz)
        lx /= d
        ly /= d
        lz /= d
        cos_p = n[i, 0] * lx + n[i, 1] * ly + n[i, 2] * lz
        if pz > 0.0:
            xn = px / pz
            yn = py / pz
            u, v = _to_pixel(xn, yn, fx, fy, cx, cy, skew, k1, k2, p1, p2, k3)
        else:
            u = np.nan
            v = np.nan
        u_out[i] = u
        v_out[i] = v
        lit = pz > 1.0 and cos_p > 0.0 and -0.5 <= u < pw - 0.5 and -0.5 <= v < ph - 0.5
        if lit:
            # Shadow map (already max-filtered over 2x2 texels): nearest surface along the ray.
            su = smk[0] * px / pz + smk[1]
            sv = smk[2] * py / pz + smk[3]
            iu = int(math.floor(su))
            iv = int(math.floor(sv))
            if iu < 0 or iv < 0 or iu >= Ws - 1 or iv >= Hs - 1:
                lit = False
            else:
                lit = pz <= sm_depth[iv, iu] * (1.0 + 2e-4) + 0.05
        lit_out[i] = lit
        zpc = max(pz, 1.0)
        coc = aperture_px * abs(pz - zf) / (zpc * zf)
        pix = pix_scale * max(z, 1.0) / zpc
        # Subsurface scattering spreads the pattern over sss mm of the surface: more blur, in
        # projector pixels at this distance.
        sss = sss_by_surface[sid[i]] * fx / zpc
        sigma_out[i] = math.sqrt(blur0 * blur0 + (coc / 4.0) ** 2 + pix * pix + sss * sss)
        if not lit:
            G_out[i] = 0.0
            spec_out[i] = 0.0
            continue
        # Inverse square from the projector centre, cos(theta) at the surface, the projector's
        # natural falloff towards its image corners (cos^3 of the off-axis angle) and its lens
        # vignetting 1 + k1 r^2 (r the undistorted normalised radius, the tangent of that angle).
        fall = min(max(pz / d, 0.0), 1.0)
        inv2 = (1000.0 / d) ** 2
        vig = max(1.0 + vignetting * ((px * px + py * py) / (pz * pz)), 0.0)
        G_out[i] = power * cos_p * inv2 * fall * fall * fall * vig
        ks = ks_by_surface[sid[i]]
        if ks > 0.0:
            # Phong lobe around the mirror direction of the projector's light, seen from the camera.
            rx = 2.0 * cos_p * n[i, 0] - lx
            ry = 2.0 * cos_p * n[i, 1] - ly
            rz = 2.0 * cos_p * n[i, 2] - lz
            vn = math.sqrt(x * x + y * y + z * z)
            rv = -(rx * x + ry * y + rz * z) / vn
            spec_out[i] = ks * power * inv2 * rv ** shin_by_surface[sid[i]] if rv > 0.0 else 0.0
        else:
            spec_out[i] = 0.0


def shade_points(P: np.ndarray, n: np.ndarray, R: np.ndarray, T: np.ndarray, Kp: np.ndarray, dist_p: np.ndarray,
                 proj_size: tuple[int, int], sm_depth: np.ndarray, sm_K: np.ndarray, power: float, blur0: float,
                 aperture_px: float, focus: float, pix_scale: float, sid: np.ndarray, ks_by_surface: np.ndarray,
                 shin_by_surface: np.ndarray, sss_by_surface: np.ndarray | None = None,
                 vignetting: float = 0.0) -> dict[str, np.ndarray]:
    """How the projector lights camera-frame points: the per-point terms of the image model.

    Parameters
    ----------
    P, n : (N, 3) float64 points (mm) and unit normals facing the camera
    R, T : rig extrinsics (X_projector = R X_camera + T); Kp, dist_p, proj_size: the projector
    sm_depth, sm_K : projector shadow map (2x2-max filtered depth) and its undistorted pinhole matrix
    power : white signal of an albedo-1 surface facing the projector at 1 m
    blur0, aperture_px, focus : pattern blur in focus (projector px), aperture x projector focal
        length (mm x px), focus distance (mm) - defocus blur grows as |z - focus| / (z focus)
    pix_scale : camera pixel footprint in projector pixels at equal depths (0.29 fx_p / fx_c)
    sid : (N,) int surface index; ks_by_surface, shin_by_surface : Phong coefficient and exponent per surface
    sss_by_surface : subsurface-scattering spread per surface (mm, Gaussian std), default none
    vignetting : k1 of the projector lens's vignetting ``1 + k1 r^2``, r the undistorted
        normalised radius ``|(x, y)| / z`` in the projector frame, on top of the natural cos^3 falloff

    Returns
    -------
    dict with ``u``, ``v`` (N,) float64 projector pixel coordinates (NaN behind the projector),
    ``lit`` (N,) bool, ``G`` (N,) float32 direct irradiance factor (0 unless lit): ``power * cos(theta)
    * (1000 / d)^2 * cos^3(off-axis) * (1 + vignetting * r^2)``, ``sigma`` (N,)
    float32 pattern blur (projector px), ``spec`` (N,) float32 specular factor (0 unless lit).
    """
    N = P.shape[0]
    out = {"u": np.empty(N), "v": np.empty(N), "lit": np.empty(N, np.bool_), "G": np.empty(N, np.float32),
           "sigma": np.empty(N, np.float32), "spec": np.empty(N, np.float32)}
    d = np.zeros(5)
    dd = np.asarray(dist_p, float).ravel()[:5]
    d[: dd.size] = dd
    kp = np.array([Kp[0, 0], Kp[1, 1], Kp[0, 2], Kp[1, 2], Kp[0, 1]], np.float64)
    smk = np.array([sm_K[0, 0], sm_K[0, 2], sm_K[1, 1], sm_K[1, 2]], np.float64)
    _shade_points(np.ascontiguousarray(P, np.float64), np.ascontiguousarray(n, np.float64),
                  np.ascontiguousarray(R, np.float64), np.asarray(T, np.float64).ravel(), kp, d,
                  float(proj_size[0]), float(proj_size[1]), sm_depth, smk, float(power), float(blur0),
                  float(aperture_px), float(focus), float(pix_scale), float(vignetting), np.asarray(sid, np.int64),
                  np.asarray(ks_by_surface, np.float64), np.asarray(shin_by_surface, np.float64),
                  np.zeros(len(ks_by_surface)) if sss_by_surface is None else np.asarray(sss_by_surface, np.float64),
                  out["u"], out["v"], out["lit"], out["G"], out["sigma"], out["spec"])
    return out
