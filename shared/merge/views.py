"""Views of a scan set as point clouds in their own sensor frame: the base type of the merge.

A :class:`ViewCloud` holds one view's points in mm in the view's sensor frame, row-aligned with
optional colours, unit normals (facing the sensor), sample sizes and a per-point confidence, plus
the view's range image and camera model when it was captured by our rig (they are the raw data
and the free-space test of the fusion needs them).

- Captured views (``graycode-v1``) are decoded and triangulated with the scanner's own stage
  functions (:mod:`shared.scan.pipeline`); the confidence is the decoder's contrast.
- Cloud views are read from PLY and scaled to mm by their ``units``; normals are estimated (when
  absent) from the 16 nearest neighbours and turned to the sensor, sizes are the mean distance to
  the 4 nearest neighbours, and the confidence is 1.

:func:`view_from_scan_outputs` rebuilds a captured view from the files the job service's
per-view stages write (``cloud.ply``, ``range.npz``, ``decoded.npz``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.core.threads import cpu_budget
from shared.formats.capture import load_capture
from shared.formats.ply import read_ply
from shared.formats.rig import load_rig
from shared.formats.scanset import Roi, ScanSet, ViewSpec
from shared.scan.albedo import linear_from_srgb
from shared.scan.decode import decode_capture, load_decoded
from shared.scan.pipeline import ingest_stage, view_albedo
from shared.scan.triangulate import triangulate

log = logging.getLogger(__name__)

__all__ = ["ViewCloud", "crop_to_roi", "estimate_normals", "load_view", "load_views", "view_from_scan_outputs"]


@dataclass
class ViewCloud:
    """One view's points in its own sensor frame, N of them, arrays row-aligned.

    xyz : (N, 3) float64 mm.
    normals : (N, 3) float32 unit normals facing the sensor.
    size : (N,) float32 world-space sample size in mm (``Z / f`` for captured views).
    confidence : (N,) float32 in [0, 1] (decoder contrast for captured views, 1 for clouds).
    rgb : (N, 3) uint8 or None.
    pixel : (N, 2) int32 camera pixel (x, y) of each point, or None for cloud views.
    range_image : (H, W) float32 Z in mm (NaN holes) or None.
    K, dist : the camera's (3, 3) intrinsics (pixels) and (5,) distortion, or None.
    albedo : (N, 3) float32 linear albedo from the projector's light (:mod:`shared.scan.albedo`),
        NaN where masked; None for cloud views and views whose albedo is not trusted.
    albedo_weight : (N,) float32 cosine to the projector (0 where masked), or None.
    """

    index: int
    name: str
    xyz: np.ndarray
    normals: np.ndarray
    size: np.ndarray
    confidence: np.ndarray
    rgb: np.ndarray | None = None
    pixel: np.ndarray | None = None
    range_image: np.ndarray | None = None
    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    albedo: np.ndarray | None = None
    albedo_weight: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def subset(self, keep: np.ndarray) -> ViewCloud:
        """The view with only the points selected by ``keep`` (bool mask or indices); images stay."""
        return ViewCloud(
            index=self.index, name=self.name, xyz=self.xyz[keep], normals=self.normals[keep], size=self.size[keep],
            confidence=self.confidence[keep], rgb=None if self.rgb is None else self.rgb[keep],
            pixel=None if self.pixel is None else self.pixel[keep], range_image=self.range_image, K=self.K,
            dist=self.dist, albedo=None if self.albedo is None else self.albedo[keep],
            albedo_weight=None if self.albedo_weight is None else self.albedo_weight[keep],
        )


def estimate_normals(xyz: np.ndarray, k: int = 16, sensor: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of a cloud by PCA of each point's ``k`` nearest neighbours, and the sample size.

    Normals are turned towards ``sensor`` ((3,) position); when None, towards the side the points
    were seen from: the one that puts the cloud's centroid behind the surface (a single range scan
    sees the near side of the object). Returns normals (N, 3) float32 and sizes (N,) float32, the
    mean distance to the 4 nearest neighbours.
    """
    xyz = np.asarray(xyz, np.float64)
    n = len(xyz)
    k = int(min(k, max(3, n - 1)))
    tree = cKDTree(xyz)
    dist, idx = tree.query(xyz, k=k + 1, workers=cpu_budget())
    nb = xyz[idx[:, 1:]]
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred)
    _, vecs = np.linalg.eigh(cov)
    normals = vecs[:, :, 0]
    if sensor is not None:
        flip = np.einsum("ij,ij->i", normals, np.asarray(sensor, float) - xyz) < 0
    else:
        # Face +Z first, then flip every normal if that puts the centroid in front of the surface.
        normals[normals[:, 2] < 0] *= -1
        if np.mean(np.einsum("ij,ij->i", normals, xyz - xyz.mean(axis=0))) < 0:
            normals *= -1
        flip = np.zeros(n, bool)
    normals[flip] *= -1
    size = dist[:, 1 : min(5, k + 1)].mean(axis=1)
    return normals.astype(np.float32), size.astype(np.float32)


