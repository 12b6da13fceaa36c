"""Multi-view merge benchmark: our registration against Open3D's ICP + multiway pose graph, and a whole
12-view 2048x1536 merge from PNG files to meshes.

1. Registration, side by side on the same samples from the same coarse poses (the turntable model:
   the axis estimated from FPFH+RANSAC of neighbouring views, computed once, not timed):
   - ours: :func:`shared.merge.registration.refine_registration` (robust point-to-plane over every
     overlapping pair at once, pairs pruned by overlap);
   - Open3D 0.19+: its multiway-registration recipe, point-to-plane ICP (coarse then fine) for every
     pair that overlaps, a ``PoseGraph`` with odometry and loop-closure edges and
     ``global_optimization`` (Levenberg-Marquardt, ``edge_prune_threshold`` 0.25);
   - small_gicp: its GICP for the same pairs into the same Open3D pose graph.
   Accuracy: the worst view's rotation error and RMS displacement of its object points against the
   truth (simulated 12 views at 2048x1536) and against Stanford's registration (real dragon, 15
   views). Targets: ours at least as accurate as Open3D and at least 2x faster.
2. ``graylight merge`` of the simulated 12-view 2048x1536 turntable scan set (PNG files to meshes)
   in a child process: wall time and peak memory. Targets: under 2 minutes and under 6 GB.
   The scan set is rendered once into the temporary folder and kept for later runs.
3. Issue 22, real turntables (``turntable``): 3 objects of the shared meshes (bunny, teapot, spot),
   16 views rendered once with backdrop, table, base and plate (the 8-view set is every second
   view), each registered and fused as ``graylight merge`` does with no roi and no hints, with the
   angles given, and cropped by the roi: every view's error against the truth, the merged points
   by the simulator's labels, the coverage of the object surface any view saw. ``--size`` sets
   the image size (2048x1536 by default; the measured run below is 1024x768).
4. Issue 22, real data (``dragon_pairs``): the Stanford dragon registered with no hints and with the
   angles only; per overlapping pair the median nearest-neighbour distance in the overlap under our
   poses and Stanford's, and our poses' distance to Stanford's.

Measured for issue 22 at 1024x768 (load 7-12 on 2 cores; worst view; merged points off the object
by the simulator's labels; coverage of the seen object surface; the free-space check's worst view,
bound 0.5 %):
- no roi, no hints: bunny 8 views 0.023 deg / 0.052 mm, 0.10 %, 99.2 %; bunny 16 0.025 / 0.052,
  0.13 %, 99.4 %; teapot 8 0.031 / 0.064, 0.11 %, 97.7 %; teapot 16 0.0155 / 0.030, 0.15 %, 96.7 %
  (before the free-space repair 0.81-0.83 / 1.46-1.50 with every check passing: the joint fit of
  the near-symmetric body left views 6-15 slipped 0.8 deg about the axis against views 0-5, and the
  loop closed all the same; the new free-space check puts that registration at 1.37 % and refuses
  it; the repair turns the arc back); spot 8 0.014 / 0.032, spot 16 0.022 / 0.042, 0.11-0.18 %,
  98.7-98.8 %. Free space, worst view: 0.06-0.15 % in every mode;
- angles given: bunny 8 0.023 / 0.052, bunny 16 0.024 / 0.052, teapot 8 0.031 / 0.063, teapot 16
  0.016 / 0.027, spot 8 0.014 / 0.032, spot 16 0.022 / 0.041 (target 0.02 / 0.05 not reached at
  1024x768 for bunny, teapot 8 and spot 16; the roi-cropped run is as far). On bunny 8 and spot 8
  and 16 the errors are a tilt of the whole set's axis, 0.006-0.009 deg from the true one, like the
  plate's own axis (0.010-0.011 deg off, found on the static plate alone; each view's error turns
  about a line across the axis, its share along the axis under 0.006 deg): the reconstructed camera
  frame is turned against the true one (a principal point about 0.3 pixel off does that), so every
  pose is the true one conjugated by that small turn (error 2 sin(angle / 2) times the tilt) and no
  registration removes it; the poses already turn about one axis, so a joint fit held to one axis
  would not either (reasoned, not run);
- roi crop, no hints: bunny 8 0.023 / 0.055, bunny 16 0.028 / 0.053, teapot 8 0.019 / 0.044,
  teapot 16 0.014 / 0.039, spot 8 0.017 / 0.042, spot 16 0.025 / 0.040.
  Before the axis search the teapot was refused in every mode but 16 views with angles, and its
  16-view roi-cropped run passed every check 44.9 deg / 79 mm from the truth.
- at 2048x1536, bunny (``--size 2048x1536 --scenes bunny``, load 6-7): no roi, no hints 8 views
  0.012 / 0.023, 16 views 0.018 / 0.029; angles given 8 views 0.012 / 0.023, 16 views 0.016 /
  0.027 (target 0.02 / 0.05: reached); roi crop 8 views 0.015 / 0.027, 16 views 0.018 / 0.030;
  0.04-0.05 % off the object, 99.0-99.2 % covered; free space, worst view 0.16-0.19 % (bound 0.5).
- dragon (41 pairs overlapping by 20 % within 1 mm under Stanford's poses): ours at least as tight on
  41 of 41, median of the pairs' medians 0.323 mm against 0.362 mm; 0.653 deg / 1.503 mm from
  Stanford's poses with no hints and with angles (target 0.7 / 1.6: reached).

Parts run alone by name: ``python -m tests.bench.bench_merge sim dragon`` (registration only),
``python -m tests.bench.bench_merge turntable --size 1024x768`` (``--scenes bunny --views 16`` to
run a part of it).
Times are printed as wall and CPU seconds (Open3D's ICP uses both cores, ours runs the edges' searches
in 2 threads); on the shared machine the CPU ratio is the steadier one.

Measured here (2 shared cores, load average 5-6, three runs):
- simulated 12 views: ours 3.1-3.4 s CPU (4.8-7.4 s wall), worst view 0.0059 deg / 0.020 mm;
  Open3D 14.5-15.1 s CPU (27.6-29.7 s wall), 0.048 deg / 0.19 mm; small_gicp 15.3-15.7 s CPU,
  0.095 deg / 0.19 mm: ours 8x more accurate, 4.5-4.9x less CPU, 3.7-6.0x less wall (target 2x:
  reached; before: 1.86x wall);
- dragon against Stanford: ours 1.75-1.92 s CPU (1.8-5.6 s wall), 0.65 deg / 1.50 mm; Open3D
  4.7-4.9 s CPU (2.8-13.8 s wall), 0.86 deg / 1.59 mm; small_gicp 3.2-3.6 s CPU, 0.60 deg / 1.39 mm:
  2.5-2.8x less CPU (target 2x: reached; before 0.56x); wall ratios 1.6-3.9x swing with the load
  (one run of five under 2x). Every method is about 0.6 deg from Stanford's poses, which are not
  the optimum of any objective tried (see tests/shared/merge/test_dragon.py): the median
  point-to-plane residual of neighbouring scans is 0.118 mm with their poses, 0.082 mm with ours,
  0.084 mm with Open3D's and 0.082 mm with small_gicp's;
- whole merge: 198.5 s wall, 187 s CPU (not reached: load 37 s, register 49 s, fuse 20 s, Poisson
  depth 9 80 s, LODs 6 s), peak 5.09 GB (reached). Now 90.2 s wall, 67.0 s CPU, peak 4.24 GB at
  load 4-6 (both reached; stages in wall seconds: load 24.6, register 13.2, fuse 5.5, Poisson
  depth 9 41.3, LODs 2.1, write 1.7; the same run's mesh: Hausdorff 95th percentile 1.98x the
  merged cloud's 0.022 mm RMS, bound 3x). A run before the fusion's gather kernel (fuse about 4 s
  more CPU) at load 4-5 took 127.2 s wall, 76.5 s CPU: the wall time follows the other processes.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from shared.formats.scanset import load_scanset
from shared.merge.registration import (
    RegistrationParams,
    _Features,
    _turntable_init,
    pose_error,
    prepare_samples,
    refine_registration,
)
from shared.merge.views import crop_to_roi, load_views
from shared.sim.simulate import load_truth
from tests.bench._child import run_graylight
from tests.support.scansets import (
    DRAGON,
    dragon_scanset,
    merged_label_shares,
    plane_residuals,
    stanford_poses,
)

REPO = Path(__file__).resolve().parents[2]
SIM = Path(tempfile.gettempdir()) / "graylight-bench" / "scanset-bunny-turntable-12-2048x1536"


def _sim_scanset() -> Path:
    from shared.sim.scanset import simulate_scanset

    if not (SIM / "scanset.json").is_file():
        t0 = time.perf_counter()
        simulate_scanset("bunny", SIM, views=12, mode="turntable", size=(2048, 1536), projector=(1024, 768),
                         overwrite=True)
        print(f"  (rendered the 12-view 2048x1536 scan set once in {time.perf_counter() - t0:.0f} s: {SIM})")
    return SIM


def _open3d_multiway(S, init: np.ndarray, voxel: float, pairs, fit: str) -> np.ndarray:
    """Open3D's multiway registration recipe over ``pairs`` from ``init``; ``fit`` picks the
    pairwise fit: ``"open3d"`` point-to-plane ICP or ``"small_gicp"`` GICP."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    clouds = []
    for s in S:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(s.target_xyz))
        pc.normals = o3d.utility.Vector3dVector(s.target_normals)
        clouds.append(pc)
    graph = reg.PoseGraph()
    for P in init:
        graph.nodes.append(reg.PoseGraphNode(P))
    coarse, fine = 3.0 * voxel, 1.0 * voxel
    for i, j in pairs:
        T0 = np.linalg.solve(init[j], init[i])  # i -> j
        if fit == "open3d":
            r1 = reg.registration_icp(clouds[i], clouds[j], coarse, T0, reg.TransformationEstimationPointToPlane())
            r2 = reg.registration_icp(clouds[i], clouds[j], fine, r1.transformation,
                                      reg.TransformationEstimationPointToPlane())
            T = r2.transformation
        else:
            import small_gicp

            res = small_gicp.align(S[j].target_xyz, S[i].target_xyz, init_T_target_source=T0,
                                   registration_type="GICP", max_correspondence_distance=coarse, num_threads=2)
            T = res.T_target_source
        info = reg.get_information_matrix_from_point_clouds(clouds[i], clouds[j], fine, T)
        graph.edges.append(reg.PoseGraphEdge(i, j, T, info, uncertain=abs(i - j) not in (1, len(S) - 1)))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=fine, edge_prune_threshold=0.25,
                                          reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    poses = np.stack([np.asarray(n.pose) for n in graph.nodes])
    return np.linalg.inv(poses[0]) @ poses


