"""Seam levelling of the photograph bake on a simulated turntable set: the object's true mesh and
true poses (no merge, so the tests stay fast), its views' real white and black frames, and the
renderer's albedo as the truth the seams are measured against."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from shared.derive.bake import ColourSource, bake_maps, unwrap, vertex_normals
from shared.derive.photo import PhotoParams, PhotoSource, load_photo_source
from shared.derive.pipeline import simplify_to
from shared.formats.scanset import load_scanset
from shared.scan.albedo import encode_srgb, linear_from_srgb
from shared.sim.scanset import load_scanset_truth, turntable_scenes
from tests.support.derive_scene import seam_figures
from tests.support.scansets import cached_scanset

# One group: the module's set, true registration and atlas (``truth_set``) are made on one xdist
# worker, not once a worker.
pytestmark = pytest.mark.xdist_group("seams")

SCENE, VIEWS, S = "spot", 8, 384
_LUMA = np.array([0.2126, 0.7152, 0.0722])


@pytest.fixture(scope="module")
def truth_set(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The set's folder, a folder with its true registration, the object's level with its atlas, the
    master (the true mesh) and a colour source of the true mesh's vertices (for texels no view sees)."""
    folder = cached_scanset(tmp_path_factory.mktemp("seam-set"), scene=SCENE, views=VIEWS, size=(320, 240),
                            projector=(256, 192))
    truth = load_scanset_truth(folder)
    reg = {"views": [{"name": spec.name, "registered": True, "R": P[:3, :3].tolist(), "T": P[:3, 3].tolist()}
                     for spec, P in zip(load_scanset(folder).views, truth.poses, strict=True)]}
    merge = tmp_path_factory.mktemp("seam-reg")
    (merge / "registration.json").write_text(json.dumps(reg))
    mv = np.asarray(truth.mesh_vertices, np.float64)
    mf = np.asarray(truth.mesh_faces, np.int64)
    mn = vertex_normals(mv, mf)
    obj = turntable_scenes(SCENE, VIEWS)[0][0].surfaces[0]
    edge = float(np.median(np.linalg.norm(mv[mf[:, 0]] - mv[mf[:, 1]], axis=1)))
    colours = ColourSource(mv, encode_srgb(obj.albedo_at(mv)), mn, np.full(len(mv), edge, np.float32), "albedo")
    m = unwrap(*simplify_to(mv, mf, 6000), S)
    return {"folder": folder, "merge": merge, "m": m, "mv": mv, "mn": mn, "colours": colours}


def _photo(ts: dict, **kw) -> PhotoSource:
    photo, why = load_photo_source(ts["merge"], ts["folder"], PhotoParams(**kw))
    assert photo is not None, why
    assert len(photo.views) == VIEWS
    return photo


def _bake(ts: dict, photo: PhotoSource):
    return bake_maps(ts["m"], S, ts["colours"], ts["mv"], ts["mn"], photo=photo)


def test_levelling_lowers_the_colour_jump_across_view_borders(truth_set: dict) -> None:
    ts = truth_set
    plain = _bake(ts, _photo(ts, seam_levelling=False))
    levelled = _bake(ts, _photo(ts))
    st = levelled.stats["photo"]["seams"]
    # The views agree better where they overlap once corrected (the solve's own residual) ...
    assert st["rms_log_disagreement"][1] < 0.8 * st["rms_log_disagreement"][0]
    before, after = seam_figures(ts["m"], S, [plain, levelled], SCENE, VIEWS)
    print("seams before:", before, "after:", after)
    assert before["border_pairs"] > 300
    # ... and against the truth the step a border between views adds to the error drops, the
    # colour jump with it, while the error per texel stays where it was.
    assert after["jump_error"] < before["jump_error"]
    assert after["jump_error_view_set"] < before["jump_error_view_set"]
    assert after["jump"] < before["jump"]
    assert after["mae"] < 1.03 * before["mae"]


def test_levelled_colour_stays_within_the_correction_bounds(truth_set: dict) -> None:
    ts = truth_set
    plain = _bake(ts, _photo(ts, seam_levelling=False))
    photo = _photo(ts, seam_max_factor=1.25)
    levelled = _bake(ts, photo)
    tree, factor = photo._corrections
    assert factor.shape == (VIEWS, tree.n, 3)
    assert factor.min() >= 1 / 1.25 - 1e-6 and factor.max() <= 1.25 + 1e-6
    seen = (levelled.view >= 0) & (plain.view >= 0)
    a = linear_from_srgb(plain.base_colour[seen] / 255.0) @ _LUMA
    b = linear_from_srgb(levelled.base_colour[seen] / 255.0) @ _LUMA
    lit = a > 0.02  # 8-bit rounding dominates the ratio of the darkest texels
    ratio = b[lit] / a[lit]
    # A blend of views each scaled within the bounds (and the same gains) stays within them, but
    # where the correction changes which view is left out as a highlight (a handful of texels).
    out = (ratio < 1 / 1.25 - 0.02) | (ratio > 1.25 + 0.02)
    print(f"ratio {ratio.min():.4f}..{ratio.max():.4f}, beyond the bounds {out.sum()} of {out.size}")
    assert out.mean() < 1e-3
    assert abs(np.median(ratio) - 1) < 0.03  # no drift of the whole object's brightness


def test_one_view_is_left_as_it_is(truth_set: dict) -> None:
    ts = truth_set
    one = _photo(ts)
    one.views = one.views[:1]
    off = replace(one, params=replace(one.params, seam_levelling=False))
    a, b = _bake(ts, one), _bake(ts, off)
    assert one._corrections is None and "seams" not in a.stats["photo"]
    assert (a.view >= 0).sum() > 1000  # the one view colours part of the object
    assert np.array_equal(a.base_colour, b.base_colour)
