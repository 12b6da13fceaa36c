"""The virtual rig tells the truth about colour: a known per-channel albedo, the camera's response,
the projector's falloff, and white/black frames from which dividing out the projector's irradiance
gives the albedo back."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from shared.core.errors import InputError
from shared.sim.response import apply_response, linearise
from shared.sim.scenes import LABEL_OBJECT, Material, Scene, TexturedPlane, build_scene
from shared.sim.simulate import ImagingParams, make_rig, render_pattern_images, sim_radiometry

FRAMES = {"white.png", "black.png"}
# Noise and optical blur off, 16 bits: each pixel's value is exactly the image model's.
EXACT = {"noise": False, "camera_blur": 0.0, "bits": 16, "colour": True, "rows": False}


def _linear(img: np.ndarray, response: str) -> np.ndarray:
    """A 16-bit BGR image's linear signal (fractions of full scale), RGB order."""
    return linearise(img[:, :, ::-1].astype(np.float64) / 65535.0, response)


def _wall(albedo: np.ndarray, z: float = 1000.0, size: float = 1200.0) -> Scene:
    """A flat wall facing the camera at distance ``z`` with the given texture, covering the projector's frame."""
    tex = np.asarray(albedo, np.float32)
    h, w = tex.shape[:2]
    t = np.array([-size / 2, -size / 2 * h / w, z])
    return Scene("wall", [TexturedPlane(np.eye(3), t, tex, size / w, Material(albedo=(1.0, 1.0, 1.0)))])


@pytest.mark.parametrize("scene", ["bunny", "teapot"])
def test_white_minus_black_over_irradiance_is_the_albedo(scene: str) -> None:
    rig = make_rig(camera_size=(320, 240), projector_size=(256, 192), seed=1)
    images, truth = render_pattern_images(build_scene(scene), rig, imaging=ImagingParams(**EXACT), names=FRAMES)
    assert truth.response == "srgb"
    signal = _linear(images["white.png"], truth.response) - _linear(images["black.png"], truth.response)
    irr = truth.irradiance
    ok = truth.lit & (truth.labels == LABEL_OBJECT) & (irr > 0.1 * np.nanmax(irr))
    # Away from the projector frame's and the shadows' edges (the pattern's blur reaches there).
    ok = cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert ok.sum() > 3000
    est = signal[ok] / irr[ok][:, None]
    rel = np.abs(est - truth.albedo[ok]) / truth.albedo[ok]
    if scene == "bunny":  # matte: the albedo itself
        assert np.median(rel) < 2e-3 and np.percentile(rel, 99) < 0.02, (np.median(rel), np.percentile(rel, 99))
    else:  # glossy: matte almost everywhere, and a specular lobe that only adds light
        assert np.median(rel) < 2e-3
        excess = (est - truth.albedo[ok]).min(axis=1)
        assert np.mean(excess > 0.05) > 0.002 and np.min(excess) > -0.01


