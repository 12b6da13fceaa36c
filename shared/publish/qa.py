"""The quality report of a published object (``qa.json``): the evidence that the model is right.

Sections (each ``null`` with a ``note`` when the source has nothing for it):

- ``calibration``: the rig's calibration session (reprojection RMS per device and per pose, the
  board's squares measured with the rig) when ``graylight calibrate`` made it;
- ``views``: per view its points, the share of its range image with a depth, its decode
  statistics (a scan), its fit (a merge: RMS, overlap, inlier share);
- ``pairs``: per registered pair its residual RMS, overlap and inlier share; the loop closure; the
  merge's quality flags (its ``quality`` block, when it wrote one);
- ``noise``: the cloud's noise: RMS distance of points from the plane of their 16 neighbours (mm),
  median and 90th percentile over a sample;
- ``coverage``: how many views saw each part of the model (counts of mesh vertices, or points, by
  the number of views with a sample within ``radius_mm``) and the share of the mesh bridged
  without data (vertices farther than ``radius_mm`` from every sample: Poisson's fill-in);
- ``derivatives``: each level's size against Voyager's budgets;
- ``verdict``: ``publishable`` and the reasons when not.

Thresholds are parameters with physical meaning (:class:`QaThresholds`).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError
from shared.core.jsonsafe import read_json_bounded
from shared.publish.calibration import calibration_report_for
from shared.publish.glb import GlbInfo
from shared.publish.source import Source

log = logging.getLogger(__name__)

__all__ = ["BUDGETS", "QaThresholds", "build_qa", "coverage_counts", "noise_estimate", "rig_path_of"]

#: Voyager's guidance per quality: largest GLB bytes (Thumb), faces, texture side (px).
BUDGETS: dict[str, dict[str, int | None]] = {
    "Thumb": {"bytes": 200_000, "faces": 20_000, "image": 512},
    "Low": {"bytes": None, "faces": 150_000, "image": 1024},
    "Medium": {"bytes": None, "faces": 150_000, "image": 2048},
    "High": {"bytes": None, "faces": 150_000, "image": 4096},
    "Highest": {"bytes": None, "faces": 500_000, "image": 8192},
}


@dataclass(frozen=True)
class QaThresholds:
    """What makes an object publishable. ``max_reprojection_px``: calibration RMS per device;
    ``max_fit_rms_mm``: a view's registration RMS; ``max_loop_deg`` / ``max_loop_mm``: loop closure;
    ``max_bridged_share``: share of mesh vertices without a sample near; ``coverage_radius_factor``:
    the radius (in median point spacings) within which a view's sample counts as seeing a place."""

    max_reprojection_px: float = 1.0
    max_fit_rms_mm: float = 1.0
    max_loop_deg: float = 1.0
    max_loop_mm: float = 2.0
    max_bridged_share: float = 0.25
    coverage_radius_factor: float = 3.0


def rig_path_of(source: Source) -> Path | None:
    """The rig file the source was made with: the scan's, or the scan set's shared one."""
    if source.kind == "scan":
        rig = source.report.get("rig")
        return Path(rig) if isinstance(rig, str) and Path(rig).is_file() else None
    scanset = source.report.get("scanset")
    if not isinstance(scanset, str) or not (Path(scanset) / "scanset.json").is_file():
        return None
    try:
        doc = read_json_bounded(Path(scanset) / "scanset.json", "scanset.json", missing="not found")
    except InputError:
        return None
    rig = doc.get("rig") if isinstance(doc, dict) else None
    path = Path(scanset) / rig if isinstance(rig, str) else None
    return path if path is not None and path.is_file() else None


def _calibration(source: Source, th: QaThresholds, rig: Path | None) -> tuple[dict[str, Any] | None, list[str]]:
    rig = rig or rig_path_of(source)
    if rig is None:
        return {"note": "the rig file is not where the source says: no calibration evidence"}, []
    report = calibration_report_for(rig)
    if report is None:
        return {"rig": str(rig), "note": "the rig was not made by graylight calibrate here (no session report "
                                          "beside it): no reprojection errors to show"}, []
    why = [f"calibration reprojection RMS of the {dev} {v:.2f} px > {th.max_reprojection_px:g} px"
           for dev, v in report.rms_px.items() if dev in ("camera", "projector") and v > th.max_reprojection_px]
    poses = [{"name": p.get("name"), "used": bool(p.get("used")), "reason": p.get("reason"),
              "camera_rms_px": p.get("camera_rms_px"), "projector_rms_px": p.get("projector_rms_px")}
             for p in report.poses]
    return {"rig": str(rig), **report.summary(), "per_pose": poses,
            "board_per_pose": report.board_check.get("poses", [])}, why


