"""The multi-view merge against the virtual rig's truth: poses, turntable axis, coverage, accuracy, mesh.

Every test runs as a real turntable capture looks: no ``roi`` (the scan set's crop is removed), so
the backdrop, the floor and the plate are in every view and the merge must find the object itself
(the issue's reproduction: before the static removal every view registered at about 0 deg, on the wall).

The scan set is 8 turntable views of the bunny at 640x480 (the issue's figures are for 2048x1536,
which costs minutes per run: the bench measures those). At 640x480 the fits have 3.2x fewer samples
across the object, so the pose tolerances here are 0.05 deg / 0.15 mm with and without angles
(the issue's 2048x1536 figures: 0.02 deg / 0.05 mm with angles, 0.05 deg / 0.1 mm without).
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.formats.ply import write_ply
from shared.formats.scanset import load_scanset, scanset_doc, write_scanset
from shared.merge.checks import check_registration, register_checked
from shared.merge.consistency import FREE_SPACE_SHARE, free_space_pairs, free_space_shares, repair_slips
from shared.merge.fusion import read_fused
from shared.merge.geometry import _about_axis
from shared.merge.isolate import IsolationParams, isolate_object
from shared.merge.meshing import MeshParams
from shared.merge.pipeline import merge_views
from shared.merge.registration import Registration, pose_error, register_views
from shared.merge.views import load_views
from shared.sim.scanset import load_scanset_truth, turntable_scenes
from shared.sim.scenes import LABEL_OBJECT, LABEL_PLATE, LABEL_SUPPORT
from shared.sim.simulate import load_truth
from tests.support.scansets import cached_scanset, merged_label_shares

# One group: the module's scan set and its loaded views (decoded and triangulated) are made on one
# xdist worker, not once a worker.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("merge_simulated")]

SET = {"scene": "bunny", "views": 8, "mode": "turntable", "size": (640, 480), "projector": (512, 384)}


@pytest.fixture(scope="module")
def scanset_dir(scanset_factory: Callable[..., Path]) -> Path:
    return scanset_factory(**SET)


@pytest.fixture(scope="module")
def loaded(scanset_dir: Path):
    ss = dataclasses.replace(load_scanset(scanset_dir), roi=None)  # what a real turntable capture looks like
    views = load_views(ss)
    truth = load_scanset_truth(scanset_dir)
    obj = []
    for spec in ss.views:
        t = load_truth(spec.path)
        m = (t.labels == LABEL_OBJECT) & np.isfinite(t.depth)
        obj.append(t.points[m].astype(np.float64))
    return ss, views, truth, obj


@pytest.fixture(scope="module")
def labels(loaded) -> list[np.ndarray]:
    """Each view's (H, W) simulator labels (object, plate, support, base, backdrop)."""
    return [load_truth(spec.path).labels for spec in loaded[0].views]


def _check_poses(reg, truth, obj, max_deg: float, max_mm: float) -> None:
    errs = [pose_error(reg.poses[i], truth.poses[i], obj[i]) for i in range(len(obj))]
    for i, (deg, mm) in enumerate(errs):
        print(f"view {i}: {deg:.4f} deg, {mm:.4f} mm (fit RMS {reg.rms_mm[i]:.3f} mm, overlap {reg.overlap[i]:.2f})")
    assert max(e[0] for e in errs) <= max_deg
    assert max(e[1] for e in errs) <= max_mm


def _check_poses_of(poses, truth, obj, max_deg: float, max_mm: float) -> None:
    errs = [pose_error(poses[i], truth.poses[i], obj[i]) for i in range(len(obj))]
    print("pose errors (deg, mm):", [(round(d, 4), round(m, 4)) for d, m in errs])
    assert max(e[0] for e in errs) <= max_deg and max(e[1] for e in errs) <= max_mm


@pytest.fixture(scope="module")
def isolated_given_angles(loaded):
    """The object isolated from the views of the set as it is (its turntable angles given), made once
    for the tests that read it."""
    ss, views, *_ = loaded
    return isolate_object(views, ss)


def test_turntable_angles_register_within_tolerance(loaded, isolated_given_angles) -> None:
    ss, views, truth, obj = loaded
    reg = register_views(isolated_given_angles.registration, turntable_deg=ss.turntable_deg)
    _check_poses(reg, truth, obj, 0.05, 0.15)
    axis_err = np.degrees(np.arccos(min(1.0, abs(float(np.dot(reg.axis.direction, truth.axis_direction))))))
    print(f"turntable axis {axis_err:.4f} deg from the truth; loop closure {reg.loop_closure}")
    assert axis_err <= 0.1
    assert reg.loop_closure is not None and reg.loop_closure["order"] == list(range(8))
    # The estimated angles are the table's, with the sign the registration found.
    ang = np.abs(reg.axis.angles_deg)
    np.testing.assert_allclose(np.minimum(ang, 360 - ang), np.minimum(ss.turntable_deg, 360 - ss.turntable_deg),
                               atol=0.05)


