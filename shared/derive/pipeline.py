"""The derivative set of a merged model (``graylight derivatives``).

In: a merge's output folder (``mesh.ply``, the master; ``merged.ply``, the fused cloud whose
albedo or shaded colour is baked; :mod:`shared.merge.pipeline`). Out, in ``out_dir``: per level
``mesh_<level>.glb`` (textured, Draco, :mod:`shared.derive.gltf`) and ``mesh_<level>_bridged.png``
(the texels where the master bridged a gap without data), and ``derivatives.json`` (per level the
faces, bytes, budget, bake figures and seconds; the colour used and any fallback). ``mesh.glb``
stays the master. Every file is written under a staging folder and moved into place when all are
done: a failure leaves none of them.

Colour: ``photo`` (default) the albedo from the views' photographs at their resolution
(:mod:`shared.derive.photo`; measured per texel against the simulator's truth on 8-view 480x360
turntable sets, 1024 px level of 20 k faces, mean absolute error of linear albedo up to one scale:
bunny 0.101 against 0.118 for the cloud's albedo and 0.185 for the per-vertex white-frame colour,
spot 0.097 / 0.123 / 0.216), the cloud's albedo where no view sees a texel, and the cloud's albedo
throughout, with a warning, when the scan set's photographs are not at hand; ``albedo`` the fused
cloud's albedo where the cloud carries it, else the shaded colour, with a warning in the report; ``shaded`` always the white-frame colour. Without a ``merged.ply`` the master's
vertex colours are the source (a warning again).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.core.files import write_json_atomic
from shared.core.threads import cpu_budget
from shared.derive.bake import BakeParams, ColourSource, bake_maps, unwrap, vertex_normals
from shared.derive.gltf import encode_jpeg, write_textured_glb
from shared.derive.levels import Level, parse_levels
from shared.derive.photo import PhotoSource, load_photo_source
from shared.formats.ply import read_ply

log = logging.getLogger(__name__)

__all__ = ["REPORT_FILE", "load_bridged", "load_master", "make_derivatives", "simplify_to"]

REPORT_FILE = "derivatives.json"
COLOUR_MODES = ("photo", "albedo", "shaded")


def load_master(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The master mesh: vertices (V, 3) float64 mm, faces (F, 3) int64, vertex colours (V, 3) uint8 or None."""
    import trimesh

    if not path.is_file():
        raise InputError(path, "master mesh not found (run graylight merge first)")
    try:
        tm = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds for a bad file
        raise InputError(path, f"not a readable mesh ({type(exc).__name__})") from None
    v = np.asarray(tm.vertices, np.float64)
    f = np.asarray(tm.faces, np.int64)
    if len(f) == 0 or not np.isfinite(v).all():
        raise InputError(path, "the mesh has no faces or non-finite vertices")
    colours = None
    if getattr(tm.visual, "kind", None) == "vertex":
        colours = np.asarray(tm.visual.vertex_colors)[:, :3].astype(np.uint8)
    return v, f, colours


def load_bridged(path: Path, vertices: int) -> np.ndarray | None:
    """The master's per-vertex ``bridged`` flag (V,) bool from ``mesh.ply``
    (:mod:`shared.merge.meshing`), or None when the file has none (older merges)."""
    from shared.formats.ply import read_header

    try:
        header = read_header(path)
    except (InputError, ValueError):
        return None
    if "bridged" not in (header.dtype.names or ()):
        return None
    import trimesh

    raw = trimesh.load(path, force="mesh", process=False).metadata.get("_ply_raw", {})
    flag = np.asarray(raw.get("vertex", {}).get("data", {})["bridged"]).astype(bool)
    return flag if len(flag) == vertices else None