def _load_cloud(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    from shared.formats.ply import read_ply

    cloud = read_ply(path)
    return np.asarray(cloud.xyz, np.float64), None if cloud.rgb is None else np.asarray(cloud.rgb)


def noise_estimate(xyz: np.ndarray, sample: int = 5000, k: int = 16, seed: int = 0) -> dict[str, Any]:
    """RMS distance of points from the plane of their ``k`` nearest neighbours (mm), over a sample of
    ``sample`` points of ``xyz`` (N, 3): median, 90th percentile, and the median spacing to the nearest
    neighbour. On a smooth surface this is the measurement noise (curvature adds to it at edges)."""
    from scipy.spatial import cKDTree

    if len(xyz) < k + 1:
        return {"points": int(len(xyz)), "note": "too few points for a noise estimate"}
    tree = cKDTree(xyz)
    idx = np.random.default_rng(seed).choice(len(xyz), size=min(sample, len(xyz)), replace=False)
    dist, nb = tree.query(xyz[idx], k=k + 1)
    patches = xyz[nb]  # (S, k+1, 3)
    centred = patches - patches.mean(axis=1, keepdims=True)
    cov = np.einsum("sni,snj->sij", centred, centred) / (k + 1)
    smallest = np.linalg.eigvalsh(cov)[:, 0]
    rms = np.sqrt(np.clip(smallest, 0, None) * (k + 1) / max(k - 2, 1))  # unbiased for a 3-parameter plane
    return {"points": int(len(xyz)), "sample": int(len(idx)), "neighbours": k,
            "median_mm": float(np.median(rms)), "p90_mm": float(np.percentile(rms, 90)),
            "spacing_mm": float(np.median(dist[:, 1]))}


def _view_samples(source: Source) -> list[np.ndarray]:
    """Each registered view's samples in the model's frame (mm): range images back-projected through
    their lens (``ranges/<view>.npz``) and moved by the registration; for a scan its cloud."""
    import cv2

    if source.kind == "scan":
        return [_load_cloud(source.cloud)[0]]
    out = []
    for v in source.registration.get("views", []):
        path = source.root / "ranges" / f"{v.get('name')}.npz"
        if not v.get("registered", True) or not path.is_file() or "R" not in v:
            continue
        with np.load(path) as d:
            z, K, dist = d["z"].astype(np.float64), d["K"], d["dist"]
        vv, uu = np.nonzero(np.isfinite(z) & (z > 0))
        if not len(vv):
            continue
        pix = np.stack([uu, vv], axis=1).astype(np.float64).reshape(-1, 1, 2)
        norm = cv2.undistortPoints(pix, K, dist).reshape(-1, 2)
        zz = z[vv, uu]
        X = np.column_stack([norm * zz[:, None], zz])
        out.append(X @ np.asarray(v["R"], np.float64).T + np.asarray(v["T"], np.float64))
    return out


def coverage_counts(targets: np.ndarray, views: list[np.ndarray], radius: float) -> np.ndarray:
    """For each target point (N, 3) mm, how many views have a sample within ``radius`` mm: (N,) int."""
    from scipy.spatial import cKDTree

    counts = np.zeros(len(targets), np.int32)
    for pts in views:
        d, _ = cKDTree(pts).query(targets, k=1, distance_upper_bound=radius)
        counts += np.isfinite(d)
    return counts


def _derivatives(levels: dict[str, GlbInfo]) -> tuple[list[dict[str, Any]], list[str]]:
    rows, over = [], []
    for q, info in levels.items():
        b = BUDGETS.get(q, {})
        problems = []
        if b.get("bytes") and info.byte_size > b["bytes"]:
            problems.append(f"{info.byte_size} bytes > {b['bytes']}")
        if b.get("faces") and info.faces > b["faces"]:
            problems.append(f"{info.faces} faces > {b['faces']}")
        if b.get("image") and info.image_size > b["image"]:
            problems.append(f"texture {info.image_size} px > {b['image']}")
        rows.append({"quality": q, "file": info.path.name, "bytes": info.byte_size, "faces": info.faces,
                     "points": info.points, "image_size": info.image_size, "budget": b, "within_budget": not problems,
                     "problems": problems})
        over += [f"{q} derivative over budget ({'; '.join(problems)})"] if problems else []
    return rows, over


def _derivative_set(source: Source) -> dict[str, Any]:
    """How the published levels were made: ``graylight derivatives`` (textured, from its report), the
    merge's own untextured levels, or a single view's cloud."""
    rep = source.derivatives
    if rep is None:
        made = "textured derivatives" if any(p.name.startswith("mesh_") and "lod" not in p.name and p.name != "mesh.glb"
                                             for p in source.levels.values()) else (
            "the merge's own levels (untextured)" if source.levels else "the cloud as points")
        return {"made_by": made}
    master = rep.get("master") if isinstance(rep.get("master"), dict) else {}
    return {"made_by": "graylight derivatives", "colour": rep.get("colour_baked"),
            "master_faces": master.get("faces"), "bridged_vertex_share": master.get("bridged_vertex_share"),
            "seconds": rep.get("seconds"),
            "levels": [{k: lv.get(k) for k in ("level", "file", "faces", "texture_px", "bytes")}
                       for lv in rep.get("levels", []) if isinstance(lv, dict)]}


def _flags(quality: dict[str, Any] | None) -> tuple[list[dict[str, Any]], list[str]]:
    """The merge's quality checks, whatever their shape: a ``flags`` list, or named blocks with ``ok``."""
    if not quality:
        return [], []
    rows: list[dict[str, Any]] = []
    for name, val in quality.items():
        if isinstance(val, dict) and "ok" in val:
            rows.append({"check": name, "ok": bool(val["ok"]),
                         "detail": {k: v for k, v in val.items() if k != "ok" and not isinstance(v, dict | list)}})
    for flag in quality.get("flags", []) if isinstance(quality.get("flags"), list) else []:
        rows.append({"check": str(flag.get("name", flag)) if isinstance(flag, dict) else str(flag), "ok": False,
                     "detail": flag if isinstance(flag, dict) else {}})
    # The turntable merge's block (shared.merge.checks): passed, the loop's closes, per-view flags, failures.
    loop = quality.get("loop_closure")
    if isinstance(loop, dict) and isinstance(loop.get("closes"), bool):
        rows.append({"check": "loop closure", "ok": loop["closes"],
                     "detail": {k: v for k, v in loop.items() if isinstance(v, int | float) and not isinstance(v, bool)}})
    for v in quality.get("views", []) if isinstance(quality.get("views"), list) else []:
        for flag in v.get("flags", []) if isinstance(v, dict) and isinstance(v.get("flags"), list) else []:
            rows.append({"check": f"{v.get('name', v.get('view'))}: {flag}", "ok": False, "detail": {}})
    for failure in quality.get("failures", []) if isinstance(quality.get("failures"), list) else []:
        rows.append({"check": str(failure), "ok": False, "detail": {}})
    for key in ("ok", "passed"):
        if isinstance(quality.get(key), bool):
            rows.append({"check": "overall", "ok": quality[key], "detail": {}})
    return rows, [f"registration check failed: {r['check']}" for r in rows if not r["ok"]]


def build_qa(source: Source, levels: dict[str, GlbInfo], model_points: np.ndarray, mesh_vertices: np.ndarray | None,
             meta: dict[str, str], th: QaThresholds | None = None,
             rig: Path | None = None) -> tuple[dict[str, Any], np.ndarray]:
    """The quality report (see the module's docstring) and the coverage count of each target
    ((M,) int: views within the radius of each mesh vertex, or of each cloud point without a mesh).
    ``model_points`` (N, 3) mm: the cloud; ``mesh_vertices`` (M, 3) mm of the highest mesh level, or None;
    ``rig``: the rig file when the source's records do not say where it is now (a job's stages)."""
    th = th or QaThresholds()
    why: list[str] = []
    calib, w = _calibration(source, th, rig)
    why += w
    views: list[dict[str, Any]] = []
    pairs: list[dict[str, Any]] = []
    loop = None
    if source.kind == "scan":
        r = source.report
        dec = r.get("decode", {}) if isinstance(r.get("decode"), dict) else {}
        views.append({"name": Path(str(r.get("capture", "view"))).name, "points": r.get("points"),
                      "lit_pixels": r.get("lit_pixels"), "points_share_of_lit": r.get("points_share_of_lit"),
                      "decoded_share_of_lit": dec.get("column_decoded_share_of_lit"),
                      "camera_size": r.get("camera_size"), "registered": True})
    else:
        reg = source.registration
        per_view = (source.report.get("points") or {}).get("per_view", {})
        for v in reg.get("views", []):
            row = {k: v.get(k) for k in ("name", "registered", "rms_mm", "overlap", "inlier_share")}
            row["points"] = per_view.get(v.get("name"))
            rng = source.root / "ranges" / f"{v.get('name')}.npz"
            if rng.is_file():
                with np.load(rng) as d:
                    z = d["z"]
                    row["range_valid_share"] = float(np.mean(np.isfinite(z) & (z > 0)))
            views.append(row)
            if not v.get("registered", True):
                why.append(f"view {v.get('name')} not registered")
            elif isinstance(v.get("rms_mm"), int | float) and v["rms_mm"] > th.max_fit_rms_mm:
                why.append(f"view {v.get('name')} fits with RMS {v['rms_mm']:.2f} mm > {th.max_fit_rms_mm:g} mm")
        pairs = [dict(e) for e in reg.get("edges", []) if isinstance(e, dict)]
        loop = reg.get("loop_closure")
        if isinstance(loop, dict):
            deg, mm = loop.get("chained_pairwise_deg"), loop.get("chained_pairwise_mm")
            if isinstance(deg, int | float) and deg > th.max_loop_deg:
                why.append(f"loop closure {deg:.2f} deg > {th.max_loop_deg:g} deg")
            if isinstance(mm, int | float) and mm > th.max_loop_mm:
                why.append(f"loop closure {mm:.2f} mm > {th.max_loop_mm:g} mm")
        for name in source.report.get("dropped_views", []) or []:
            why.append(f"view {name} left out (registered to nothing)")
    flags, w = _flags(source.quality)
    why += w
    noise = noise_estimate(model_points)
    spacing = noise.get("spacing_mm") or 1.0
    radius = th.coverage_radius_factor * spacing
    samples = _view_samples(source)
    targets = mesh_vertices if mesh_vertices is not None and len(mesh_vertices) else model_points
    counts = coverage_counts(targets, samples, radius) if samples else np.zeros(len(targets), np.int32)
    hist = np.bincount(counts, minlength=len(samples) + 1)
    bridged = float(hist[0] / max(len(targets), 1)) if mesh_vertices is not None else None
    coverage = {"of": "mesh vertices" if mesh_vertices is not None else "cloud points", "radius_mm": radius,
                "views": len(samples), "seen_by": {str(i): int(n) for i, n in enumerate(hist)},
                "bridged_share": bridged}
    if bridged is not None and bridged > th.max_bridged_share:
        why.append(f"{100 * bridged:.0f} % of the mesh is bridged without data (> {100 * th.max_bridged_share:.0f} %)")
    deriv, w = _derivatives(levels)
    why += w
    if not levels:
        why.append("no model to publish")
    doc = {
        "format": "graylight-qa-v1",
        "object": {**meta, "kind": source.kind, "source": str(source.root)},
        "thresholds": asdict(th),
        "calibration": calib,
        "views": views,
        "pairs": pairs,
        "loop_closure": loop,
        "method": source.report.get("method") if source.kind == "merge" else "single view",
        "turntable_axis": (source.registration or {}).get("turntable_axis"),
        "quality_flags": flags,
        "noise": noise,
        "coverage": coverage,
        "derivatives": deriv,
        "derivative_set": _derivative_set(source),
        "notes": list(source.notes),
        "verdict": {"publishable": not why, "reasons": why,
                    "line": "publishable" if not why else "not publishable: " + "; ".join(why)},
    }
    return doc, counts
