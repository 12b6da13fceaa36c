"""Albedo from the projector's light: against the virtual rig's own albedo, masks, fallbacks, the PLY fields."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.capture import load_capture
from shared.formats.images import read_colour
from shared.formats.ply import read_header, read_ply, write_ply
from shared.formats.rig import load_rig, parse_rig
from shared.scan.albedo import (
    REASONS,
    AlbedoParams,
    CameraResponse,
    estimate_albedo,
    linear_from_srgb,
    params_for_rig,
    parse_response,
    smooth_normals,
)
from shared.scan.decode import decode_capture
from shared.scan.pipeline import scan, view_albedo
from shared.scan.triangulate import triangulate
from shared.sim._imaging import _albedo
from shared.sim.raycast import undistort_grid
from shared.sim.scenes import build_scene
from shared.sim.simulate import ImagingParams, load_truth, make_rig, simulate_capture

#: How the simulator forms today's images: linear sensor, projector cos^3 and camera cos^4 falloff.
SIM = AlbedoParams(response=CameraResponse("linear"), projector_cos_power=3, camera_cos_power=4)


@pytest.fixture(scope="module")
def spheres(tmp_path_factory: pytest.TempPathFactory):
    """A colour capture of the spheres scene (dark, coloured, glossy, marbled spheres before a printed wall)."""
    w, h = 400, 300
    scene = build_scene("spheres")
    rig = make_rig((w, h))
    root = tmp_path_factory.mktemp("alb") / "cap"
    cap = simulate_capture(scene, rig, root, imaging=ImagingParams(colour=True))
    decoded = decode_capture(cap)
    tri = triangulate(decoded, rig)
    truth = load_truth(root / "truth.npz")
    rx, ry = undistort_grid(rig.camera.K, rig.camera.dist, w, h)
    idx = tri.flat_index
    sid = truth.surface.ravel()[idx].astype(np.int64)
    seen = sid >= 0
    true_albedo = np.full((len(idx), 3), np.nan, np.float32)
    true_albedo[seen] = _albedo(scene, sid[seen], truth.points.reshape(-1, 3)[idx][seen].astype(np.float64),
                                (rx, ry), idx[seen], w)
    return cap, rig, decoded, tri, true_albedo


def _mae_up_to_scale(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """Mean absolute error after the one scale (projector power times camera gain) no scan can know."""
    s = np.median(truth[mask].sum(axis=1)) / np.median(estimate[mask].sum(axis=1))
    return float(np.abs(s * estimate[mask] - truth[mask]).mean())


def test_albedo_matches_the_simulators_albedo_far_better_than_the_shaded_colour(spheres) -> None:
    cap, rig, decoded, tri, true_albedo = spheres
    rig = load_rig(Path(cap.root) / "rig.json")  # the simulator writes how it forms images there
    alb = view_albedo(cap, tri, rig, white=decoded.colour)
    # The simulator renders through an sRGB camera by default and says so in the rig.
    assert alb.stats["response"] == rig.radiometry["camera_response"] == "srgb"
    assert alb.stats["projector_cos_power"] == SIM.projector_cos_power
    assert alb.trusted and alb.stats["valid_share"] > 0.8
    ok = (alb.weight > 0) & np.isfinite(true_albedo).all(axis=1)
    shaded = tri.rgb.astype(np.float32) / 255.0  # the white frame's colour as the cloud carried it before
    err_albedo = _mae_up_to_scale(alb.albedo, true_albedo, ok)
    err_shaded = _mae_up_to_scale(shaded, true_albedo, ok)
    # Measured: 0.016 against 0.111 (the projector's shading divided out).
    assert err_albedo < 0.3 * err_shaded
    # Every surface on its own (wall, floor, each sphere, the glossy one included) is better too,
    # each estimate at its one scale over the whole view.
    truth = load_truth(Path(cap.root) / "truth.npz")
    sid = truth.surface.ravel()[tri.flat_index]
    s_a = np.median(true_albedo[ok].sum(1)) / np.median(alb.albedo[ok].sum(1))
    s_s = np.median(true_albedo[ok].sum(1)) / np.median(shaded[ok].sum(1))
    for surface in np.unique(sid[ok]):
        m = ok & (sid == surface)
        if m.sum() < 500:
            continue
        e_a = np.abs(s_a * alb.albedo[m] - true_albedo[m]).mean()
        e_s = np.abs(s_s * shaded[m] - true_albedo[m]).mean()
        assert e_a < e_s, f"surface {surface}: albedo {e_a:.3f}, shaded {e_s:.3f}"


def test_window_normals_are_steadier_than_the_triangulations(spheres) -> None:
    cap, rig, decoded, tri, true_albedo = spheres
    truth = load_truth(Path(cap.root) / "truth.npz")
    tn = truth.normals.reshape(-1, 3)[tri.flat_index]
    seen = np.isfinite(tn).all(axis=1)
    sn = smooth_normals(tri.xyz, tri.pixel, tri.range_image.shape, 4)

    def median_angle(n: np.ndarray) -> float:
        c = np.clip(np.einsum("ij,ij->i", n[seen], tn[seen]), -1, 1)
        return float(np.degrees(np.nanmedian(np.arccos(c))))

    assert median_angle(sn) < 0.4 * median_angle(tri.normals)


def _plane(n: int = 200):
    """Points on a plane 1 m in front of a rig whose projector sits 200 mm to the side, facing the camera."""
    rig = make_rig((320, 240))
    xs = np.linspace(-100, 100, n, dtype=np.float32)
    xyz = np.stack([xs, np.zeros(n, np.float32), np.full(n, 1000.0, np.float32)], axis=1)
    normals = np.tile(np.array([[0, 0, -1]], np.float32), (n, 1))
    return rig, xyz, normals


def test_masks_name_saturated_dark_grazing_and_outside_samples() -> None:
    rig, xyz, normals = _plane(6)
    white = np.full((6, 3), 150, np.uint8)
    black = np.full((6, 3), 10, np.uint8)
    white[0] = (255, 120, 120)  # one channel clipped
    white[1] = black[1] + 1  # no signal
    # Grazing to the projector: 84 degrees from the direction to it, still facing the camera.
    lhat = (-rig.R.T @ rig.T - xyz[2]) / np.linalg.norm(-rig.R.T @ rig.T - xyz[2])
    perp = np.cross(lhat, [0.0, 1.0, 0.0])
    perp *= -np.sign(perp @ xyz[2])
    normals[2] = 0.1 * lhat + np.sqrt(0.99) * perp
    xyz[3] = (5000.0, 0.0, 1000.0)  # far outside the projector's image
    alb = estimate_albedo(white, black, xyz, normals, rig, AlbedoParams())
    assert [REASONS[r] for r in alb.reason[:4]] == ["saturated", "dark", "grazing", "outside_projector"]
    assert np.isnan(alb.albedo[:4]).all() and (alb.weight[:4] == 0).all()
    assert (alb.weight[4:] > 0).all() and np.isfinite(alb.albedo[4:]).all()
    enc, w = alb.encoded()
    assert (enc[:4] == 0).all() and (w[:4] == 0).all() and (w[4:] > 0).all()


def test_a_saturated_view_falls_back_to_the_shaded_colour_and_says_why() -> None:
    rig, xyz, normals = _plane(50)
    alb = estimate_albedo(np.full((50, 3), 255, np.uint8), np.zeros((50, 3), np.uint8), xyz, normals, rig)
    assert not alb.trusted
    assert "saturated" in alb.stats["fallback"] and "shaded colour" in alb.stats["fallback"]


def test_the_same_surface_gives_the_same_albedo_at_any_distance_and_angle() -> None:
    """The geometric irradiance model: a white frame formed by it is inverted exactly."""
    rig, xyz, normals = _plane(40)
    xyz[:, 2] = np.linspace(700, 1400, 40)
    tilt = np.radians(np.linspace(-40, 40, 40))
    normals = np.stack([np.sin(tilt), np.zeros(40), -np.cos(tilt)], axis=1).astype(np.float32)
    centre = -rig.R.T @ rig.T
    L = centre - xyz
    d = np.linalg.norm(L, axis=1)
    cos = np.einsum("ij,ij->i", normals, L) / d
    lin = 0.6 * cos * (1000.0 / d) ** 2  # albedo 0.6, linear camera
    white = np.clip(np.rint(np.stack([lin, lin * 0.5, lin * 0.25], 1) * 255), 0, 255).astype(np.uint8)
    alb = estimate_albedo(white, np.zeros_like(white), xyz, normals, rig,
                          AlbedoParams(response=CameraResponse("linear"), reference_distance=1000.0))
    ok = alb.weight > 0
    assert ok.sum() >= 35
    ratio = alb.albedo[ok] / np.array([0.6, 0.3, 0.15])
    assert np.abs(ratio - 1).max() < 0.06  # 8-bit quantisation of the darkest samples
    shaded_spread = white[ok, 0].max() / white[ok, 0].min()
    assert shaded_spread > 1.5  # the test would not tell anything on an evenly lit plane


def test_response_specs_and_files(tmp_path: Path) -> None:
    assert parse_response("srgb").lut()[128] == pytest.approx(linear_from_srgb(np.float32(128 / 255)), rel=1e-6)
    assert parse_response("gamma:2.0").lut()[255] == pytest.approx(1.0)
    with pytest.raises(InputError, match="gamma"):
        parse_response("gamma:abc")
    with pytest.raises(InputError, match="response"):
        parse_response(tmp_path / "missing.json")
    bad = tmp_path / "r.json"
    bad.write_text(json.dumps({"response": [1, 0.5]}))
    with pytest.raises(InputError, match="256"):
        parse_response(bad)
    good = tmp_path / "g.json"
    good.write_text(json.dumps({"response": list(np.linspace(0, 2, 256) ** 2)}))
    lut = parse_response(good).lut()
    assert lut[0] == 0 and lut[-1] == pytest.approx(1.0)


def test_ply_carries_albedo_beside_the_shaded_colour(tmp_path: Path) -> None:
    xyz = np.random.default_rng(0).normal(size=(10, 3)).astype(np.float32)
    rgb = np.full((10, 3), 90, np.uint8)
    alb = np.arange(30, dtype=np.uint8).reshape(10, 3)
    w = np.arange(10, dtype=np.uint8)
    write_ply(tmp_path / "a.ply", xyz, rgb=rgb, albedo=alb, albedo_weight=w)
    cloud = read_ply(tmp_path / "a.ply")
    np.testing.assert_array_equal(cloud.albedo, alb)
    np.testing.assert_array_equal(cloud.albedo_weight, w)
    np.testing.assert_array_equal(cloud.rgb, rgb)
    write_ply(tmp_path / "b.ply", xyz, rgb=rgb)
    assert read_ply(tmp_path / "b.ply").albedo is None
    with pytest.raises(ValueError, match="together"):
        write_ply(tmp_path / "c.ply", xyz, albedo=alb)


def test_scan_writes_the_albedo_and_falls_back_on_a_saturated_white_frame(tmp_path: Path, spheres) -> None:
    cap = spheres[0]
    report = scan(cap.root, tmp_path / "out")
    assert report["albedo"]["status"] == "measured"
    names = read_header(tmp_path / "out" / "cloud.ply").dtype.names
    assert {"albedo_red", "albedo_green", "albedo_blue", "albedo_weight"} <= set(names)
    cloud = read_ply(tmp_path / "out" / "cloud.ply")
    assert (cloud.albedo_weight > 0).mean() > 0.7
    # A white frame burnt out everywhere: the cloud keeps the shaded colour only, the report says why.
    white = read_colour(load_capture(cap.root).white)
    cv2.imwrite(str(Path(cap.root) / "white.png"), np.full_like(white, 255))
    report = scan(cap.root, tmp_path / "sat")
    assert report["albedo"]["status"] == "fallback" and "saturated" in report["albedo"]["fallback"]
    assert "albedo_red" not in read_header(tmp_path / "sat" / "cloud.ply").dtype.names


def test_rig_radiometry_is_validated_and_drives_the_albedo_parameters() -> None:
    rig = make_rig((320, 240))
    doc = rig.to_json()
    doc["radiometry"] = {"camera_response": "gamma:2.2", "projector_falloff_cos_power": 3,
                         "projector_vignetting": [-0.2]}
    params = params_for_rig(parse_rig(doc))
    assert params.response.kind == "gamma" and params.response.gamma == 2.2
    assert params.projector_cos_power == 3 and params.vignetting == (-0.2,) and params.camera_cos_power == 0
    assert params_for_rig(rig).response.kind == "srgb"  # no radiometry: an sRGB camera
    for bad, field in (({"camera_response": "log"}, "camera_response"), ({"camera_response": [0, 1]}, "camera_response"),
                       ({"projector_falloff_cos_power": 12}, "projector_falloff_cos_power"), ({"flash": 1}, "flash")):
        with pytest.raises(InputError, match=f"radiometry.{field}"):
            parse_rig({**doc, "radiometry": bad})
