"""Simulated scan sets: a turntable set sees what a real turntable does (backdrop, table, base,
plate), with per-pixel labels that agree with the geometry; the roi crop only when asked."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from services.cli.main import main as cli_main
from shared.formats.scanset import load_scanset
from shared.sim.scanset import (
    BACKDROP_DISTANCE,
    BASE_HEIGHT,
    PLATE_THICKNESS,
    load_scanset_truth,
    simulate_scanset,
    turntable_scenes,
)
from shared.sim.scenes import (
    LABEL_BACKDROP,
    LABEL_BASE,
    LABEL_NONE,
    LABEL_OBJECT,
    LABEL_PLATE,
    LABEL_SUPPORT,
    LABELS,
)
from shared.sim.simulate import compute_truth, load_truth, make_rig

STATIC = (LABEL_SUPPORT, LABEL_BASE, LABEL_BACKDROP)


@pytest.fixture(scope="module")
def turntable_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("tt") / "set"
    simulate_scanset("bunny", out, views=4, size=(256, 192), projector=(128, 96), seed=0)
    return out


def _distance_to_mesh(vertices: np.ndarray, faces: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Exact point-to-triangle distances (mm) of points near the mesh: each point against the
    triangles whose centroids lie within 8 mm of it (the meshes' triangles are a few mm wide)."""
    tri = vertices[faces]
    tree = cKDTree(tri.mean(axis=1))
    out = np.full(len(pts), np.inf)
    for i, cand in enumerate(tree.query_ball_point(pts, 8.0)):
        if cand:
            q = trimesh.triangles.closest_point(tri[cand], np.repeat(pts[i : i + 1], len(cand), axis=0))
            out[i] = np.linalg.norm(q - pts[i], axis=1).min()
    return out


def test_turntable_set_has_no_roi_and_labels_every_part(turntable_set: Path) -> None:
    doc = json.loads((turntable_set / "scanset.json").read_text())
    assert "roi" not in doc
    ss = load_scanset(turntable_set)
    assert ss.roi is None
    np.testing.assert_allclose(ss.turntable_deg, [0, 90, 180, 270])
    for spec in ss.views:
        t = load_truth(spec.path)
        assert t.labels is not None and t.labels.dtype == np.int8 and t.labels.shape == t.depth.shape
        shares = {LABELS[int(c)]: float((t.labels == c).mean()) for c in np.unique(t.labels)}
        # Everything a real turntable rig sees, nothing empty: the backdrop and table fill the rest.
        assert set(shares) == {"object", "plate", "support", "base", "backdrop"}, shares
        assert shares["object"] > 0.05 and shares["backdrop"] + shares["support"] > 0.4, shares
        assert np.array_equal(t.labels == LABEL_NONE, ~np.isfinite(t.depth))
        # Labels and surface indices agree: surface 0 is the object, 1 the plate.
        assert np.array_equal(t.labels == LABEL_OBJECT, t.surface == 0)
        assert np.array_equal(t.labels == LABEL_PLATE, t.surface == 1)


