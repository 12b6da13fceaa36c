"""The whole multi-view merge of a scan set, in-process (``graylight merge``), and its stages.

In: a ``graylight-scanset-v1`` folder (:mod:`shared.formats.scanset`). Out, in an output folder:

- ``merged.ply``: the fused cloud (:data:`shared.merge.fusion.FUSED_DTYPE`, mm, view 0's frame);
- ``registration.json``: per view ``R``, ``T``, the fit's RMS in mm, overlap, inlier share; the
  method; the turntable axis; the loop-closure error;
- ``mesh.ply``, ``mesh.glb`` and ``mesh_lod1.glb`` ... (1/4, 1/16, 1/64 of the faces);
- ``ranges/<view>.npz``: each captured view's range image (``z`` in mm, ``K``, ``dist``): the raw data;
- ``report.json``: counts, per-stage seconds, the files.

Every file is written under a hidden staging folder inside the output folder and moved into place
only when all of them are complete, so an error leaves nothing half-written.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.files import write_json_atomic
from shared.formats.scanset import ScanSet, load_scanset
from shared.merge.checks import Checks, register_checked
from shared.merge.fusion import FusedCloud, FusionParams, fuse_views, write_fused
from shared.merge.isolate import IsolationParams, isolate_object
from shared.merge.meshing import MeshParams, reconstruct_mesh, simplify_lods, write_mesh
from shared.merge.registration import Registration, RegistrationParams, register_views
from shared.merge.views import ViewCloud, load_views

log = logging.getLogger(__name__)

__all__ = ["MERGED_FILE", "REGISTRATION_FILE", "REPORT_FILE", "hints_mm", "merge_scanset", "merge_views",
           "registration_views"]

MERGED_FILE = "merged.ply"
REGISTRATION_FILE = "registration.json"
REPORT_FILE = "report.json"


def hints_mm(scanset: ScanSet) -> list[np.ndarray | None]:
    """Each view's pose hint as a 4x4 matrix in mm (None where the view has none)."""
    out: list[np.ndarray | None] = []
    for v in scanset.views:
        if v.pose is None:
            out.append(None)
            continue
        P = np.eye(4)
        P[:3, :3] = v.pose[0]
        P[:3, 3] = v.pose[1] * v.scale_mm
        out.append(P)
    return out


def registration_views(views: Sequence[ViewCloud], params: RegistrationParams | None = None) -> list[ViewCloud]:
    """The views thinned on their pixel grid to what the registration's sampling uses.

    The registration keeps about ``fine_samples`` sources per view and dense targets
    ``target_density`` times finer in spacing, so about ``target_density**2 * fine_samples``
    targets; a captured view keeps every ``s``-th pixel in both directions, ``s`` the largest
    stride that leaves it 1.5 times that many points (a 2048x1536 view of about 750 000 points:
    every second pixel). Measured on the 12-view 2048x1536 turntable set against the truth: the
    worst view 0.0034 deg / 0.011 mm with angles and 0.0033 deg / 0.011 mm without, against
    0.0059 deg / 0.020 mm and 0.0058 deg / 0.020 mm from every pixel, in 5.7-6.0 s of CPU instead
    of 8.8-9.9 s (the samples' voxel grids sort a quarter of the points). Cloud views, views
    already that sparse and registrations with a fixed ``voxel`` are passed whole.
    """
    params = params or RegistrationParams()
    if params.voxel is not None:
        return list(views)
    need = 1.5 * params.target_density**2 * params.fine_samples
    out = []
    for v in views:
        stride = int(np.sqrt(len(v) / need)) if v.pixel is not None else 1
        if stride < 2:
            out.append(v)
            continue
        on_grid = (v.pixel[:, 0] % stride == 0) & (v.pixel[:, 1] % stride == 0)
        out.append(v.subset(on_grid))
        log.info("view %s: every %d-th pixel for the registration (%d of %d points)", v.name, stride,
                 int(on_grid.sum()), len(v))
    return out