def test_no_hints_register_within_tolerance(loaded, isolated) -> None:
    ss, views, truth, obj = loaded
    reg = register_views(isolated.registration)  # isolated without the turntable angles
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


def test_merge_covers_fuses_and_meshes(loaded, labels, isolated_given_angles, tmp_path: Path) -> None:
    ss, views, truth, obj = loaded
    out = tmp_path / "out"
    report = merge_views(views, dataclasses.replace(ss, turntable_deg=None), out)  # no roi, no hints
    for name in ("merged.ply", "registration.json", "mesh.ply", "mesh.glb", "mesh_lod1.glb", "mesh_lod2.glb",
                 "mesh_lod3.glb", "report.json"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "ranges").iterdir()) == [f"view_{i:02d}.npz" for i in range(8)]
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
    poses = json_poses(out)
    rec = read_fused(out / "merged.ply")
    merged = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    # The right model: every view where it belongs, and almost nothing but the object in the cloud.
    _check_poses_of(poses, truth, obj, 0.05, 0.15)
    # What is object and what is static, by the simulator's per-pixel labels.
    shares = merged_label_shares(merged, isolated_given_angles.fusion, poses, labels)
    off_object = shares["plate"] + shares["support"] + shares["base"] + shares["backdrop"]
    quality = report["quality"]
    print(f"merged points by label: {({k: round(100 * v, 3) for k, v in shares.items()})} %; removed "
          f"{quality['removed']['static']} static samples, object sphere {quality['removed']['object']}")
    assert off_object <= 0.005 and shares["object"] >= 0.99
    assert quality["passed"] and quality["removed"]["object"]["source"] == "found"
    assert quality["removed"]["static"] > 0.5 * quality["removed"]["samples"]
    assert [v["flags"] for v in quality["views"]] == [[]] * 8 and quality["loop_closure"]["closes"]
    free = quality["free_space"]
    print(f"free space: worst view {free['worst_view']} {100 * free['worst_share']:.3f} % (bound "
          f"{100 * free['bound_share']:.2f} %)")
    assert free["views_tested"] == 8 and free["worst_share"] <= free["bound_share"]
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
    for v, P in zip(isolated_given_angles.registration, truth.poses, strict=True):
        c = v
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
                      rig="rig.json", roi=turntable_scenes(SET["scene"], SET["views"], SET["mode"])[4])
    # the simulator's crop: two captures and a cloud are not one fixed rig, so only a crop leaves
    # the captures the object alone
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


def _scanset_of(tmp_path: Path, captures: list[tuple[str, Path]], rig: Path, angles=None):
    """A scan set of the given captures: hard-linked into its folder, since a scan set names only
    paths inside it (the confinement rule)."""
    for n, p in captures:
        shutil.copytree(p, tmp_path / n)
    shutil.copyfile(rig, tmp_path / "rig.json")
    doc = scanset_doc([{"capture": n, "name": n} for n, _p in captures], rig="rig.json", turntable_deg=angles)
    write_scanset(tmp_path, doc)
    return load_scanset(tmp_path)


def test_all_backdrop_fails_saying_so(loaded, scanset_dir: Path, tmp_path: Path) -> None:
    ss, views, truth, obj = loaded
    empty = []
    for spec, v in zip(ss.views, views, strict=True):
        label = load_truth(spec.path).labels
        backdrop = label >= LABEL_SUPPORT  # table, base and backdrop: what a turntable with nothing on it shows
        keep = backdrop[v.pixel[:, 1], v.pixel[:, 0]]
        e = v.subset(keep)
        e.range_image = np.where(backdrop, v.range_image, np.nan).astype(np.float32)
        empty.append(e)
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"^views: every view shows only geometry that does not turn .* all backdrop"):
        merge_views(empty, ss, out)
    assert not out.exists() or not any(out.iterdir())


def test_identical_views_are_named(loaded, tmp_path: Path) -> None:
    ss, views, truth, obj = loaded
    twice = list(views)
    twice[1] = dataclasses.replace(views[0], index=1, name="view_01")
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"^views\[0\] \(view_00\), views\[1\] \(view_01\): identical") as exc:
        merge_views(twice, ss, out)
    assert "\n" not in str(exc.value)
    assert not out.exists() or not any(out.iterdir())