def _compare(label: str, views, truth_poses: np.ndarray, points, angles: np.ndarray) -> dict[str, np.ndarray]:
    params = RegistrationParams()
    S, voxel = prepare_samples(views, params)
    coarse_voxel = voxel * float(np.sqrt(params.fine_samples / params.coarse_samples))
    init, _ = _turntable_init(S, _Features(S, coarse_voxel, 0), angles, voxel, params)
    V = len(S)
    pairs = [(i, j) for i in range(V) for j in range(i + 1, V) if min(j - i, V - (j - i)) <= 2]

    def worst(poses: np.ndarray) -> tuple[float, float]:
        e = [pose_error(poses[i], truth_poses[i], points[i]) for i in range(V)]
        return max(x[0] for x in e), max(x[1] for x in e)

    # Our kernels come from numba's cache as a worker loads them at start (Open3D is imported above).
    from workers.warmup import load_cached_kernels

    load_cached_kernels(("merge",))
    rows = []
    found: dict[str, np.ndarray] = {}
    for name, run in (
        ("ours (joint robust point-to-plane)", lambda: refine_registration(S, init, voxel, params)[0]),
        ("Open3D ICP + multiway pose graph", lambda: _open3d_multiway(S, init, voxel, pairs, "open3d")),
        ("small_gicp GICP + Open3D pose graph", lambda: _open3d_multiway(S, init, voxel, pairs, "small_gicp")),
    ):
        for s in S:
            s._neighbours = None  # each run builds what it needs from the shared samples
        t0, c0 = time.perf_counter(), time.process_time()
        poses = run()
        rows.append((name, time.perf_counter() - t0, time.process_time() - c0, *worst(poses)))
        found[name] = poses
    print(f"{label}: {V} views, {voxel:.2f} mm samples, same coarse start "
          f"(turntable model: worst {worst(init)[0]:.3f} deg / {worst(init)[1]:.3f} mm)")
    for name, sec, cpu, deg, mm in rows:
        print(f"  {name:<38} {sec:7.2f} s wall {cpu:7.2f} s CPU   worst view {deg:.4f} deg / {mm:.4f} mm")
    ours, o3d_row = rows[0], rows[1]
    print(f"  ratio: Open3D / ours time {o3d_row[1] / ours[1]:.2f}x wall, {o3d_row[2] / ours[2]:.2f}x CPU (target "
          f">= 2x); accuracy ours {ours[3]:.4f} deg / {ours[4]:.4f} mm vs Open3D {o3d_row[3]:.4f} deg / "
          f"{o3d_row[4]:.4f} mm (target: ours <= Open3D); load average {os.getloadavg()[0]:.1f}")
    return found


