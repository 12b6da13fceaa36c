"""The single-view scan pipeline as stage functions: ingest -> decode -> triangulate -> write.

In: a capture folder (``capture.json`` + images, contract ``graycode-v1``) and a ``rig.json``
(from the capture or given explicitly).
Out, in an output folder: ``cloud.ply`` (binary little-endian, see :mod:`shared.formats.ply`;
with the albedo of :mod:`shared.scan.albedo` beside the shaded colour when the capture's white
and black frames are at hand),
``range.npz`` (``z``: (H, W) float32 range image of Z in rig units, NaN holes; ``K`` and
``dist`` of the camera; ``units``) and ``report.json`` (counts, per-stage timings, decode and
triangulation statistics).

The job service runs :func:`ingest_stage`, :func:`decode_stage` and :func:`triangulate_stage`
as separate tasks; :func:`scan` runs the whole in-process (``graylight scan``). Every file is
written to a temporary name and renamed, so a failure never leaves a half-written file.
Bad input raises :class:`~shared.core.errors.InputError` naming the file and the problem.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError
from shared.core.files import atomic_file, write_json_atomic
from shared.core.threads import cpu_budget
from shared.formats.capture import Capture, load_capture
from shared.formats.images import probe_image, read_colour
from shared.formats.ply import write_ply
from shared.formats.rig import Rig, check_rig_matches, load_rig
from shared.scan.albedo import AlbedoParams, SampleAlbedo, estimate_albedo, params_for_rig, smooth_normals
from shared.scan.decode import Decoded, decode_capture, load_decoded, save_decoded
from shared.scan.triangulate import Triangulated, triangulate
from shared.scan.triangulate import load_kernels as load_triangulation_kernels

log = logging.getLogger(__name__)

CLOUD_FILE = "cloud.ply"
RANGE_FILE = "range.npz"
REPORT_FILE = "report.json"
DECODED_FILE = "decoded.npz"
TRIANGULATE_REPORT_FILE = "triangulate.json"


#: Smallest and largest camera image side a capture may have: below 16 pixels nothing can be
#: decoded or framed (a 1x1 capture would fail only at export), above 65536 no camera exists.
MIN_IMAGE_SIDE, MAX_IMAGE_SIDE = 16, 65536


def ingest_stage(capture_dir: Path, rig: Path | None = None) -> Capture:
    """Validate a capture completely without decoding pixels.

    Checks the ``capture.json`` contract, that every image exists and its header is readable,
    that all images share the white frame's size and bit depth, and (when a rig is given
    or named by the capture) that the rig parses and its device sizes match.

    Parameters
    ----------
    capture_dir : capture folder or its ``capture.json``.
    rig : ``rig.json`` overriding the capture's own ``rig`` field.

    Returns
    -------
    The :class:`Capture`, with ``rig`` set to the rig file that applies (or None).
    """
    capture = load_capture(capture_dir)
    white = probe_image(capture.white)
    if not (MIN_IMAGE_SIDE <= white.width <= MAX_IMAGE_SIDE and MIN_IMAGE_SIDE <= white.height <= MAX_IMAGE_SIDE):
        raise InputError(capture.white, f"image is {white.width}x{white.height}; a capture's images must be "
                                        f"{MIN_IMAGE_SIDE}..{MAX_IMAGE_SIDE} pixels a side")
    for path in capture.image_paths()[1:]:
        info = probe_image(path)
        if info.size != white.size:
            raise InputError(
                path,
                f"image is {info.width}x{info.height}, but the white frame {capture.white.name} is "
                f"{white.width}x{white.height} (mixed image sizes)",
            )
        if (info.bit_depth > 8) != (white.bit_depth > 8):
            raise InputError(
                path, f"image is {info.bit_depth}-bit, but the white frame {capture.white.name} is {white.bit_depth}-bit"
            )
    rig_path = Path(rig) if rig is not None else capture.rig
    if rig_path is not None:
        r = load_rig(rig_path)
        check_rig_matches(r, white.size, (capture.projector_width, capture.projector_height), rig_path)
        capture = replace(capture, rig=rig_path)
    return capture


def _require_rig(capture: Capture) -> Rig:
    if capture.rig is None:
        raise InputError(
            capture.root / "capture.json", 'no rig: name one in the "rig" field or pass --rig FILE'
        )
    return load_rig(capture.rig)


def decode_stage(capture_dir: Path, out_dir: Path, progress: Callable[[float], None] | None = None) -> dict[str, Any]:
    """Decode a capture and write ``out_dir/decoded.npz``; returns the decode statistics.
    ``progress`` is called with the fraction of images read, in [0, 1]."""
    capture = load_capture(capture_dir)
    decoded = decode_capture(capture, progress=progress)
    save_decoded(decoded, Path(out_dir) / DECODED_FILE)
    return decoded.stats


def _save_range_atomic(path: Path, tri: Triangulated, rig: Rig) -> None:
    # Uncompressed: zlib on a 15 MP float image costs seconds; consumers recompress as they need.
    with atomic_file(path, suffix=".tmp.npz") as tmp:
        np.savez(
            tmp,
            z=tri.range_image,
            K=np.asarray(rig.camera.K, np.float64),
            dist=np.asarray(rig.camera.dist, np.float64),
            units=np.array(rig.units),
        )


class _Staging:
    """Files written under hidden temporary names in ``out_dir`` and renamed together on commit,
    so a failure part-way leaves none of them (and a reader never sees a cloud without its report)."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.token = f".staging-{os.getpid()}-{time.monotonic_ns()}"
        self.names: list[str] = []

    def path(self, name: str) -> Path:
        self.names.append(name)
        return self.out_dir / f"{self.token}.{name}"

    def commit(self) -> None:
        for name in self.names:
            os.replace(self.out_dir / f"{self.token}.{name}", self.out_dir / name)

    def discard(self) -> None:
        for name in self.names:
            (self.out_dir / f"{self.token}.{name}").unlink(missing_ok=True)