def test_wrong_turntable_angle_is_named(loaded, tmp_path: Path) -> None:
    ss, views, truth, obj = loaded
    angles = ss.turntable_deg.copy()
    angles[3] += 25.0  # one view's angle off by an offset
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"view_03") as exc:
        merge_views(views, dataclasses.replace(ss, turntable_deg=angles), out)
    print(exc.value)
    assert "angle" in str(exc.value) and "\n" not in str(exc.value)
    assert not out.exists() or not any(out.iterdir())


def test_view_of_another_object_is_named_not_merged(loaded, scanset_dir: Path, tmp_path: Path) -> None:
    ss, views, truth, obj = loaded
    other_set = cached_scanset(tmp_path / "other", scene="teapot", views=2, mode="turntable", size=SET["size"],
                               projector=SET["projector"])
    captures = [(spec.name, spec.path) for spec in ss.views] + [("teapot", other_set / "view_01")]
    ss9 = _scanset_of(tmp_path / "set", captures, scanset_dir / "rig.json")
    from shared.merge.views import load_view

    nine = [*views, load_view(ss9.views[8])]
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"views\[8\] \(teapot\)[,:]") as exc:
        merge_views(nine, ss9, out)
    print(exc.value)
    assert "overlaps no other view" in str(exc.value) and "\n" not in str(exc.value)
    assert not str(exc.value).startswith(tuple(f"views[{i}]" for i in range(8)))  # the bunny's views are not named
    assert not out.exists() or not any(out.iterdir())
    # --drop-unregistered leaves out exactly the foreign view; the other eight pass every check (before
    # the foreign view's backdrop was kept out of the object's search, views 2 and 3 failed too and
    # four of the eight were left out).
    report = merge_views(nine, ss9, out, drop_unregistered=True, meshing=MeshParams(max_depth=6))  # the mesh: elsewhere
    assert report["dropped_views"] == ["teapot"] and report["registered_views"] == 8
    quality = report["quality"]
    assert quality["passed"] and [v["flags"] for v in quality["views"][:8]] == [[]] * 8
    assert quality["removed"]["foreign_background"] == ["teapot"]
    # Measured 0.049 deg / 0.12 mm (the eight alone: 0.040 / 0.092); the bound here is where they belong,
    # the accuracy is the other tests'.
    _check_poses_of(json_poses(out)[:8], truth, obj, 0.1, 0.2)