def simplify_to(vertices: np.ndarray, faces: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation to about ``target`` faces (fast-simplification); the mesh itself when it
    already has no more."""
    import fast_simplification

    if target >= len(faces):
        return vertices, faces
    v, f = fast_simplification.simplify(np.asarray(vertices, np.float64), np.asarray(faces, np.int32),
                                        target_count=int(target))
    if len(f) == 0:
        raise InputError("mesh", f"simplification to {target} faces left nothing")
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


def _colour_source(merge_dir: Path, colour: str, master: tuple[np.ndarray, np.ndarray, np.ndarray | None],
                   warnings: list[str]) -> ColourSource:
    cloud_path = merge_dir / "merged.ply"
    if cloud_path.is_file():
        pc = read_ply(cloud_path)
        if pc.rgb is None or pc.normals is None or pc.size is None:
            raise InputError(cloud_path, "the cloud lacks colour, normals or size")
        rgb = pc.rgb.copy()
        kind = "shaded"
        if colour == "albedo":
            if pc.albedo is None or pc.albedo_weight is None:
                warnings.append("no albedo in merged.ply (cloud views, or views whose white frame could not give "
                                "it): the shaded colour is baked")
            else:
                has = pc.albedo_weight > 0
                rgb[has] = pc.albedo[has]
                kind = "albedo" if has.all() else "mixed"
                if not has.all():
                    warnings.append(f"{100 * (1 - has.mean()):.1f} % of the cloud has no albedo: the shaded colour "
                                    "stands in there")
        return ColourSource(np.asarray(pc.xyz, np.float64), rgb, pc.normals, pc.size, kind)
    v, f, c = master
    warnings.append("no merged.ply beside the master: its vertex colours are baked")
    n = vertex_normals(v, f)
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1)
    rgb = c if c is not None else np.full((len(v), 3), 200, np.uint8)
    return ColourSource(v, rgb, n, np.full(len(v), float(np.median(edge)), np.float32), "mesh")


def _level(level: Level, v: np.ndarray, f: np.ndarray, colours: ColourSource, master_v: np.ndarray,
           master_n: np.ndarray, staging: Path, params: BakeParams, colour_mode: str,
           photo: PhotoSource | None = None, master_bridged: np.ndarray | None = None) -> dict[str, Any]:
    t0 = time.perf_counter()
    lv, lf = simplify_to(v, f, level.faces)
    t1 = time.perf_counter()
    uvm = unwrap(lv, lf, level.texture_px, params.padding_px)
    t2 = time.perf_counter()
    maps = bake_maps(uvm, level.texture_px, colours, master_v, master_n, params, photo=photo,
                     master_bridged=master_bridged)
    t3 = time.perf_counter()
    q = level.jpeg_quality
    textures = {"base_colour": encode_jpeg(maps.base_colour, q), "normal": encode_jpeg(maps.normal, max(q, 80)),
                "occlusion": encode_jpeg(maps.occlusion, q)}
    extras = {"units": "mm", "level": level.name, "faces_budget": level.faces, "texture_px": level.texture_px,
              "colour": maps.stats["colour"], "colour_mode": colour_mode,
              "bridged_share": maps.stats["bridged_share"], "bridged_mask": f"mesh_{level.name}_bridged.png"}
    glb = write_textured_glb(staging / level.file_name, uvm.vertices, uvm.faces, uvm.uv, uvm.normals, textures, extras)
    ok, png = cv2.imencode(".png", maps.bridged)
    (staging / f"mesh_{level.name}_bridged.png").write_bytes(png.tobytes())
    t4 = time.perf_counter()
    return {
        "level": level.name, "file": level.file_name, "faces": int(len(lf)), "faces_budget": level.faces,
        "vertices_after_unwrap": int(len(uvm.vertices)), "texture_px": level.texture_px, "bytes": glb["bytes"],
        "max_bytes": level.max_bytes, "within_max_bytes": None if level.max_bytes is None else glb["bytes"] <= level.max_bytes,
        "geometry_bytes": glb["geometry_bytes"], "texture_bytes": glb["texture_bytes"], "bake": maps.stats,
        "seconds": {"simplify": round(t1 - t0, 3), "unwrap": round(t2 - t1, 3), "bake": round(t3 - t2, 3),
                    "encode": round(t4 - t3, 3), "total": round(t4 - t0, 3)},
    }


def make_derivatives(merge_dir: Path, out_dir: Path | None = None, levels: str | list | None = None,
                     colour: str = "photo", params: BakeParams | None = None,
                     measure_memory: bool = False, scanset: Path | None = None) -> dict[str, Any]:
    """Make the derivative set of a merge (see the module docstring); returns the report.

    levels : a spec for :func:`shared.derive.levels.parse_levels` (None: Thumb, Low, Medium, High).
    colour : ``photo``, ``albedo`` or ``shaded``. scanset : the scan set whose photographs ``photo``
    bakes (None: the one the merge's report names). measure_memory : also report tracemalloc's peak (slower).
    """
    merge_dir = Path(merge_dir)
    out_dir = Path(out_dir) if out_dir is not None else merge_dir
    if colour not in COLOUR_MODES:
        raise InputError("colour", f"must be one of {', '.join(COLOUR_MODES)}, got {colour!r}")
    plan = parse_levels(levels)
    params = params or BakeParams()
    t0 = time.perf_counter()
    if measure_memory:
        tracemalloc.start()
    master = load_master(merge_dir / "mesh.ply")
    mv, mf, _ = master
    warnings: list[str] = []
    photo = None
    if colour == "photo":
        photo, why = load_photo_source(merge_dir, scanset)
        if photo is None:
            warnings.append(f"no photographs to bake from ({why}): the cloud's albedo is baked")
    source = _colour_source(merge_dir, "shaded" if colour == "shaded" else "albedo", master, warnings)
    for w in warnings:
        log.warning("derivatives: %s", w)
    mn = vertex_normals(mv, mf)
    flag = load_bridged(merge_dir / "mesh.ply", len(mv))
    out_dir.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".derivatives-", dir=out_dir))
    try:
        # Each level from the master, largest first (a coarser level from a finer one would be
        # faster, but each level's own quadric error is measured against the master this way).
        results = [_level(lv, mv, mf, source, mv, mn, staging, params, colour, photo, flag) for lv in plan]
        # The master's own vertices where no sample is near: surface Poisson bridged without data.
        d, nb = cKDTree(source.xyz).query(mv, workers=cpu_budget())
        bridged = d > params.bridge_factor * np.maximum(source.size[nb], 1e-6)
        if flag is not None:
            bridged |= flag  # the merge's own flag, measured against every sample
        report: dict[str, Any] = {
            "master": {"faces": int(len(mf)), "vertices": int(len(mv)),
                       "bridged_vertex_share": round(float(bridged.mean()), 5),
                       "bridged_flag": "mesh.ply" if flag is not None else "from the cloud"},
            "colour": colour, "colour_baked": "photo" if photo is not None else source.kind, "warnings": warnings, "levels": results,
            "seconds": round(time.perf_counter() - t0, 3),
        }
        if measure_memory:
            report["peak_traced_bytes"] = int(tracemalloc.get_traced_memory()[1])
        write_json_atomic(staging / REPORT_FILE, report)
        for p in sorted(staging.iterdir()):
            os.replace(p, out_dir / p.name)
    finally:
        if measure_memory:
            tracemalloc.stop()
        shutil.rmtree(staging, ignore_errors=True)
    return report
