"""Base colour from the views' photographs: highlights left out by disagreement, and the baked
albedo per texel against the simulator's truth beside the cloud's albedo and today's per-vertex
white-frame colour."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shared.derive.photo import PhotoSource


def test_a_highlight_seen_by_one_view_is_left_out_and_unseen_points_say_so() -> None:
    src = PhotoSource(views=[])
    alb = np.full((3, 4, 3), 0.4, np.float32)
    alb[1, 0] = 0.9  # a glint in view 1 at point 0
    wts = np.ones((3, 4), np.float32)
    wts[:, 3] = 0.0  # point 3: no view sees it
    out, seen, rejected = src._combine(alb, wts, np.zeros((3, 4), bool), np.ones(3))
    assert np.allclose(out[:3], 0.4, atol=1e-6) and rejected == 1
    assert seen.tolist() == [True, True, True, False]
    # A view darker overall (its gain) is levelled, not left out.
    out, _, rejected = src._combine(alb * np.array([1.0, 1.0, 0.5])[:, None, None], wts, np.zeros((3, 4), bool),
                                    np.array([1.0, 1.0, 2.0]))
    assert np.allclose(out[1:3], 0.4, atol=1e-6) and rejected == 1


def test_a_highlight_in_the_heaviest_view_is_left_out_with_one_vote_a_view() -> None:
    from shared.derive.photo import PhotoParams

    alb = np.full((3, 2, 3), 0.4, np.float32)
    alb[0, 0] = 0.9  # the glint is in view 0, which faces point 0 and outweighs the others
    wts = np.array([[3.0, 1.0], [1.0, 1.0], [0.8, 1.0]], np.float32)
    no_lobe = np.zeros((3, 2), bool)
    _, _, rejected = PhotoSource(views=[])._combine(alb, wts, no_lobe, np.ones(3))
    assert rejected == 0  # weighted, the glint is its own reference
    out, _, rejected = PhotoSource(views=[], params=PhotoParams(highlight_vote_share=0.2))._combine(
        alb, wts, no_lobe, np.ones(3))
    assert rejected == 1 and np.allclose(out, 0.4, atol=1e-6)
    # The default: view 0 sees point 0 in its mirror configuration (the normal on the half-vector
    # between its camera and its projector), so the other views are the reference.
    lobe = no_lobe.copy()
    lobe[0, 0] = True
    out, _, rejected = PhotoSource(views=[])._combine(alb, wts, lobe, np.ones(3))
    assert rejected == 1 and np.allclose(out, 0.4, atol=1e-6)
    # A matte point in the mirror configuration agrees with the others and is kept.
    out, _, rejected = PhotoSource(views=[])._combine(np.full((3, 2, 3), 0.4, np.float32), wts, lobe, np.ones(3))
    assert rejected == 0


@pytest.mark.slow
def test_photograph_bake_beats_the_cloud_and_the_per_vertex_colour(tmp_path_factory: pytest.TempPathFactory) -> None:
    from shared.derive.bake import bake_maps, unwrap, vertex_normals
    from shared.derive.photo import load_photo_source
    from shared.derive.pipeline import _colour_source, load_master, simplify_to
    from shared.merge.pipeline import merge_scanset
    from shared.scan.albedo import linear_from_srgb
    from tests.support.derive_scene import texel_truth
    from tests.support.scansets import cached_scanset

    folder = cached_scanset(tmp_path_factory.mktemp("photo-set"), scene="bunny", views=8, size=(480, 360),
                            projector=(512, 384), roi=True)
    out = tmp_path_factory.mktemp("photo-merge") / "m"
    merge_scanset(folder, out)
    S = 512
    v, f, vc = load_master(out / "mesh.ply")
    cloud = _colour_source(out, "albedo", (v, f, vc), [])
    photo, why = load_photo_source(out)
    assert photo is not None, why
    m = unwrap(*simplify_to(v, f, 10_000), S)
    vn = vertex_normals(v, f)
    baked = {"cloud": bake_maps(m, S, cloud, v, vn), "photo": bake_maps(m, S, cloud, v, vn, photo=photo)}
    assert baked["photo"].stats["photo"]["texels_seen_share"] > 0.9
    cov, P, on, truth = texel_truth(m, S)  # texels on the bunny (not the plate) and the renderer's albedo there
    luma = np.array([0.2126, 0.7152, 0.0722])

    def mae(est: np.ndarray) -> float:
        scale = np.median(truth @ luma) / np.median(est @ luma)  # the one scale no scan knows
        return float(np.abs(scale * est - truth).mean())

    err = {k: mae(linear_from_srgb(mp.base_colour[cov] / 255.0).astype(np.float64)[on]) for k, mp in baked.items()}
    # Today's colour: the master's per-vertex white-frame colour (sRGB camera), nearest vertex.
    err["vertex"] = mae(linear_from_srgb(vc[cKDTree(v).query(P)[1]] / 255.0).astype(np.float64)[on])
    print("per-texel mean abs error of linear albedo: " + ", ".join(f"{k} {e:.3f}" for k, e in err.items()))
    assert err["photo"] < err["cloud"]
    assert err["photo"] < 0.7 * err["vertex"]