def _plane_fit(views, poses: np.ndarray) -> tuple[float, float]:
    """Median |point-to-plane residual| (mm) between neighbouring views under ``poses`` (both
    directions, every point within 1 mm of the other view with agreeing normals: the figure the fits
    minimise), and the mean signed residual of those under 0.5 mm (negative: each scan lies inside
    its neighbour)."""
    from scipy.spatial import cKDTree

    trees = [cKDTree(v.xyz) for v in views]
    n = len(views)
    r = np.concatenate([plane_residuals(views, trees, poses, a, b)
                        for i in range(n) for a, b in ((i, (i + 1) % n), ((i + 1) % n, i))])  # fmt: skip
    return float(np.median(np.abs(r))), float(np.mean(r[np.abs(r) < 0.5]))


def bench_registration_sim() -> None:
    folder = _sim_scanset()
    ss = load_scanset(folder)
    views = [crop_to_roi(v, ss.roi) for v in load_views(ss)]
    with np.load(folder / "truth.npz") as z:
        truth = z["poses"]
    points = []
    for spec in ss.views:
        t = load_truth(spec.path)
        points.append(t.points[(t.surface == 0) & np.isfinite(t.depth)].astype(np.float64))
    _compare("simulated bunny turntable 2048x1536 (truth)", views, truth, points, ss.turntable_deg)