def crop_to_roi(view: ViewCloud, roi: Roi | None) -> ViewCloud:
    """The view's points inside the scan set's region of interest (the view itself when all are)."""
    if roi is None:
        return view
    d = view.xyz - np.asarray(roi.center, np.float64)
    keep = np.einsum("ij,ij->i", d, d) <= float(roi.radius) ** 2
    return view if keep.all() else view.subset(keep)


def _cloud_view(spec: ViewSpec) -> ViewCloud:
    try:
        pc = read_ply(spec.path)
    except InputError as exc:
        raise InputError(spec.where, f"bad point cloud: {exc}") from None
    xyz = np.asarray(pc.xyz, np.float64) * spec.scale_mm
    finite = np.all(np.isfinite(xyz), axis=1)
    xyz = xyz[finite]
    if len(xyz) < 16:
        raise InputError(spec.where, f"point cloud {spec.path.name} holds {len(xyz)} finite points (need 16)")
    normals, size = estimate_normals(xyz)
    if pc.normals is not None:
        given = np.asarray(pc.normals, np.float32)[finite]
        length = np.linalg.norm(given, axis=1)
        ok = length > 0.5
        given[ok] /= length[ok, None]
        normals[ok] = given[ok]
    if pc.size is not None:
        # another scanner's sizes where they are sizes (NaN, zero or negative: the estimate stays,
        # as the fusion's grid is scaled by them)
        given_size = np.asarray(pc.size, np.float32)[finite] * np.float32(spec.scale_mm)
        ok = np.isfinite(given_size) & (given_size > 0)
        size[ok] = given_size[ok]
    rgb = None if pc.rgb is None else np.asarray(pc.rgb)[finite]
    return ViewCloud(index=spec.index, name=spec.name, xyz=xyz, normals=normals, size=size,
                     confidence=np.ones(len(xyz), np.float32), rgb=rgb)


def _from_arrays(spec: ViewSpec, xyz: np.ndarray, normals: np.ndarray, size: np.ndarray, rgb: np.ndarray,
                 pixel: np.ndarray, range_image: np.ndarray, confidence_image: np.ndarray, K: np.ndarray,
                 dist: np.ndarray, scale: float) -> ViewCloud:
    conf = confidence_image[pixel[:, 1], pixel[:, 0]].astype(np.float32)
    return ViewCloud(index=spec.index, name=spec.name, xyz=np.asarray(xyz, np.float64) * scale,
                     normals=np.asarray(normals, np.float32), size=np.asarray(size, np.float32) * np.float32(scale),
                     confidence=np.clip(conf, 0.0, 1.0), rgb=np.asarray(rgb, np.uint8), pixel=np.asarray(pixel, np.int32),
                     range_image=np.asarray(range_image, np.float32) * np.float32(scale),
                     K=np.asarray(K, np.float64), dist=np.asarray(dist, np.float64).ravel())