def merge_views(
    views: Sequence[ViewCloud],
    scanset: ScanSet,
    out_dir: Path,
    *,
    drop_unregistered: bool = False,
    registration: RegistrationParams | None = None,
    fusion: FusionParams | None = None,
    meshing: MeshParams | None = None,
    isolation: IsolationParams | None = None,
    progress: Callable[[float], None] | None = None,
    timings: dict[str, float] | None = None,
    registered: Registration | None = None,
) -> dict[str, Any]:
    """Register, fuse and mesh loaded views (mm, own frames) and write every output of the merge.

    The stage after the per-view scans: the job service calls it with views rebuilt from the
    per-view stage outputs, :func:`merge_scanset` with views it decoded itself. ``registered``
    skips the registration with one already made of these views (reduced to the object as
    :func:`shared.merge.isolate.isolate_object` does); it is checked all the same. A registration
    that fails its checks (:mod:`shared.merge.checks`) raises an
    :class:`~shared.core.errors.InputError` naming the views before anything is written.
    """
    report_progress = progress or (lambda f: None)
    seconds = dict(timings or {})
    out_dir = Path(out_dir)
    names = [v.name for v in scanset.views]
    t0 = time.perf_counter()
    iso = isolate_object(views, scanset, isolation)
    t_iso = time.perf_counter()
    hints = hints_mm(scanset)
    thinned = registration_views(iso.registration, registration)

    def register(idx: list[int]) -> Registration:
        angles = None if scanset.turntable_deg is None else scanset.turntable_deg[idx]
        return register_views([thinned[i] for i in idx], hints=[hints[i] for i in idx], turntable_deg=angles,
                              params=registration, drop_unregistered=drop_unregistered, names=[names[i] for i in idx],
                              progress=lambda f: report_progress(0.55 * f), table_axis=iso.axis)

    reg, checks = register_checked(register, iso.registration, names,
                                   turntable=bool(iso.report["fixed_rig"] or scanset.turntable_deg is not None),
                                   angles_deg=scanset.turntable_deg, drop_unregistered=drop_unregistered,
                                   registered=registered)
    t_reg = time.perf_counter()
    kept = [i for i in range(len(views)) if i not in reg.dropped]
    fused = fuse_views([iso.fusion[i] for i in kept], reg.poses[kept], fusion)
    t_fuse = time.perf_counter()
    report_progress(0.65)
    mesh, mesh_stats = reconstruct_mesh(fused.xyz, fused.normals, fused.rgb, fused.size, meshing)
    t_mesh = time.perf_counter()
    report_progress(0.85)
    lods = simplify_lods(mesh, (meshing or MeshParams()).lods)
    t_lod = time.perf_counter()
    seconds.update({"isolate": round(t_iso - t0, 3), "register": round(t_reg - t_iso, 3), "fuse": round(t_fuse - t_reg, 3),
                    "mesh": round(t_mesh - t_fuse, 3), "lods": round(t_lod - t_mesh, 3)})
    out_dir.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".merge-staging-", dir=out_dir))
    try:
        quality = _quality(checks, iso.report, fused)
        files = _write_all(staging, out_dir, views, scanset, reg, fused, mesh, lods, quality)
        report = {
            "scanset": str(scanset.root), "views": len(views), "registered_views": len(kept),
            "dropped_views": [names[i] for i in reg.dropped], "method": reg.method,
            "points": {"samples": fused.stats["samples"], "merged": len(fused),
                       "per_view": {names[i]: len(views[i]) for i in range(len(views))}},
            "fusion": fused.stats, "mesh": {**mesh_stats, "lod_faces": [m.n_faces for m in lods]},
            "registration": {"worst_rms_mm": round(float(np.nanmax(reg.rms_mm[kept])), 5),
                             "loop_closure": reg.loop_closure,
                             "turntable_axis": None if reg.axis is None else reg.axis.to_json(),
                             "seconds": reg.seconds},
            "quality": quality,
            "seconds": {**seconds, "write": 0.0},
            "files": {k: str(out_dir / v) for k, v in files.items()},
        }
        t_w = time.perf_counter()
        report["seconds"]["write"] = round(t_w - t_lod, 3)
        report["seconds"]["total"] = round(sum(v for k, v in report["seconds"].items() if k != "total"), 3)
        report["files"]["report"] = str(out_dir / REPORT_FILE)
        write_json_atomic(staging / REPORT_FILE, report)
        _commit(staging, out_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    report_progress(1.0)
    log.info("merged %d views into %d points, %d faces", len(kept), len(fused), mesh.n_faces)
    return report


def _quality(checks: Checks, isolation: dict[str, Any], fused: FusedCloud) -> dict[str, Any]:
    """The ``quality`` block of ``report.json`` and ``registration.json``: the checks (per view RMS,
    overlap, inliers and flags; per pair residuals; loop closure; the turn) and what was removed
    before the registration (static, support and clutter samples; the object's sphere)."""
    return {**checks.doc, "removed": isolation, "fused_sizes_capped": fused.stats.get("sizes_capped", 0)}


def _write_all(staging: Path, out_dir: Path, views: Sequence[ViewCloud], scanset: ScanSet, reg: Registration,
               fused: FusedCloud, mesh: Any, lods: list[Any], quality: dict[str, Any]) -> dict[str, str]:
    names = [v.name for v in scanset.views]
    files = {"merged": MERGED_FILE, "registration": REGISTRATION_FILE, "mesh_ply": "mesh.ply", "mesh_glb": "mesh.glb"}
    write_fused(staging / MERGED_FILE, fused, comments=(f"graylight merge of {len(views)} views",))
    write_json_atomic(staging / REGISTRATION_FILE, {**reg.to_json(names), "quality": quality})
    write_mesh(staging / "mesh.ply", mesh)
    write_mesh(staging / "mesh.glb", mesh)
    for k, lod in enumerate(lods, start=1):
        name = f"mesh_lod{k}.glb"
        write_mesh(staging / name, lod)
        files[f"mesh_lod{k}"] = name
    ranges = [v for v in views if v.range_image is not None]
    if ranges:
        (staging / "ranges").mkdir()
        for v in ranges:
            np.savez(staging / "ranges" / f"{v.name}.npz", z=v.range_image, K=v.K, dist=v.dist, units=np.array("mm"))
        files["ranges"] = "ranges"
    return files


def _commit(staging: Path, out_dir: Path) -> None:
    """Move every staged file into ``out_dir`` (replacing older results), the report last."""
    entries = sorted(staging.iterdir(), key=lambda p: p.name == REPORT_FILE)
    for p in entries:
        dest = out_dir / p.name
        if p.is_dir():
            if dest.exists():
                shutil.rmtree(dest)
            os.replace(p, dest)
        else:
            os.chmod(p, 0o644)
            os.replace(p, dest)


def merge_scanset(
    scanset_dir: Path,
    out_dir: Path,
    *,
    drop_unregistered: bool = False,
    registration: RegistrationParams | None = None,
    fusion: FusionParams | None = None,
    meshing: MeshParams | None = None,
    isolation: IsolationParams | None = None,
    progress: Callable[[float], None] | None = None,
) -> dict[str, Any]:
    """Run the whole merge of a scan set in-process; returns the report written to ``report.json``.

    Parameters
    ----------
    scanset_dir : the scan set folder (or its ``scanset.json``).
    out_dir : output folder (see the module docstring for what it receives).
    drop_unregistered : leave out, with a warning, views that register to nothing (else an error).
    registration, fusion, meshing : parameters of the three algorithms.
    isolation : parameters of the static and support removal (``keep_support`` keeps the plate's disc).
    progress : called with the overall fraction done in [0, 1].
    """
    report_progress = progress or (lambda f: None)
    t0 = time.perf_counter()
    scanset = load_scanset(scanset_dir)
    views = load_views(scanset, progress=lambda f: report_progress(0.4 * f))
    t_load = time.perf_counter()
    return merge_views(views, scanset, Path(out_dir), drop_unregistered=drop_unregistered, registration=registration,
                       fusion=fusion, meshing=meshing, isolation=isolation,
                       progress=lambda f: report_progress(0.4 + 0.6 * f),
                       timings={"load_views": round(t_load - t0, 3)})