def _dragon_views():
    """The dragon's scan set (angles given) and its views, or None (printed) when the data is missing."""
    if not (DRAGON / "dragonStandRight.conf").is_file():
        print(f"dragon: missing {DRAGON}")
        return None
    ss = load_scanset(dragon_scanset(Path(tempfile.mkdtemp(prefix="graylight-bench-dragon-")), turntable=True))
    return ss, load_views(ss)


def bench_registration_dragon() -> None:
    loaded = _dragon_views()
    if loaded is None:
        return
    ss, views = loaded
    found = _compare("real dragon turntable (against Stanford's registration)", views, stanford_poses(),
                     [v.xyz for v in views], ss.turntable_deg)
    # Which poses fit the scans better: Stanford's are not the optimum (test_dragon.py has the checks).
    print("  fit of neighbouring scans, median |point-to-plane residual| (mean signed residual):")
    for name, poses in [("Stanford's registration", stanford_poses()), *found.items()]:
        med, signed = _plane_fit(views, poses)
        print(f"    {name:<38} {med:.4f} mm ({signed:+.4f} mm)")


def bench_whole_merge() -> None:
    folder = _sim_scanset()
    out = Path(tempfile.mkdtemp(prefix="graylight-bench-merge-"))
    load = os.getloadavg()[0]
    run = run_graylight(["merge", str(folder), "--out", str(out / "m")])  # peak: the merge's own
    report = json.loads((out / "m" / "report.json").read_text())
    print("graylight merge, simulated 12-view 2048x1536 turntable scan set, PNG files -> merged cloud and meshes:")
    print(f"  wall {run.wall:.1f} s (target < 120 s), CPU {run.cpu:.1f} s, peak memory "
          f"{run.peak_gb:.2f} GB (target < 6 GB); load average at start {load:.1f}")
    print(f"  stages (s): {report['seconds']}")
    print(f"  {report['points']['merged']} merged points, {report['mesh']['faces']} faces (Poisson depth "
          f"{report['mesh']['depth']}); {run.stdout.strip().splitlines()[0]}")