def view_albedo(capture: Capture, tri: Triangulated, rig: Rig, white: np.ndarray | None = None,
                params: AlbedoParams | None = None) -> SampleAlbedo:
    """The albedo of a triangulated view from its capture's white and black frames.

    white : (H, W, 3) uint8 RGB white frame when already read (the decode's ``colour``).
    params : None: from the rig's ``radiometry`` (:func:`shared.scan.albedo.params_for_rig`).
    """
    params = params or params_for_rig(rig)
    size = (rig.camera.width, rig.camera.height)
    if white is None:
        white = read_colour(capture.white, size)
    black = read_colour(capture.black, size)
    flat = tri.flat_index
    normals = smooth_normals(tri.xyz, tri.pixel, tri.range_image.shape, params.normal_radius)
    bad = ~np.isfinite(normals).all(axis=1)
    normals[bad] = tri.normals[bad]
    return estimate_albedo(white.reshape(-1, 3)[flat], black.reshape(-1, 3)[flat], tri.xyz, normals, rig, params)


def _albedo_report(albedo: SampleAlbedo | None) -> dict[str, Any]:
    if albedo is None:
        return {"status": "absent", "reason": "no capture frames at hand"}
    return {"status": "measured" if albedo.trusted else "fallback", **albedo.stats}


def _write_outputs(out_dir: Path, tri: Triangulated, rig: Rig, staging: _Staging,
                   albedo: SampleAlbedo | None = None) -> dict[str, str]:
    out_dir.mkdir(parents=True, exist_ok=True)
    # A view whose albedo is not trusted (white frame saturated or dark nearly everywhere)
    # writes none: the renderers then use the shaded colour, and the report says why.
    enc, weight = albedo.encoded() if albedo is not None and albedo.trusted else (None, None)
    write_ply(
        staging.path(CLOUD_FILE),
        tri.xyz,
        rgb=tri.rgb,
        normals=tri.normals,
        size=tri.size,
        comments=("generated by graylight scan", f"units {rig.units}", "frame camera"),
        albedo=enc,
        albedo_weight=weight,
    )
    _save_range_atomic(staging.path(RANGE_FILE), tri, rig)
    return {"cloud": str(out_dir / CLOUD_FILE), "range": str(out_dir / RANGE_FILE)}


def _check_decoded_rig(decoded: Decoded, rig: Rig, where: Path) -> None:
    h, w = decoded.shape
    check_rig_matches(rig, (w, h), decoded.projector_size, where)