def _capture_view(spec: ViewSpec, progress: Callable[[float], None] | None) -> ViewCloud:
    try:
        capture = ingest_stage(spec.path, spec.rig)
        rig = load_rig(capture.rig) if capture.rig is not None else None
        if rig is None:
            raise InputError(spec.path, "no rig")
        decoded = decode_capture(capture, progress=progress)
        tri = triangulate(decoded, rig)
        albedo = view_albedo(capture, tri, rig, white=decoded.colour)
    except InputError as exc:
        raise InputError(spec.where, str(exc)) from None
    if len(tri) < 16:
        raise InputError(spec.where, f"the capture gave {len(tri)} points (need 16): nothing was lit or decoded")
    view = _from_arrays(spec, tri.xyz, tri.normals, tri.size, tri.rgb, tri.pixel, tri.range_image,
                        decoded.confidence, rig.camera.K, rig.camera.dist, spec.scale_mm)
    if albedo.trusted:
        view.albedo, view.albedo_weight = albedo.albedo, albedo.weight
    else:
        log.warning("view %s: %s", spec.name, albedo.stats.get("fallback"))
    return view


def view_from_scan_outputs(spec: ViewSpec, scan_dir: Path, decoded_dir: Path | None = None) -> ViewCloud:
    """A captured view rebuilt from the per-view stage outputs in ``scan_dir``.

    ``cloud.ply`` and ``range.npz`` come from :func:`shared.scan.pipeline.triangulate_stage`,
    ``decoded.npz`` from :func:`shared.scan.pipeline.decode_stage` (in ``decoded_dir`` when the
    decode is a stage of its own, else in ``scan_dir`` too). The points of ``cloud.ply`` are
    the range image's finite pixels in row-major order (the triangulator writes them so).
    """
    scan_dir = Path(scan_dir)
    try:
        pc = read_ply(scan_dir / "cloud.ply")
        rng_path = scan_dir / "range.npz"
        if not rng_path.is_file():
            raise InputError(rng_path, "range image not found")
        with np.load(rng_path) as z:
            range_image, K, dist = z["z"], z["K"], z["dist"]
        decoded = load_decoded(Path(decoded_dir or scan_dir) / "decoded.npz")
    except InputError as exc:
        raise InputError(spec.where, str(exc)) from None
    flat = np.flatnonzero(np.isfinite(range_image))
    if len(flat) != len(pc):
        raise InputError(spec.where, f"{scan_dir / 'cloud.ply'} holds {len(pc)} points but its range image {len(flat)}")
    w = range_image.shape[1]
    pixel = np.stack([flat % w, flat // w], axis=1).astype(np.int32)
    if pc.normals is None or pc.size is None or pc.rgb is None:
        raise InputError(spec.where, f"{scan_dir / 'cloud.ply'} lacks normals, size or colour")
    view = _from_arrays(spec, pc.xyz, pc.normals, pc.size, pc.rgb, pixel, range_image, decoded.confidence, K, dist,
                        spec.scale_mm)
    if pc.albedo is not None and pc.albedo_weight is not None:
        view.albedo = linear_from_srgb(pc.albedo.astype(np.float32) / 255.0)
        view.albedo_weight = pc.albedo_weight.astype(np.float32) / 255.0
        view.albedo[pc.albedo_weight == 0] = np.nan
    return view


def load_view(spec: ViewSpec, progress: Callable[[float], None] | None = None) -> ViewCloud:
    """Load one view: decode and triangulate a capture, or read a cloud; mm in the view's frame."""
    if spec.kind == "capture":
        load_capture(spec.path)  # a clear error before any pixel is read
        return _capture_view(spec, progress)
    return _cloud_view(spec)


def load_views(scanset: ScanSet, progress: Callable[[float], None] | None = None) -> list[ViewCloud]:
    """Every view of a scan set, in order. ``progress`` gets the fraction of views loaded.

    One view at a time: the decoder already reads its PNG frames on two threads and runs parallel
    kernels, and loading two views at once measured no faster (4 views at 2048x1536: 3.8-4.3 s
    wall and CPU either way, on a busy 2-core machine) while holding two views' frames.
    """
    out = []
    n = len(scanset.views)
    for k, spec in enumerate(scanset.views):
        sub = None if progress is None else (lambda f, k=k: progress((k + f) / n))
        out.append(load_view(spec, sub))
        log.info("view %s: %d points", spec.name, len(out[-1]))
    return out
