"""Albedo through the merge: views' albedo fused per cell with specular highlights left out; the
merged cloud's albedo is free of the lamp's speckle that the white-frame colour has."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shared.formats.ply import read_header, read_ply
from shared.merge.fusion import fuse_views, write_fused
from shared.merge.pipeline import merge_scanset
from shared.merge.views import ViewCloud
from tests.support.scansets import cached_scanset


def _view(index: int, albedo: np.ndarray, xyz: np.ndarray) -> ViewCloud:
    n = len(xyz)
    return ViewCloud(index=index, name=f"v{index}", xyz=xyz, normals=np.tile(np.float32([0, 0, -1]), (n, 1)),
                     size=np.full(n, 1.0, np.float32), confidence=np.ones(n, np.float32),
                     rgb=np.full((n, 3), 100, np.uint8), albedo=albedo, albedo_weight=np.ones(n, np.float32))


def test_a_glint_seen_by_one_view_is_left_out_of_the_fused_albedo(tmp_path: Path) -> None:
    g = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2)
    xyz = np.column_stack([g + 0.5, np.full(len(g), 500.0)])
    base = np.full((len(g), 3), 0.4, np.float32)
    glint = base.copy()
    glint[:50] = 0.95  # a highlight in view 1 only
    views = [_view(0, base, xyz), _view(1, glint, xyz), _view(2, base, xyz)]
    fused = fuse_views(views, np.stack([np.eye(4)] * 3), free_space=False)
    assert fused.albedo is not None
    assert np.allclose(fused.albedo, 0.4, atol=1e-5)  # the glint is gone, not averaged in
    assert fused.stats["albedo"]["specular_rejected"] == 50
    write_fused(tmp_path / "m.ply", fused)
    names = read_header(tmp_path / "m.ply").dtype.names
    assert names[-4:] == ("albedo_red", "albedo_green", "albedo_blue", "albedo_weight")
    # Views without albedo (cloud views): no albedo fields, as before.
    plain = [ViewCloud(index=i, name="c", xyz=xyz, normals=v.normals, size=v.size, confidence=v.confidence, rgb=v.rgb)
             for i, v in enumerate(views)]
    fused = fuse_views(plain, np.stack([np.eye(4)] * 3), free_space=False)
    assert fused.albedo is None
    write_fused(tmp_path / "p.ply", fused)
    assert "albedo_red" not in read_header(tmp_path / "p.ply").dtype.names


def _speckle(values: np.ndarray, xyz: np.ndarray, mask: np.ndarray) -> float:
    """Share of points more than 40 grey levels darker than the median of their 12 neighbours."""
    _, nb = cKDTree(xyz).query(xyz, k=13)
    med = np.median(values[nb[:, 1:]], axis=1)
    return float(np.mean((med - values)[mask] > 40))


@pytest.mark.slow
def test_merged_albedo_has_a_tenth_of_the_white_frame_colours_speckle(tmp_path_factory) -> None:
    folder = cached_scanset(tmp_path_factory.mktemp("alb-merge"), scene="bunny", views=8, size=(480, 360),
                            projector=(512, 384))
    out = tmp_path_factory.mktemp("alb-out") / "m"
    report = merge_scanset(folder, out)
    assert report["fusion"]["albedo"]["points_with_albedo"] > 0.9 * report["fusion"]["merged_points"]
    cloud = read_ply(out / "merged.ply")
    assert cloud.albedo is not None and cloud.albedo_weight is not None
    ok = cloud.albedo_weight > 0
    luma = np.array([0.299, 0.587, 0.114])
    shaded = _speckle(cloud.rgb @ luma, cloud.xyz, ok)
    albedo = _speckle(cloud.albedo @ luma, cloud.xyz, ok)
    print(f"speckle: white-frame colour {100 * shaded:.2f} %, albedo {100 * albedo:.2f} %")
    assert shaded > 0.01  # the lamp's speckle is there to remove
    assert albedo * 10 <= shaded
