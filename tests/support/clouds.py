"""Synthetic single-view scans as cloud PLYs, with any subset of the cloud contract's properties.

:func:`scan_surface` samples a bumpy sphere cap seen by a pinhole camera at the origin (x right,
y down, z forward, units mm) on the camera's pixel grid, as Graylight's scanner does: every
sample carries its colour, a unit normal facing the camera and the world sample size Z / f.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.formats.ply import write_ply_records

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
