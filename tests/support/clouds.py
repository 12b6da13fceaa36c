"""Synthetic single-view scans as cloud PLYs, for tests and the bench.

- :func:`synthetic_scan`: a camera at the origin ray-casts a wall, a floor and a sphere, one
  point a pixel, with ``size`` = Z / f like the scanner writes (the full cloud contract),
  built in bands of rows so a 15 M-point cloud costs little memory.
- :func:`scan_surface` / :func:`surface_points` / :func:`write_cloud`: a bumpy sphere cap seen
  by a pinhole camera at the origin (x right, y down, z forward, units mm) on the camera's
  pixel grid, written with any subset of the properties (``xyz`` only, no normals, no size,
  plus ``confidence`` and ``view``), for clouds "from elsewhere" and the exports.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from shared.formats.ply import CLOUD_DTYPE, write_ply_records

F_SCAN = 1400.0  # focal length (px) of the simulated scanner camera


def _scan_rows(width: int, height: int, v0: int, v1: int, rng: np.random.Generator) -> np.ndarray:
    """Ray-cast image rows [v0, v1) of the synthetic scene; returns CLOUD_DTYPE records."""
    f = F_SCAN * width / 3000.0
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(v0, v1, dtype=np.float64))
    u = u.ravel() + rng.uniform(-0.5, 0.5, u.size)
    v = v.ravel() + rng.uniform(-0.5, 0.5, v.size)
    d = np.stack([(u - width / 2) / f, (v - height / 2) / f, np.ones_like(u)], axis=1)
    t = np.full(u.size, 1500.0)  # wall at z = 1500 mm
    normal = np.tile([0.0, 0.0, -1.0], (u.size, 1))
    kind = np.zeros(u.size, np.int8)
    floor_t = np.where(d[:, 1] > 1e-9, 350.0 / np.maximum(d[:, 1], 1e-9), np.inf)  # floor y = 350
    hit = floor_t < t
    t[hit] = floor_t[hit]
    normal[hit] = [0.0, -1.0, 0.0]
    kind[hit] = 1
    c = np.array([80.0, 50.0, 1100.0])  # sphere
    r = 280.0
    b = d @ c
    dd = np.einsum("ij,ij->i", d, d)
    disc = b * b - dd * (c @ c - r * r)
    ts = np.where(disc > 0, (b - np.sqrt(np.maximum(disc, 0))) / dd, np.inf)
    hit = (ts > 0) & (ts < t)
    t[hit] = ts[hit]
    kind[hit] = 2
    xyz = d * t[:, None]
    normal[hit] = (xyz[hit] - c) / r
    rec = np.empty(u.size, CLOUD_DTYPE)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    checker = ((np.floor(xyz[:, 0] / 100) + np.floor(xyz[:, 1] / 100)) % 2).astype(np.float64)
    shade = np.clip(-normal[:, 2] * 0.7 + 0.3, 0, 1)
    col = np.empty((u.size, 3))
    col[:] = np.where(checker[:, None] > 0, [200, 190, 170], [90, 110, 160])
    col[kind == 1] = [120, 90, 60]
    col[kind == 2] = np.array([220, 60, 50]) * shade[kind == 2, None]
    rec["red"], rec["green"], rec["blue"] = col[:, 0], col[:, 1], col[:, 2]
    rec["nx"], rec["ny"], rec["nz"] = normal[:, 0], normal[:, 1], normal[:, 2]
    rec["size"] = xyz[:, 2] / f
    return rec


def synthetic_scan(path: Path, points: int, seed: int = 0) -> Path:
    """Write a synthetic single-view scan of about ``points`` points (4:3 image) as a cloud PLY,
    built in bands of rows so memory stays small. Returns ``path``."""
    width = max(4, int(round(math.sqrt(points * 4 / 3))))
    height = max(3, int(round(points / width)))
    rng = np.random.default_rng(seed)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {width * height}"]
    names = {"u1": "uchar", "<f4": "float"}
    for name in CLOUD_DTYPE.names or ():
        header.append(
            f"property {names[CLOUD_DTYPE[name].str if CLOUD_DTYPE[name].str != '|u1' else 'u1']} {name}"
        )
    header.append("end_header")
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        band = max(1, (1 << 20) // width)
        for v0 in range(0, height, band):
            f.write(_scan_rows(width, height, v0, min(height, v0 + band), rng).tobytes())
    tmp.replace(path)
    return path


#: Properties of a full Graylight cloud, plus the optional per-point extras of merged clouds.
ALL_FIELDS = ("xyz", "rgb", "normal", "size", "confidence", "view")


def surface_points(width: int = 160, height: int = 120, focal: float = 400.0, seed: int = 0) -> dict:
    """Arrays of a scanned surface: ``xyz`` (N, 3) float32 mm, ``rgb`` (N, 3) uint8, ``normal``
    (N, 3) float32 unit (towards the camera), ``size`` (N,) float32 = Z / f, ``confidence`` (N,)
    float32 in [0, 1], ``view`` (N,) uint8. A sphere of radius 80 mm centred 500 mm ahead."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.arange(width) - width / 2, np.arange(height) - height / 2)
    d = np.stack([u / focal, v / focal, np.ones_like(u)], axis=-1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = np.array([0.0, 0.0, 500.0])
    r = 80.0
    # Ray-sphere: |t d - c|^2 = r^2, nearest root.
    b = d @ c
    disc = b * b - (c @ c - r * r)
    hit = disc > 0
    t = b[hit] - np.sqrt(disc[hit])
    xyz = t[:, None] * d[hit]
    normal = (xyz - c) / r
    xyz += normal * 0.5 * np.sin(xyz[:, :1] / 7.0)  # small bumps, so the surface is not a sphere
    xyz = xyz.astype(np.float32)
    n = xyz.shape[0]
    return {
        "xyz": xyz,
        "rgb": rng.integers(0, 256, (n, 3), dtype=np.uint8),
        "normal": normal.astype(np.float32),
        "size": (xyz[:, 2] / focal).astype(np.float32),
        "confidence": rng.uniform(0, 1, n).astype(np.float32),
        "view": rng.integers(0, 3, n).astype(np.uint8),
    }


def write_cloud(path: Path, arrays: dict, fields: tuple[str, ...] = ("xyz", "rgb", "normal", "size")) -> Path:
    """Write the chosen ``fields`` of :func:`surface_points` arrays as a binary PLY."""
    spec = {
        "xyz": [("x", "<f4"), ("y", "<f4"), ("z", "<f4")],
        "rgb": [("red", "u1"), ("green", "u1"), ("blue", "u1")],
        "normal": [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")],
        "size": [("size", "<f4")],
        "confidence": [("confidence", "<f4")],
        "view": [("view", "u1")],
    }
    dtype = np.dtype([f for name in fields for f in spec[name]])
    n = arrays["xyz"].shape[0]
    rec = np.empty(n, dtype)
    for name in fields:
        cols = [f[0] for f in spec[name]]
        a = arrays[name]
        for k, col in enumerate(cols):
            rec[col] = a[:, k] if a.ndim == 2 else a
    return write_ply_records(path, iter([rec]), n, dtype, ("units mm", "frame camera"))


def scan_surface(path: Path, fields: tuple[str, ...] = ("xyz", "rgb", "normal", "size"), **kw) -> Path:
    """:func:`surface_points` written with ``fields`` to ``path``."""
    return write_cloud(path, surface_points(**kw), fields)