def json_poses(out: Path) -> np.ndarray:
    """(V, 4, 4) the poses of ``registration.json`` in ``out`` (NaN for a view left out)."""
    doc = json.loads((out / "registration.json").read_text())
    return np.stack([np.block([[np.array(v["R"]), np.array(v["T"])[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
                     if "R" in v else np.full((4, 4), np.nan) for v in doc["views"]])


def test_keep_support_keeps_the_plate_disc(loaded, labels) -> None:
    """--keep-support adds the plate's disc to what is fused, and nothing else: judged by the
    simulator's labels, and the disc's radius against the plate's true rim (the labelled plate
    samples' largest distance from the true axis)."""
    ss, views, truth, obj = loaded
    iso = isolate_object(views, ss, IsolationParams(keep_support=True))
    disc = iso.report["support_plane"]["disc"]
    rim = []
    for v, lab in zip(views, labels, strict=True):
        plate = v.xyz[lab[v.pixel[:, 1], v.pixel[:, 0]] == LABEL_PLATE] - truth.axis_point
        rim.append(np.linalg.norm(plate - np.outer(plate @ truth.axis_direction, truth.axis_direction), axis=1).max())
    centre = np.array(disc["centre_mm"]) - truth.axis_point
    off_axis = float(np.linalg.norm(centre - truth.axis_direction * (centre @ truth.axis_direction)))
    print(f"plate disc radius {disc['radius_mm']:.2f} mm (true rim {max(rim):.2f} mm), centre {off_axis:.2f} mm "
          "from the axis")
    assert abs(disc["radius_mm"] - max(rim)) <= 0.03 * max(rim) and off_axis <= 0.03 * max(rim)
    added = kept = 0
    for reg_v, fus_v, lab in zip(iso.registration, iso.fusion, labels, strict=True):
        extra = np.setdiff1d(fus_v.pixel[:, 1] * lab.shape[1] + fus_v.pixel[:, 0],
                             reg_v.pixel[:, 1] * lab.shape[1] + reg_v.pixel[:, 0])
        kept += int(np.count_nonzero(lab.ravel()[extra] == LABEL_PLATE))
        added += len(extra)
    print(f"support kept: {added} samples, {100 * kept / max(1, added):.2f} % on the plate")
    assert added > 0 and kept >= 0.99 * added
    assert iso.report["support_kept"] and sum(v["support_kept"] for v in iso.report["per_view"]) == added


def _registration_at(poses: np.ndarray) -> Registration:
    """The given poses as a registration (figures of the fit left blank: the checks under test are
    about the poses)."""
    V = len(poses)
    return Registration(poses=np.asarray(poses, float), method="given", rms_mm=np.zeros(V), overlap=np.ones(V),
                        inlier_share=np.ones(V), voxel_mm=1.0)


def _turned(truth, views: list[int], deg: float) -> np.ndarray:
    """The true poses with ``views`` turned ``deg`` about the true axis (a wrong angle for those views)."""
    turn = _about_axis(truth.axis_direction, truth.axis_point, deg)
    poses = truth.poses.copy()
    poses[views] = turn @ poses[views]
    return poses


@pytest.fixture(scope="module")
def isolated(loaded):
    ss, views, *_ = loaded
    return isolate_object(views, dataclasses.replace(ss, turntable_deg=None))


def test_free_space_check_passes_the_truth_and_names_a_view_off_about_the_axis(loaded, isolated) -> None:
    """The free-space check on the real simulated views: the true poses pass; one view turned
    1.5 deg about the true axis (still one axis, the loop not chained: the other checks pass it)
    is named, in one line (at 640x480 a sample is 0.7 mm: 0.8 deg moves the bunny's silhouette by
    about a pixel, the limit of the check here; at 1024x768 0.8 deg is found on every object)."""
    ss, views, truth, obj = loaded
    names = [v.name for v in ss.views]
    views_obj = isolated.registration
    right = check_registration(_registration_at(truth.poses), views_obj, names, turntable=True)
    shares = [v["free_space_share"] for v in right.doc["views"]]
    print(f"true poses: free-space shares {[round(100 * s, 3) for s in shares]} %")
    assert right.doc["passed"] and max(shares) <= FREE_SPACE_SHARE
    wrong = check_registration(_registration_at(_turned(truth, [3], 1.5)), views_obj, names, turntable=True)
    shares = [v["free_space_share"] for v in wrong.doc["views"]]
    print(f"view_03 1.5 deg off: free-space shares {[round(100 * s, 3) for s in shares]} %; {wrong.failures}")
    assert wrong.failed_views == [3] and int(np.argmax(shares)) == 3
    assert wrong.doc["views"][3]["flags"] == ["in_free_space"]
    with pytest.raises(InputError, match=r"^views\[3\] \(view_03\): view_03 put samples where other views saw "
                                         r"through") as exc:
        register_checked(lambda idx: pytest.fail("not registered again"), views_obj, names, turntable=True,
                         angles_deg=None, drop_unregistered=False, registered=_registration_at(_turned(truth, [3], 1.5)))
    assert "\n" not in str(exc.value)


def test_free_space_figure_grows_with_the_error(loaded, isolated) -> None:
    """The figure measures the error: an arc of three views turned 0.3, 0.8 and 1.5 deg raises the
    worst view's share monotonically from the truth's."""
    ss, views, truth, obj = loaded
    worst = [float(np.nanmax(free_space_shares(*free_space_pairs(isolated.registration, poses))))
             for poses in (truth.poses, *(_turned(truth, [3, 4, 5], d) for d in (0.3, 0.8, 1.5)))]
    print(f"worst free-space share at 0, 0.3, 0.8, 1.5 deg: {[round(100 * w, 3) for w in worst]} %")
    assert all(b > a for a, b in zip(worst, worst[1:], strict=False))
    assert worst[0] <= FREE_SPACE_SHARE < worst[3]


def test_repair_turns_a_slipped_arc_back(loaded, isolated) -> None:
    """Two arcs that each fit but slipped 0.8 deg against each other (what the joint fit of a
    near-symmetric teapot left at 16 views): the free-space repair finds the arc and the turn."""
    ss, views, truth, obj = loaded
    slipped = _turned(truth, [4, 5, 6, 7], 0.8)
    poses, lines = repair_slips(isolated.registration, slipped, (truth.axis_direction, truth.axis_point))
    errs = [pose_error(poses[i], truth.poses[i], obj[i])[0] for i in range(8)]
    print(lines, [round(e, 3) for e in errs])
    assert len(lines) == 1
    named = re.match(r"views (.*) turned ([-+][0-9.]+) deg", lines[0])
    assert named and sorted(named.group(1).split(", ")) == ["view_04", "view_05", "view_06", "view_07"]
    assert max(errs) <= 0.1  # the turn grid's step is 0.2 deg: the joint refinement takes it from there
