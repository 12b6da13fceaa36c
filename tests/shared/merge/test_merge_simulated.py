"""The multi-view merge against the virtual rig's truth: poses, turntable axis, coverage, accuracy, mesh.

The scan set is 8 turntable views of the bunny at 640x480 (the issue's figures are for 2048x1536,
which costs minutes per run: the bench measures those). At 640x480 the fits have 3.2x fewer samples
across the object, so the pose tolerances here are 0.05 deg / 0.15 mm with and without angles
(the issue's 2048x1536 figures: 0.02 deg / 0.05 mm with angles, 0.05 deg / 0.1 mm without).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.formats.ply import write_ply
from shared.formats.scanset import load_scanset, scanset_doc, write_scanset
from shared.merge.fusion import read_fused
from shared.merge.pipeline import merge_views
from shared.merge.registration import pose_error, register_views
from shared.merge.views import crop_to_roi, load_views
from shared.sim.scanset import load_scanset_truth, turntable_scenes
from shared.sim.simulate import load_truth
from tests.support.scansets import cached_scanset

pytestmark = pytest.mark.slow

SET = {"scene": "bunny", "views": 8, "mode": "turntable", "size": (640, 480), "projector": (512, 384)}


@pytest.fixture(scope="module")
def scanset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return cached_scanset(tmp_path_factory.mktemp("merge-sim"), **SET)


@pytest.fixture(scope="module")
def loaded(scanset_dir: Path):
    ss = load_scanset(scanset_dir)
    views = load_views(ss)
    truth = load_scanset_truth(scanset_dir)
    obj = []
    for spec in ss.views:
        t = load_truth(spec.path)
        m = (t.surface == 0) & np.isfinite(t.depth)
        obj.append(t.points[m].astype(np.float64))
    return ss, views, truth, obj


def _check_poses(reg, truth, obj, max_deg: float, max_mm: float) -> None:
    errs = [pose_error(reg.poses[i], truth.poses[i], obj[i]) for i in range(len(obj))]
    for i, (deg, mm) in enumerate(errs):
        print(f"view {i}: {deg:.4f} deg, {mm:.4f} mm (fit RMS {reg.rms_mm[i]:.3f} mm, overlap {reg.overlap[i]:.2f})")
    assert max(e[0] for e in errs) <= max_deg
    assert max(e[1] for e in errs) <= max_mm


def test_turntable_angles_register_within_tolerance(loaded) -> None:
    ss, views, truth, obj = loaded
    cropped = [crop_to_roi(v, ss.roi) for v in views]
    reg = register_views(cropped, turntable_deg=ss.turntable_deg)
    _check_poses(reg, truth, obj, 0.05, 0.15)
    axis_err = np.degrees(np.arccos(min(1.0, abs(float(np.dot(reg.axis.direction, truth.axis_direction))))))
    print(f"turntable axis {axis_err:.4f} deg from the truth; loop closure {reg.loop_closure}")
    assert axis_err <= 0.1
    assert reg.loop_closure is not None and reg.loop_closure["order"] == list(range(8))
    # The estimated angles are the table's, with the sign the registration found.
    ang = np.abs(reg.axis.angles_deg)
    np.testing.assert_allclose(np.minimum(ang, 360 - ang), np.minimum(ss.turntable_deg, 360 - ss.turntable_deg),
                               atol=0.05)


def test_no_hints_register_within_tolerance(loaded) -> None:
    ss, views, truth, obj = loaded
    cropped = [crop_to_roi(v, ss.roi) for v in views]
    reg = register_views(cropped)
    assert reg.method.startswith("global FPFH+RANSAC")
    _check_poses(reg, truth, obj, 0.05, 0.15)


def _true_surface(ss) -> trimesh.Trimesh:
    scenes, *_ = turntable_scenes(SET["scene"], SET["views"], SET["mode"], seed=0)
    parts = [s.placed for s in scenes[0].surfaces[:2]]  # object and turntable plate, view 0's frame
    return trimesh.util.concatenate([trimesh.Trimesh(p.vertices, p.faces, process=False) for p in parts])


def _dist_to(mesh: trimesh.Trimesh, pts: np.ndarray, n: int = 20000, seed: int = 0) -> np.ndarray:
    """Exact point-to-triangle distances (Open3D's raycasting scene) of up to ``n`` of the points."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    pick = pts[rng.choice(len(pts), size=min(n, len(pts)), replace=False)]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32))
    return scene.compute_distance(o3d.core.Tensor(pick.astype(np.float32))).numpy().astype(np.float64)


def test_merge_covers_fuses_and_meshes(loaded, tmp_path: Path) -> None:
    ss, views, truth, obj = loaded
    out = tmp_path / "out"
    report = merge_views(views, ss, out)
    for name in ("merged.ply", "registration.json", "mesh.ply", "mesh.glb", "mesh_lod1.glb", "mesh_lod2.glb",
                 "mesh_lod3.glb", "report.json"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "ranges").iterdir()) == [f"view_{i:02d}.npz" for i in range(8)]
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
    reg_doc = json.loads((out / "registration.json").read_text())
    poses = np.stack([np.block([[np.array(v["R"]), np.array(v["T"])[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
                      for v in reg_doc["views"]])
    rec = read_fused(out / "merged.ply")
    merged = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    assert set(np.unique(rec["view"])) == set(range(8))
    assert np.all(rec["confidence"] > 0)
    # Coverage of the object's surface that any view saw (true points in the set frame, truth poses).
    seen = np.concatenate([o @ P[:3, :3].T + P[:3, 3] for o, P in zip(obj, truth.poses, strict=True)])
    tree = cKDTree(merged)
    reach = 3.0 * float(np.median(rec["size"]))
    covered = np.isfinite(tree.query(seen, distance_upper_bound=reach)[0]).mean()
    single = max(np.isfinite(cKDTree(v.xyz @ P[:3, :3].T + P[:3, 3]).query(seen, distance_upper_bound=reach)[0]).mean()
                 for v, P in zip(views, poses, strict=True))
    print(f"coverage of the seen object surface: merged {100 * covered:.1f} %, best single view {100 * single:.1f} %")
    assert covered >= 0.95 and covered > single + 0.2
    # Point-to-surface error: merged (estimated poses) against the best single view (own frame).
    surface = _true_surface(ss)
    rms_merged = float(np.sqrt(np.mean(_dist_to(surface, merged) ** 2)))
    singles = []
    for v, P in zip(views, truth.poses, strict=True):
        c = crop_to_roi(v, ss.roi)
        singles.append(float(np.sqrt(np.mean(_dist_to(surface, c.xyz @ P[:3, :3].T + P[:3, 3]) ** 2))))
    print(f"RMS point-to-surface: merged {rms_merged:.3f} mm, single views {[round(s, 3) for s in singles]}")
    assert rms_merged <= min(singles)
    # Mesh: two-sided Hausdorff 95th percentile within 3x the merged cloud's RMS.
    mesh = trimesh.load(out / "mesh.ply", process=False)
    glb = trimesh.load(out / "mesh.glb", force="mesh", process=False)
    assert len(glb.faces) == len(mesh.faces) and glb.visual.kind == "vertex"
    d_mesh_to_true = _dist_to(surface, np.asarray(mesh.vertices))
    seen_obj = seen[np.isfinite(tree.query(seen, distance_upper_bound=reach)[0])]
    d_true_to_mesh = _dist_to(mesh, seen_obj)
    h95 = max(np.percentile(d_mesh_to_true, 95), np.percentile(d_true_to_mesh, 95))
    print(f"mesh Hausdorff 95th percentile {h95:.3f} mm (3x merged RMS = {3 * rms_merged:.3f} mm)")
    assert h95 <= 3 * rms_merged
    faces = [len(trimesh.load(out / f"mesh_lod{k}.glb", force="mesh", process=False).faces) for k in (1, 2, 3)]
    full = len(mesh.faces)
    for k, f in enumerate(faces, start=1):
        assert abs(f / full - 4.0**-k) < 0.25 * 4.0**-k, (k, f, full)
    assert report["registered_views"] == 8 and report["mesh"]["faces"] == full


def test_view_that_overlaps_nothing(loaded, scanset_dir: Path, tmp_path: Path) -> None:
    ss, views, truth, obj = loaded
    rng = np.random.default_rng(3)
    junk = rng.normal(size=(3000, 3)) * [40.0, 40.0, 2.0] + [0.0, 0.0, 900.0]  # a noisy disc of nothing
    write_ply(tmp_path / "junk.ply", junk.astype(np.float32))
    for name in ("view_00", "view_01"):  # a scan set's paths lie inside its folder
        shutil.copytree(scanset_dir / name, tmp_path / name)
    shutil.copyfile(scanset_dir / "rig.json", tmp_path / "rig.json")
    doc = scanset_doc([{"capture": "view_00"}, {"capture": "view_01"}, {"cloud": "junk.ply", "name": "junk"}],
                      rig="rig.json", roi=ss.roi)
    write_scanset(tmp_path, doc)
    ss2 = load_scanset(tmp_path)
    three = [views[0], views[1]]
    from shared.merge.views import load_view

    three.append(load_view(ss2.views[2]))
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"^views\[2\] \(junk\): overlaps no other view") as exc:
        merge_views(three, ss2, out)
    assert "\n" not in str(exc.value)
    assert not out.exists() or not any(out.iterdir())
    report = merge_views(three, ss2, out, drop_unregistered=True)
    assert report["dropped_views"] == ["junk"] and report["registered_views"] == 2
    assert json.loads((out / "registration.json").read_text())["views"][2]["registered"] is False
