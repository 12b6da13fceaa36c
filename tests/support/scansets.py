"""Scan sets for the multi-view tests and the bench.

- :func:`cached_scanset`: a simulated turntable/orbit scan set (:func:`shared.sim.scanset.simulate_scanset`)
  rendered once per cache folder (a file lock makes concurrent test workers wait for the first).
- :func:`dragon_scanset`: a ``scanset.json`` over the real Stanford dragon turntable scans (cloud
  views in metres), with or without the turntable angles; :func:`stanford_poses` reads Stanford's
  own registration (README convention ``X_world = R(q)^T X + t``) relative to view 0, in mm.
- :func:`plane_residuals`: how well two registered views fit each other (point-to-plane residuals),
  the figure the dragon test and the bench compare between sets of poses.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from shared.core.datapaths import shared_data_dir
from tests.support.links import place_file
from tests.support.locks import held

DRAGON = shared_data_dir() / "stanford-dragon-turntable"


def cached_scanset(root: Path, scene: str = "bunny", views: int = 8, mode: str = "turntable",
                   size: tuple[int, int] = (640, 480), projector: tuple[int, int] = (512, 384), seed: int = 0,
                   roi: bool = False) -> Path:
    """The folder of a simulated scan set under ``root`` (rendered on first use); ``roi`` writes the
    crop sphere (a real capture has none)."""
    from shared.sim.scanset import simulate_scanset

    key = json.dumps([scene, views, mode, list(size), list(projector), seed] + (["roi"] if roi else []))
    folder = root / f"scanset-{scene}-{mode}-{views}-{size[0]}x{size[1]}-{hashlib.sha1(key.encode()).hexdigest()[:8]}"
    root.mkdir(parents=True, exist_ok=True)
    with held(root / f"{folder.name}.lock"):
        if not (folder / "scanset.json").is_file():
            simulate_scanset(scene, folder, views=views, mode=mode, size=size, projector=projector, seed=seed,
                             overwrite=True, roi=roi)
    return folder


def _dragon_conf() -> list[list[str]]:
    lines = (DRAGON / "dragonStandRight.conf").read_text().splitlines()
    return [ln.split() for ln in lines if ln.startswith("bmesh")]


def dragon_scanset(folder: Path, turntable: bool) -> Path:
    """Write ``folder/scanset.json`` naming the 15 dragon scans (units m), angles from the file names.

    The scans are hard-linked (copied across filesystems) into ``folder``: a scan set's paths must
    lie inside its own folder, links leading out of it included."""
    conf = _dragon_conf()
    folder.mkdir(parents=True, exist_ok=True)
    for c in conf:
        place_file(DRAGON / c[1], folder / c[1])
    views = [{"cloud": c[1], "units": "m"} for c in conf]
    doc: dict = {"format": "graylight-scanset-v1", "views": views}
    if turntable:
        doc["turntable"] = {"angles_deg": [float(c[1].rsplit("_", 1)[1].split(".")[0]) for c in conf]}
    (folder / "scanset.json").write_text(json.dumps(doc))
    return folder


def stanford_poses() -> np.ndarray:
    """(15, 4, 4) Stanford's registration of the dragon scans relative to view 0, mm."""
    out = []
    for c in _dragon_conf():
        P = np.eye(4)
        P[:3, :3] = Rotation.from_quat(np.array(c[5:9], float)).as_matrix().T
        P[:3, 3] = np.array(c[2:5], float) * 1000.0
        out.append(P)
    P = np.stack(out)
    return np.linalg.inv(P[0]) @ P


def plane_residuals(views: list, trees: list, poses: np.ndarray, i: int, j: int) -> np.ndarray:
    """Point-to-plane residuals (mm, signed along view j's normals; negative: view i lies inside
    view j) of view i's points against their nearest points of view j within 1 mm whose normals
    agree (cosine > 0.7), under ``poses`` ((V, 4, 4), view to set frame). ``trees``: a
    ``scipy.spatial.cKDTree`` of each view's points."""
    rel = np.linalg.solve(poses[j], poses[i])
    x = views[i].xyz @ rel[:3, :3].T + rel[:3, 3]
    d, idx = trees[j].query(x, distance_upper_bound=1.0)
    ok = np.isfinite(d)
    m = views[j].normals[idx[ok]].astype(np.float64)
    agree = np.einsum("ij,ij->i", m, views[i].normals[ok].astype(np.float64) @ rel[:3, :3].T) > 0.7
    return np.einsum("ij,ij->i", m[agree], x[ok][agree] - views[j].xyz[idx[ok][agree]])


def merged_label_shares(merged_xyz: np.ndarray, fused_views: list, poses: np.ndarray,
                        labels: list[np.ndarray]) -> dict[str, float]:
    """Share of the merged points (M, 3) mm per simulator label (``shared.sim.scenes.LABELS``): each
    merged point takes the label of its nearest fused sample. ``fused_views``: the captured views
    the fusion took (pixels in their range images), ``poses`` (V, 4, 4) the poses the merge used,
    ``labels`` each view's (H, W) truth labels."""
    from scipy.spatial import cKDTree

    from shared.sim.scenes import LABELS

    xyz = np.concatenate([v.xyz @ P[:3, :3].T + P[:3, 3] for v, P in zip(fused_views, poses, strict=True)])
    lab = np.concatenate([lb[v.pixel[:, 1], v.pixel[:, 0]] for v, lb in zip(fused_views, labels, strict=True)])
    _, idx = cKDTree(xyz).query(merged_xyz, workers=2)
    counts = np.bincount(lab[idx].astype(np.int64) + 1, minlength=len(LABELS))
    return {LABELS[k - 1]: float(c) / max(1, len(merged_xyz)) for k, c in enumerate(counts)}