# --------------------------------------------------------------------------------------- issue 22: no roi, no hints

TURNTABLE_SCENES = ("bunny", "teapot", "spot")
TURNTABLE_SIZE = (2048, 1536)


def _turntable_set(scene: str, size: tuple[int, int]) -> Path:
    """A 16-view turntable set of ``scene`` at ``size`` with its ``roi`` written (the cropped run
    uses it, the others remove it), rendered once into the bench's temporary folder. The 8-view set
    is every second view of it (the same 45 degree steps a real 8-view capture takes)."""
    from tests.support.scansets import cached_scanset

    t0 = time.perf_counter()
    folder = cached_scanset(SIM.parent, scene=scene, views=16, mode="turntable", size=size,
                            projector=(1024, 768), roi=True)
    if time.perf_counter() - t0 > 5.0:
        print(f"  (rendered {folder.name} in {time.perf_counter() - t0:.0f} s)")
    return folder


def _register_as_merge(views, ss, keep_support: bool = False):
    """What ``graylight merge`` does before meshing: the object isolated, registered and checked
    (an error is raised as merge raises it), fused. Returns (registration, checks, isolation, fused)."""
    from shared.merge.checks import register_checked
    from shared.merge.fusion import fuse_views
    from shared.merge.isolate import IsolationParams, isolate_object
    from shared.merge.pipeline import registration_views
    from shared.merge.registration import register_views

    iso = isolate_object(views, ss, IsolationParams(keep_support=keep_support))
    thinned = registration_views(iso.registration)
    names = [v.name for v in views]

    def register(idx: list[int]):
        angles = None if ss.turntable_deg is None else ss.turntable_deg[idx]
        return register_views([thinned[i] for i in idx], turntable_deg=angles, names=[names[i] for i in idx],
                              table_axis=iso.axis)

    reg, checks = register_checked(register, iso.registration, names,
                                   turntable=bool(iso.report["fixed_rig"] or ss.turntable_deg is not None),
                                   angles_deg=ss.turntable_deg, drop_unregistered=False)
    fused = fuse_views(iso.fusion, reg.poses)
    return reg, checks, iso, fused


def _coverage(fused, obj_world: np.ndarray) -> float:
    """Share of the object surface any view saw (true points, set frame) within 3 median merged
    point sizes of the merged cloud."""
    from scipy.spatial import cKDTree

    reach = 3.0 * float(np.median(fused.size))
    d, _ = cKDTree(fused.xyz).query(obj_world, distance_upper_bound=reach, workers=2)
    return float(np.isfinite(d).mean())


