"""Per-camera-pixel ground truth of a simulated capture: ``truth.npz`` (keys, units and meanings in
:mod:`shared.sim.simulate`'s docstring)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.core.errors import InputError

__all__ = ["TRUTH_FILE", "Truth", "load_truth", "truth_file"]

TRUTH_FILE = "truth.npz"


@dataclass
class Truth:
    """Per-camera-pixel ground truth (see the module docstring for meanings and units).

    ``labels``, ``albedo`` and ``irradiance`` are None only in truth files written before they existed.
    """

    depth: np.ndarray  # (H, W) float32
    points: np.ndarray  # (H, W, 3) float32
    normals: np.ndarray  # (H, W, 3) float32
    proj_col: np.ndarray  # (H, W) float32
    proj_row: np.ndarray  # (H, W) float32
    lit: np.ndarray  # (H, W) bool
    surface: np.ndarray  # (H, W) int16
    labels: np.ndarray | None = None  # (H, W) int8, LABEL_* codes of shared.sim.scenes
    albedo: np.ndarray | None = None  # (H, W, 3) float32 linear RGB, NaN where no surface
    irradiance: np.ndarray | None = None  # (H, W) float32 full-scale fractions per unit albedo
    response: str = "linear"  # the camera response the images went through (see camera_response)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write ``truth.npz`` (uncompressed: it is written fast and read with ``np.load``)."""
        p = Path(path)
        extra = {k: v for k, v in (("labels", self.labels), ("albedo", self.albedo),
                                   ("irradiance", self.irradiance)) if v is not None}
        np.savez(p, depth=self.depth, points=self.points, normals=self.normals, proj_col=self.proj_col,
                 proj_row=self.proj_row, lit=self.lit, surface=self.surface, response=np.array(self.response),
                 **extra)
        return p


_TRUTH_KEYS = ("depth", "points", "normals", "proj_col", "proj_row", "lit", "surface")


def truth_file(path: str | os.PathLike[str], what: str = "ground-truth file") -> Path:
    """The ``truth.npz`` at ``path`` or in the folder ``path``; :class:`InputError` naming it when missing."""
    p = Path(path)
    if p.is_dir():
        p = p / TRUTH_FILE
    if not p.is_file():
        raise InputError(p, f"{what} not found")
    return p


def load_truth(path: str | os.PathLike[str]) -> Truth:
    """Read a ``truth.npz`` (or the capture folder holding one)."""
    p = truth_file(path)
    with np.load(p) as z:
        missing = [k for k in _TRUTH_KEYS if k not in z.files]
        if missing:
            raise InputError(p, f"not a ground-truth file: no {', '.join(missing)}")
        extra = {k: z[k] for k in ("labels", "albedo", "irradiance") if k in z.files}
        response = str(z["response"]) if "response" in z.files else "linear"
        return Truth(**{k: z[k] for k in _TRUTH_KEYS}, **extra, response=response)