def test_labels_agree_with_the_geometry(turntable_set: Path) -> None:
    ss = load_scanset(turntable_set)
    truth = load_scanset_truth(turntable_set)
    up, a0 = truth.axis_direction, truth.axis_point
    for i, spec in enumerate(ss.views):
        t = load_truth(spec.path)
        pose = truth.poses[i]  # view -> set frame
        pts = {c: t.points[t.labels == c].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3] for c in LABELS}
        # Object pixels lie on the object's true surface (set frame).
        d = _distance_to_mesh(truth.mesh_vertices, truth.mesh_faces, pts[LABEL_OBJECT][::13])
        assert np.percentile(d, 99) < 0.05, np.percentile(d, 99)
        # Support: the table top, the plate's and base's heights below the object's foot.
        h = (pts[LABEL_SUPPORT] - a0) @ up
        np.testing.assert_allclose(h, -(PLATE_THICKNESS + BASE_HEIGHT), atol=1e-3)
        # Backdrop: a vertical plane BACKDROP_DISTANCE behind the axis.
        b = pts[LABEL_BACKDROP]
        c = b.mean(axis=0)
        n = np.linalg.svd(b - c, full_matrices=False)[2][2]
        assert np.abs((b - c) @ n).max() < 1e-3 and abs(float(n @ up)) < 1e-6
        assert abs(abs(float((c - a0) @ n)) - BACKDROP_DISTANCE) < 1e-3
        # Plate: its top at the object's foot, within its radius; base: below it, wider.
        hp = (pts[LABEL_PLATE] - a0) @ up
        assert hp.max() < 1e-3 and hp.min() > -PLATE_THICKNESS - 1e-3
        hb = (pts[LABEL_BASE] - a0) @ up
        assert hb.max() < -PLATE_THICKNESS + 1e-3 and hb.min() > -PLATE_THICKNESS - BASE_HEIGHT - 1e-3

        def radius(p: np.ndarray) -> np.ndarray:
            r = p - a0
            return np.linalg.norm(r - np.outer(r @ up, up), axis=1)

        assert radius(pts[LABEL_BASE]).max() > radius(pts[LABEL_PLATE]).max() + 5.0


def test_static_parts_keep_their_depth_across_views_and_the_object_does_not(turntable_set: Path) -> None:
    ss = load_scanset(turntable_set)
    truths = [load_truth(v.path) for v in ss.views]
    t0 = truths[0]
    for t in truths[1:]:
        for c in (*STATIC, LABEL_PLATE):  # the plain plate turns but looks static: that is the point
            both = (t0.labels == c) & (t.labels == c)
            assert both.sum() > 200, LABELS[c]
            assert np.abs(t0.depth[both] - t.depth[both]).max() < 1e-3, LABELS[c]
        obj = (t0.labels == LABEL_OBJECT) & (t.labels == LABEL_OBJECT)
        assert obj.sum() > 500
        assert np.mean(np.abs(t0.depth[obj] - t.depth[obj]) > 0.5) > 0.8
        # The object hides other parts of the static set in each view.
        assert np.any((t0.labels == LABEL_BACKDROP) & (t.labels == LABEL_OBJECT))


def test_roi_is_written_only_when_asked(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["simulate", "--scene", "bunny", "--views", "2", "--size", "64x48", "--projector", "64x48"]
    assert cli_main([*args, "--out", str(tmp_path / "plain")]) == 0
    assert "roi" not in json.loads((tmp_path / "plain" / "scanset.json").read_text())
    assert cli_main([*args, "--roi", "--out", str(tmp_path / "crop")]) == 0
    assert "roi written" in capsys.readouterr().out
    ss = load_scanset(tmp_path / "crop")
    truth = load_scanset_truth(tmp_path / "crop")
    # The crop holds the whole object.
    d = np.linalg.norm(truth.mesh_vertices - ss.roi.center, axis=1)
    assert d.max() < ss.roi.radius
    # A single capture has no region of interest to write.
    assert cli_main(["simulate", "--scene", "plane", "--size", "64x48", "--roi", "--out", str(tmp_path / "one")]) == 1
    assert "--roi" in capsys.readouterr().err
    assert not (tmp_path / "one").exists()


@pytest.mark.parametrize("scene, views", [("bunny", 16), ("spot", 8), ("teapot", 16), ("fandisk", 8)])
def test_mesh_scenes_work_as_turntable_objects(scene: str, views: int) -> None:
    scenes, poses, *_ = turntable_scenes(scene, views, "turntable", seed=0)
    assert len(scenes) == views
    rig = make_rig(camera_size=(240, 180), projector_size=(128, 96), seed=0)
    for k in (0, views // 2 + 1):
        t = compute_truth(scenes[k], rig)
        lab = t.labels
        assert {int(c) for c in np.unique(lab)} == {LABEL_OBJECT, LABEL_PLATE, LABEL_SUPPORT, LABEL_BASE,
                                                     LABEL_BACKDROP}
        # The object is framed: in view, touching no image edge.
        assert (lab == LABEL_OBJECT).mean() > 0.05
        edge = np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]])
        assert not np.any(edge == LABEL_OBJECT)