def bench_turntable_no_roi(size: tuple[int, int] = TURNTABLE_SIZE, scenes: tuple[str, ...] = TURNTABLE_SCENES,
                           counts: tuple[int, ...] = (8, 16)) -> None:
    """Issue 22's figures: simulated turntable sets with backdrop, table, base and plate, no roi and
    no hints (targets 0.05 deg / 0.1 mm every view, <= 0.5 % static/support/plate points in the merged
    cloud by the simulator's labels, >= 95 % of the seen object surface covered), the same with the
    angles given (0.02 deg / 0.05 mm), beside the roi-cropped run (no hints)."""
    import dataclasses

    from shared.formats.scanset import ScanSet

    print(f"turntable sets without roi (issue 22), {size[0]}x{size[1]}, load average {os.getloadavg()[0]:.1f}:")
    for scene in scenes:
        folder = _turntable_set(scene, size)
        full: ScanSet = load_scanset(folder)
        all_views = load_views(full)
        with np.load(folder / "truth.npz") as z:
            truth = z["poses"]
        truths = [load_truth(spec.path) for spec in full.views]
        for n in counts:
            pick = list(range(0, 16, 16 // n))
            views = [all_views[i] for i in pick]
            base = dataclasses.replace(full, views=[full.views[i] for i in pick], turntable_deg=full.turntable_deg[pick])
            T0inv = np.linalg.inv(truth[pick[0]])
            poses_true = np.stack([T0inv @ truth[i] for i in pick])
            obj = [truths[i].points[(truths[i].labels == 0) & np.isfinite(truths[i].depth)].astype(np.float64)
                   for i in pick]
            labels = [truths[i].labels for i in pick]
            seen = np.concatenate([o @ P[:3, :3].T + P[:3, 3] for o, P in zip(obj, poses_true, strict=True)])
            for mode, ss, deg_t, mm_t in (("no roi, no hints", dataclasses.replace(base, roi=None, turntable_deg=None),
                                           0.05, 0.1),
                                          ("no roi, angles", dataclasses.replace(base, roi=None), 0.02, 0.05),
                                          ("roi crop, no hints", dataclasses.replace(base, turntable_deg=None),
                                           0.05, 0.1)):
                t0 = time.perf_counter()
                try:
                    reg, checks, iso, fused = _register_as_merge(views, ss)
                except Exception as exc:  # noqa: BLE001 - a refused set is a figure of the bench
                    print(f"  {scene} {n} views, {mode}: REFUSED: {exc}")
                    continue
                err = [pose_error(reg.poses[k], poses_true[k], obj[k]) for k in range(n)]
                shares = merged_label_shares(fused.xyz, iso.fusion, reg.poses, labels)
                off = 1.0 - shares["object"] - shares["none"]
                cov = _coverage(fused, seen)
                worst = (max(e[0] for e in err), max(e[1] for e in err))
                ok = worst[0] <= deg_t and worst[1] <= mm_t and off <= 0.005 and cov >= 0.95
                print(f"  {scene} {n} views, {mode}: worst view {worst[0]:.4f} deg / {worst[1]:.4f} mm "
                      f"(target {deg_t} / {mm_t}); off-object points {100 * off:.2f} % (plate "
                      f"{100 * shares['plate']:.2f}, support {100 * shares['support']:.2f}, base "
                      f"{100 * shares['base']:.2f}, backdrop {100 * shares['backdrop']:.2f}; target <= 0.5); "
                      f"coverage {100 * cov:.1f} % (target >= 95); checks {'passed' if checks.doc['passed'] else 'FAILED'}"
                      f"; {'reached' if ok else 'NOT reached'}; {time.perf_counter() - t0:.0f} s")
                free = checks.doc.get("free_space") or {}
                print(f"    free space: worst view {100 * free.get('worst_share', float('nan')):.3f} % (bound "
                      f"{100 * free.get('bound_share', float('nan')):.2f} %); {reg.method}")
                print("    per view (deg/mm): " + ", ".join(f"{d:.3f}/{m:.3f}" for d, m in err))


def _pair_medians(views, poses: np.ndarray, pairs, reach: float, n: int = 4000) -> np.ndarray:
    """Per pair (i, j): the median nearest-neighbour distance (mm) from up to ``n`` of view i's points
    to view j's within ``reach`` mm (the overlap) under ``poses``."""
    from scipy.spatial import cKDTree

    world = [v.xyz @ P[:3, :3].T + P[:3, 3] for v, P in zip(views, poses, strict=True)]
    trees = [cKDTree(w) for w in world]
    out = []
    for i, j in pairs:
        src = world[i][:: max(1, len(world[i]) // n)]
        d, _ = trees[j].query(src, distance_upper_bound=reach, workers=2)
        d = d[np.isfinite(d)]
        out.append(float(np.median(d)) if len(d) else np.nan)
    return np.array(out)


def bench_dragon_pairs() -> None:
    """Issue 22's real-data figures: the Stanford dragon (cloud views) registered with no hints and
    with the angles only; per overlapping pair the median nearest-neighbour distance in the overlap
    under our poses and under Stanford's, and our poses' distance to Stanford's (target 0.7 deg /
    1.6 mm; ours at least as tight on the pairs)."""
    from scipy.spatial import cKDTree

    from shared.merge.registration import register_views

    loaded = _dragon_views()
    if loaded is None:
        return
    ss, views = loaded
    stanford = stanford_poses()
    V = len(views)
    # Overlapping pairs under Stanford's poses: at least 20 % of either view within 1 mm of the other.
    world = [v.xyz[:: max(1, len(v) // 3000)] @ P[:3, :3].T + P[:3, 3] for v, P in zip(views, stanford, strict=True)]
    full = [cKDTree(v.xyz @ P[:3, :3].T + P[:3, 3]) for v, P in zip(views, stanford, strict=True)]
    pairs = [(i, j) for i in range(V) for j in range(i + 1, V)
             if min(np.mean(full[j].query(world[i], distance_upper_bound=1.0)[0] < 1.0),
                    np.mean(full[i].query(world[j], distance_upper_bound=1.0)[0] < 1.0)) >= 0.2]
    theirs = _pair_medians(views, stanford, pairs, 1.0)
    for mode, angles in (("no hints", None), ("angles only", ss.turntable_deg)):
        t0 = time.perf_counter()
        reg = register_views(views, turntable_deg=angles)
        ours = _pair_medians(views, reg.poses, pairs, 1.0)
        dist = [pose_error(reg.poses[k], stanford[k], views[k].xyz[:: 50]) for k in range(V)]
        worst = (max(d for d, _ in dist), max(m for _, m in dist))
        tighter = int(np.sum(ours <= theirs))
        print(f"dragon, {mode}: {tighter} of {len(pairs)} overlapping pairs at least as tight as Stanford's (median "
              f"of medians ours {np.nanmedian(ours):.4f} mm, Stanford's {np.nanmedian(theirs):.4f} mm); farthest "
              f"view from Stanford's {worst[0]:.3f} deg / {worst[1]:.3f} mm (target 0.7 / 1.6: "
              f"{'reached' if worst[0] <= 0.7 and worst[1] <= 1.6 else 'NOT reached'}); "
              f"{time.perf_counter() - t0:.0f} s")
        print("  pairs (ours/Stanford's mm): " + ", ".join(f"{i}-{j} {a:.3f}/{b:.3f}" for (i, j), a, b in
                                                          zip(pairs, ours, theirs, strict=True)))


def main(argv: list[str] | None = None) -> None:
    """Run the named parts (``sim``, ``dragon``, ``merge``; all when none is named). ``make bench``
    calls it with none; ``python -m tests.bench.bench_merge sim dragon`` runs the registration only."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m tests.bench.bench_merge", description="Multi-view merge bench.")
    ap.add_argument("parts", nargs="*", metavar="PART", help="sim: registration on the simulated 12 views; dragon: "
                    "registration on the real dragon; merge: the whole 12-view merge; turntable: issue 22's sets "
                    "without roi (3 objects, 8 and 16 views); dragon_pairs: the dragon's pairs against Stanford's "
                    "(default: all)")
    ap.add_argument("--size", default="2048x1536", help="image size of the turntable part (default 2048x1536)")
    ap.add_argument("--scenes", default=",".join(TURNTABLE_SCENES),
                    help=f"scenes of the turntable part, comma-separated (default {','.join(TURNTABLE_SCENES)})")
    ap.add_argument("--views", default="8,16", help="view counts of the turntable part: 8, 16 or both (default 8,16)")
    args = ap.parse_args([] if argv is None else argv)
    size = tuple(int(x) for x in args.size.lower().split("x"))
    scenes = tuple(s for s in args.scenes.split(",") if s)
    counts = tuple(int(n) for n in args.views.split(",") if n)
    if [s for s in scenes if s not in TURNTABLE_SCENES] or [n for n in counts if n not in (8, 16)]:
        ap.error(f"--scenes takes {', '.join(TURNTABLE_SCENES)}; --views takes 8 and 16")
    parts = {"sim": bench_registration_sim, "dragon": bench_registration_dragon, "merge": bench_whole_merge,
             "turntable": lambda: bench_turntable_no_roi(size, scenes, counts), "dragon_pairs": bench_dragon_pairs}  # type: ignore[arg-type]
    chosen = args.parts or list(parts)
    unknown = [p for p in chosen if p not in parts]
    if unknown:
        ap.error(f"unknown part(s) {', '.join(unknown)} (choose from {', '.join(parts)})")
    for part in chosen:
        parts[part]()


if __name__ == "__main__":
    main(sys.argv[1:])