def test_albedo_truth_is_coloured_and_detailed() -> None:
    rig = make_rig(camera_size=(480, 360), seed=0)
    from shared.sim.simulate import compute_truth

    for name in ("bunny", "spot", "teapot", "fandisk"):
        truth = compute_truth(build_scene(name), rig)
        a = truth.albedo
        assert a.shape == (360, 480, 3) and a.dtype == np.float32
        assert np.all(np.isnan(a[truth.labels < 0])) and np.all(np.isfinite(a[truth.labels >= 0]))
        obj = truth.labels == LABEL_OBJECT
        o = a[obj]
        assert np.all((o >= 0) & (o <= 1))
        # Colour, not grey: the channels vary independently of each other.
        chroma = o - o.mean(axis=1, keepdims=True)
        assert chroma.std(axis=0).min() > 0.02, (name, chroma.std(axis=0))
        # Detail: a 9-pixel box blur changes many object pixels' albedo noticeably.
        inner = cv2.erode(obj.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        blurred = cv2.blur(np.nan_to_num(a), (9, 9))
        changed = np.abs(blurred[inner] - a[inner]).max(axis=1) > 0.04
        assert changed.mean() > 0.1, (name, changed.mean())


def test_camera_response_is_srgb_by_default_and_recorded() -> None:
    """The white frame is not linear in the albedo under the default sRGB response; it is after linearising."""
    rig = make_rig(camera_size=(200, 150), projector_size=(128, 96), seed=0)
    tex = np.repeat(np.array([[0.1, 0.3, 0.6, 0.9]], np.float32), 3, axis=0)
    scene = _wall(tex)
    fits = {}
    for response in ("srgb", "linear", "gamma:2.2"):
        images, truth = render_pattern_images(scene, rig, imaging=ImagingParams(**{**EXACT, "response": response}),
                                              names=FRAMES)
        assert truth.response == response
        white = images["white.png"][:, :, ::-1].astype(np.float64) / 65535.0
        black = images["black.png"][:, :, ::-1].astype(np.float64) / 65535.0
        ok = truth.lit & (truth.irradiance > 0.2 * np.nanmax(truth.irradiance))
        ok = cv2.erode(ok.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        model = truth.albedo[ok] * truth.irradiance[ok][:, None]  # linear white minus black
        raw = (white - black)[ok]
        lin = (_linear(images["white.png"], response) - _linear(images["black.png"], response))[ok]
        fits[response] = (np.median(np.abs(raw - model) / model), np.median(np.abs(lin - model) / model))
        np.testing.assert_allclose(apply_response(linearise(white, response), response), white, atol=1e-9)
    assert fits["linear"][0] < 2e-3
    assert fits["srgb"][0] > 0.2 and fits["gamma:2.2"][0] > 0.2  # stored values are not linear
    assert fits["srgb"][1] < 2e-3 and fits["gamma:2.2"][1] < 2e-3  # linearised they are
    with pytest.raises(InputError, match="response"):
        render_pattern_images(scene, rig, imaging=ImagingParams(response="log"), names=FRAMES)


def test_projector_falloff_inverse_square_cosine_and_vignetting() -> None:
    """A uniform wall: the projector's irradiance follows its geometry (checked against an
    independent computation from the rig), falls towards the projector image's corners, drops as
    1/d^2 with distance, and the images carry it."""
    rig = make_rig(camera_size=(240, 180), projector_size=(128, 96), seed=2)
    flat = np.full((2, 2), 0.8, np.float32)
    C = -rig.R.T @ rig.T  # projector centre in the camera frame
    means = {}
    for vig, z in ((0.0, 1000.0), (-1.5, 1000.0), (0.0, 1600.0)):
        imaging = ImagingParams(**{**EXACT, "projector_vignetting": vig})
        assert sim_radiometry(imaging)["projector_vignetting"] == [vig]
        images, truth = render_pattern_images(_wall(flat, z, 2 * z), rig, imaging=imaging, names=FRAMES)
        ok = truth.lit & (truth.proj_col > 3) & (truth.proj_col < 124) & (truth.proj_row > 3) & (truth.proj_row < 92)
        P = truth.points[ok].astype(np.float64)
        L = C - P
        d = np.linalg.norm(L, axis=1)
        cos_t = (L / d[:, None]) @ np.array([0.0, 0.0, -1.0])
        Pp = P @ rig.R.T + rig.T  # projector frame
        r2 = (Pp[:, 0] ** 2 + Pp[:, 1] ** 2) / Pp[:, 2] ** 2
        cam_vig = (P[:, 2] / np.linalg.norm(P, axis=1)) ** 4
        expect = ((1 - imaging.black_level) * cam_vig * imaging.projector_power * cos_t * (1000.0 / d) ** 2
                  * (1 + r2) ** -1.5 * (1 + vig * r2))
        np.testing.assert_allclose(truth.irradiance[ok], expect, rtol=2e-3)
        # The images carry it: linear white minus black is albedo times irradiance.
        signal = (_linear(images["white.png"], truth.response) - _linear(images["black.png"], truth.response))[ok]
        np.testing.assert_allclose(signal.mean(axis=1), 0.8 * truth.irradiance[ok], rtol=5e-3)
        # The camera sees the middle of the projector's image: its outermost and innermost pixels.
        centre = r2 < 0.1 * r2.max()
        corner = r2 > 0.7 * r2.max()
        assert centre.sum() > 50 and corner.sum() > 50
        means[vig, z] = float(signal[corner].mean() / signal[centre].mean()), float(np.median(signal[centre]))
    # Natural falloff alone darkens the outer parts; the lens's vignetting darkens them further.
    assert means[0.0, 1000.0][0] < 0.97 and means[-1.5, 1000.0][0] < means[0.0, 1000.0][0] - 0.05, means
    # Inverse square: 1.6 times as far, about 1 / 1.6^2 of the signal near the projector's axis.
    assert means[0.0, 1600.0][1] / means[0.0, 1000.0][1] == pytest.approx(1 / 1.6**2, rel=0.05)


def test_cli_response_option(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    from services.cli.main import main as cli_main
    from shared.formats.capture import load_capture
    from shared.sim.simulate import load_truth

    args = ["simulate", "--scene", "plane", "--size", "64x48", "--projector", "64x48", "--no-rows"]
    assert cli_main([*args, "--response", "gamma:2.2", "--out", str(tmp_path / "g")]) == 0
    assert load_truth(tmp_path / "g").response == "gamma:2.2"
    assert load_capture(tmp_path / "g").extra["simulated"]["imaging"]["response"] == "gamma:2.2"
    assert cli_main([*args, "--response", "log", "--out", str(tmp_path / "bad")]) == 1
    err = capsys.readouterr().err
    assert "response" in err and "gamma:G" in err and err.count("\n") == 1
    assert not (tmp_path / "bad").exists()