def triangulate_stage(decoded_npz: Path, rig_path: Path, out_dir: Path,
                      capture_dir: Path | None = None) -> dict[str, Any]:
    """Triangulate a saved decode; writes ``cloud.ply``, ``range.npz`` and ``triangulate.json``.

    ``capture_dir`` (the capture the decode came from): its white and black frames give the
    cloud its albedo (:mod:`shared.scan.albedo`); without it the cloud has the shaded colour only.
    Returns the triangulation part of the report (counts, timings, file paths).
    """
    t0 = time.perf_counter()
    decoded = load_decoded(decoded_npz)
    rig = load_rig(rig_path)
    _check_decoded_rig(decoded, rig, Path(rig_path))
    tri = triangulate(decoded, rig)
    albedo = None
    if capture_dir is not None:
        albedo = view_albedo(load_capture(capture_dir), tri, rig, white=decoded.colour)
    t1 = time.perf_counter()
    out_dir = Path(out_dir)
    staging = _Staging(out_dir)
    try:
        files = _write_outputs(out_dir, tri, rig, staging, albedo)
        part = {
            "points": len(tri),
            "units": rig.units,
            "triangulate": tri.stats,
            "albedo": _albedo_report(albedo),
            "files": {**files, "report": str(out_dir / TRIANGULATE_REPORT_FILE)},
            "seconds": {"triangulate": round(t1 - t0, 4), "write": round(time.perf_counter() - t1, 4)},
        }
        write_json_atomic(staging.path(TRIANGULATE_REPORT_FILE), part)
        staging.commit()
    except BaseException:
        staging.discard()
        raise
    return part


def scan(
    capture_dir: Path,
    out_dir: Path,
    rig: Path | None = None,
    progress: Callable[[float], None] | None = None,
) -> dict[str, Any]:
    """Run a whole single-view scan in-process.

    Parameters
    ----------
    capture_dir : capture folder (or its ``capture.json``).
    out_dir : output folder; receives ``cloud.ply``, ``range.npz`` and ``report.json``.
    rig : ``rig.json`` overriding the capture's ``rig`` field.
    progress : called with the overall fraction done in [0, 1].

    Returns
    -------
    The report written to ``report.json``.
    """
    out_dir = Path(out_dir)
    report_progress = progress or (lambda f: None)
    t0 = time.perf_counter()
    capture = ingest_stage(Path(capture_dir), rig)
    rig_model = _require_rig(capture)
    assert capture.rig is not None
    t_ingest = time.perf_counter()
    report_progress(0.02)
    # The rig's undistortion tables (about a second of CPU, OpenCV without the GIL, unless
    # cached) are made and the triangulation kernels loaded while the images are read and
    # decoded, on a core shared with the readers. (The decoder's kernels run on threads of
    # their own, not numba's parallel layer, which is the triangulation's alone: its workqueue
    # layer, if the user chose it, would abort on parallel launches from two threads at once.)
    with ThreadPoolExecutor(max_workers=1) as pool:
        tables = pool.submit(load_triangulation_kernels, rig_model)
        # One image-reading thread a core: PNG inflation releases the GIL.
        decoded = decode_capture(capture, progress=lambda f: report_progress(0.02 + 0.73 * f),
                                 threads=cpu_budget())
        t_decode = time.perf_counter()
        decode_stats = decoded.stats
        tri = triangulate(decoded, rig_model, tables=tables.result())
    t_tri = time.perf_counter()
    albedo = view_albedo(capture, tri, rig_model, white=decoded.colour)
    del decoded
    t_albedo = time.perf_counter()
    report_progress(0.9)
    staging = _Staging(out_dir)
    try:
        files = _write_outputs(out_dir, tri, rig_model, staging, albedo)
        t_write = time.perf_counter()
        report: dict[str, Any] = {
            "capture": str(capture.root),
            "rig": str(capture.rig),
            "units": rig_model.units,
            "camera_size": [rig_model.camera.width, rig_model.camera.height],
            "projector_size": [capture.projector_width, capture.projector_height],
            "points": len(tri),
            "lit_pixels": decode_stats["lit_pixels"],
            "points_share_of_lit": len(tri) / max(1, decode_stats["lit_pixels"]),
            "decode": decode_stats,
            "triangulate": tri.stats,
            "albedo": _albedo_report(albedo),
            "seconds": {
                "ingest": round(t_ingest - t0, 4),
                "decode": round(t_decode - t_ingest, 4),
                "triangulate": round(t_tri - t_decode, 4),
                "albedo": round(t_albedo - t_tri, 4),
                "write": round(t_write - t_albedo, 4),
                "total": round(t_write - t0, 4),
            },
            "files": {**files, "report": str(out_dir / REPORT_FILE)},
        }
        write_json_atomic(staging.path(REPORT_FILE), report)
        staging.commit()
    except BaseException:
        staging.discard()
        raise
    report_progress(1.0)
    log.info("scan of %s: %d points in %.2f s", capture.root, len(tri), t_write - t0)
    return report
