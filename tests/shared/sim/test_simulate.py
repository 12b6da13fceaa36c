"""The virtual rig: ground truth self-consistency, image formation effects, capture contract, CLI."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.cli.main import main as cli_main
from shared.core.errors import InputError
from shared.formats.capture import load_capture
from shared.formats.mesh import load_obj, parse_obj
from shared.formats.rig import load_rig
from shared.scan.graycode import gray_decode
from shared.sim.response import linearise
from shared.sim.scenes import Material, Scene, TexturedPlane, build_scene, rotation_about
from shared.sim.simulate import (
    ImagingParams,
    compute_truth,
    load_truth,
    make_rig,
    render_pattern_images,
    simulate_capture,
)

SMALL = (480, 360)


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def _grey(img: np.ndarray) -> np.ndarray:
    return img.astype(np.float64).mean(axis=2) if img.ndim == 3 else img.astype(np.float64)


# ----------------------------------------------------------------------------------------------- OBJ


def test_obj_loader_triangulates_polygons_and_resolves_negative_indices() -> None:
    text = "\n".join(
        [
            "# a unit square as one quad, then a triangle with negative and slashed indices",
            "v 0 0 0",
            "v 1 0 0",
            "v 1 1 0",
            "v 0 1 0",
            "vt 0 0",
            "vn 0 0 1",
            "f 1/1/1 2/1/1 3/1/1 4/1/1",
            "v 2 2 2",
            "f -1//1 -3 -4/1",
            "f 1 2 3 4 5",
        ]
    )
    m = parse_obj(text)
    assert m.vertices.shape == (5, 3)
    np.testing.assert_array_equal(m.faces[:2], [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(m.faces[2], [4, 2, 1])
    np.testing.assert_array_equal(m.faces[3:], [[0, 1, 2], [0, 2, 3], [0, 3, 4]])
    # The quad's fan covers the square's area exactly.
    area = (
        0.5
        * np.linalg.norm(
            np.cross(
                m.vertices[m.faces[:2, 1]] - m.vertices[m.faces[:2, 0]],
                m.vertices[m.faces[:2, 2]] - m.vertices[m.faces[:2, 0]],
            ),
            axis=1,
        ).sum()
    )
    assert area == pytest.approx(1.0)


@pytest.mark.parametrize(
    "text, problem",
    [
        ("v 0 0 0\nf 1 2 3\n", "does not exist"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "index 0"),
        ("v 0 0 0\n", "no faces"),
        ("v 0 0 zero\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "not all numbers"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "not integers"),
    ],
)
def test_obj_loader_rejects_bad_files(text: str, problem: str) -> None:
    with pytest.raises(InputError, match=problem):
        parse_obj(text, "bad.obj")


def test_missing_mesh_is_input_error_naming_the_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GRAYLIGHT_SHARED_DATA", str(tmp_path))
    with pytest.raises(InputError) as exc:
        build_scene("bunny")
    assert str(tmp_path / "meshes" / "stanford-bunny.obj") in str(exc.value)
    with pytest.raises(InputError, match="not found"):
        load_obj(tmp_path / "nothing.obj")
    with pytest.raises(InputError, match="unknown scene"):
        build_scene("no-such-scene")


# ------------------------------------------------------------------------------------------- truth


@pytest.mark.parametrize("scene", ["bunny", "spheres", "corner"])
def test_truth_is_consistent_with_the_rig(scene: str) -> None:
    rig = make_rig(camera_size=SMALL, seed=3)
    truth = compute_truth(build_scene(scene), rig)
    valid = np.isfinite(truth.depth)
    assert valid.mean() > 0.95
    P = truth.points[valid].astype(np.float64)
    np.testing.assert_array_equal(truth.depth[valid], truth.points[..., 2][valid])
    # Camera: every point projects (with distortion) onto its own pixel centre.
    uv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), rig.camera.K, rig.camera.dist)
    rows, cols = np.nonzero(valid)
    assert np.abs(uv[:, 0, 0] - cols).max() < 2e-3
    assert np.abs(uv[:, 0, 1] - rows).max() < 2e-3
    # Projector: OpenCV's projection of the point through R, T and the projector's lens gives proj_col/row.
    rvec, _ = cv2.Rodrigues(rig.R)
    pp, _ = cv2.projectPoints(P.reshape(-1, 1, 3), rvec, rig.T, rig.projector.K, rig.projector.dist)
    assert np.abs(pp[:, 0, 0] - truth.proj_col[valid]).max() < 2e-3
    assert np.abs(pp[:, 0, 1] - truth.proj_row[valid]).max() < 2e-3
    # Normals: unit length and facing the camera.
    n = truth.normals[valid]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)
    assert np.all(np.einsum("ij,ij->i", n, P) <= 1e-6)
    # Lit points lie inside the projector's frame; something is seen but not lit (shadows).
    lit = truth.lit
    assert not np.any(lit & ~valid)
    w, h = rig.projector.width, rig.projector.height
    assert np.all((truth.proj_col[lit] >= -0.5) & (truth.proj_col[lit] < w - 0.5))
    assert np.all((truth.proj_row[lit] >= -0.5) & (truth.proj_row[lit] < h - 0.5))
    assert 0.5 < lit.mean() < 1.0


def test_mesh_ray_casting_is_exact_and_watertight() -> None:
    """A tilted square as a fan of triangles gives the same depths as the analytic plane, with no holes."""
    from shared.formats.mesh import TriangleMesh
    from shared.sim.scenes import MeshObject

    rig = make_rig(camera_size=SMALL, seed=2)
    R = rotation_about([1, 1, 0], 30.0)
    t = np.array([-250.0, -200.0, 950.0])
    size = 500.0
    # A 5x5 grid of vertices, each cell split into two triangles: many shared edges to leak through.
    g = np.linspace(0, size, 5)
    gx, gy = np.meshgrid(g, g)
    verts = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(25)])
    faces = []
    for r in range(4):
        for c in range(4):
            a, b, d, e = r * 5 + c, r * 5 + c + 1, (r + 1) * 5 + c, (r + 1) * 5 + c + 1
            faces += [[a, b, e], [a, e, d]]
    mesh = MeshObject(TriangleMesh(verts, np.array(faces, np.int32)), R=R, t=t)
    plane = TexturedPlane(R, t, np.full((2, 2), 0.5, np.float32), size / 2)
    tm = compute_truth(Scene("mesh", [mesh]), rig)
    tp = compute_truth(Scene("plane", [plane]), rig)
    both = np.isfinite(tp.depth)
    assert both.sum() > 50000
    assert np.array_equal(np.isfinite(tm.depth), both)
    np.testing.assert_allclose(tm.depth[both], tp.depth[both], rtol=1e-6)
    np.testing.assert_allclose(np.abs(np.einsum("ij,j->i", tm.normals[both], R[:, 2])), 1.0, atol=1e-5)


def test_rig_is_realistic_and_has_distortion() -> None:
    rig = make_rig(seed=1)
    assert (rig.camera.width, rig.camera.height, rig.projector.width, rig.projector.height) == (
        2048,
        1536,
        1024,
        768,
    )
    assert rig.baseline == pytest.approx(220.0, rel=0.1)
    assert np.all(np.abs(rig.camera.dist[:2]) > 1e-3) and np.all(np.abs(rig.projector.dist[:2]) > 1e-3)
    # The projector's axis is toed in: its centre ray meets the camera's axis near 1 m.
    C = -rig.R.T @ rig.T
    axis = rig.R[2]
    s = -C[0] / axis[0]
    assert 800 < (C + s * axis)[2] < 1200
    assert make_rig(seed=1).camera.K.tolist() == rig.camera.K.tolist()
    assert make_rig(seed=2).camera.K.tolist() != rig.camera.K.tolist()


def test_shadow_boundaries_follow_occluders() -> None:
    """A sphere before a wall: wall points whose segment to the projector crosses the sphere are not lit."""
    rig = make_rig(camera_size=SMALL, seed=0)
    R = np.eye(3)
    wall = TexturedPlane(R, np.array([-600.0, -450.0, 1200.0]), np.full((4, 4), 0.8, np.float32), 300.0)
    from shared.sim.scenes import Sphere

    ball = Sphere(np.array([0.0, 0.0, 950.0]), 60.0)
    truth = compute_truth(Scene("ball", [wall, ball]), rig)
    on_wall = truth.surface == 0
    P = truth.points[on_wall].astype(np.float64)
    C = -rig.R.T @ rig.T
    d = C - P
    # Closest approach of each wall-to-projector segment to the sphere's centre.
    s = np.clip(np.einsum("ij,ij->i", ball.center - P, d) / np.einsum("ij,ij->i", d, d), 0, 1)
    dist = np.linalg.norm(P + s[:, None] * d - ball.center, axis=1)
    lit = truth.lit[on_wall]
    clear = dist > ball.radius + 3.0
    blocked = dist < ball.radius - 3.0
    assert blocked.sum() > 1000
    assert not lit[blocked].any()
    inside = (
        (truth.proj_col[on_wall] > 2)
        & (truth.proj_col[on_wall] < 1020)
        & (truth.proj_row[on_wall] > 2)
        & (truth.proj_row[on_wall] < 765)
    )
    assert lit[clear & inside].all()


# ------------------------------------------------------------------------------------------- images


def test_small_bunny_capture(tmp_path: Path) -> None:
    """One 800x600 bunny capture checked three ways (one render: these checks share it)."""
    out = tmp_path / "cap"
    simulate_capture(build_scene("bunny"), make_rig(camera_size=(800, 600), seed=0), out, seed=5)
    _check_contract(out)
    _check_unlit_pixels_show_no_stripes_and_lit_ones_do(out)
    _check_stripes_land_where_truth_says(out)


def _check_contract(small_bunny: Path) -> None:
    cap = load_capture(small_bunny)
    assert (cap.projector_width, cap.projector_height) == (1024, 768)
    assert [e.bit for e in cap.columns] == list(range(9, -1, -1))
    assert [e.bit for e in cap.rows] == list(range(9, -1, -1))
    assert all(e.inverse is not None for e in (*cap.columns, *cap.rows))
    assert cap.rig is not None
    rig = load_rig(cap.rig)
    sizes = {_read(p).shape for p in cap.image_paths()[:4]}
    assert sizes == {(rig.camera.height, rig.camera.width)}
    assert _read(cap.white).dtype == np.uint8
    truth = load_truth(small_bunny)
    assert truth.depth.shape == (600, 800) and truth.points.shape == (600, 800, 3)
    assert truth.depth.dtype == np.float32 and truth.lit.dtype == np.bool_
    assert cap.extra["simulated"]["scene"] == "bunny"
    assert not [p for p in small_bunny.parent.iterdir() if p.name.endswith(".tmp")]


def _linear(path: Path, response: str) -> np.ndarray:
    """An 8-bit image's linear signal through the camera's response, in 8-bit steps of full scale."""
    return 255.0 * linearise(_grey(_read(path)) / 255.0, response)


def _check_unlit_pixels_show_no_stripes_and_lit_ones_do(small_bunny: Path) -> None:
    cap = load_capture(small_bunny)
    truth = load_truth(small_bunny)
    assert truth.response == "srgb" == cap.extra["simulated"]["imaging"]["response"]
    k3 = np.ones((5, 5), np.uint8)
    shadow = cv2.erode((np.isfinite(truth.depth) & ~truth.lit).astype(np.uint8), k3).astype(bool)
    lit = cv2.erode(truth.lit.astype(np.uint8), k3).astype(bool)
    assert shadow.sum() > 2000
    # Compared in the linear signal: the sRGB response stretches the noise of dark pixels.
    white, black = _linear(cap.white, truth.response), _linear(cap.black, truth.response)
    assert np.abs(white - black)[shadow].mean() < 1.0
    bright = lit & (white - black > 40)
    for e in cap.columns[:4]:
        diff = np.abs(_linear(e.pattern, truth.response) - _linear(e.inverse, truth.response))
        assert diff[shadow].mean() < 1.0
        assert np.median(diff[bright]) > 20
    # Black level and ambient: the black frame is not black where the projector reaches.
    assert np.median(black[lit]) > np.median(black[shadow])


def _check_stripes_land_where_truth_says(small_bunny: Path) -> None:
    """Pattern/inverse comparison of the coarse bits decodes to the truth's projector column (away from edges)."""
    cap = load_capture(small_bunny)
    truth = load_truth(small_bunny)
    nbits = 6
    code = np.zeros(truth.depth.shape, np.int64)
    for e in cap.columns[:nbits]:
        code = (code << 1) | (_grey(_read(e.pattern)) > _grey(_read(e.inverse)))
    col = gray_decode(code, nbits)
    stripe = 1024 // (1 << nbits)
    true_stripe = np.floor((truth.proj_col + 0.5) / stripe)
    frac = (truth.proj_col + 0.5) / stripe - true_stripe
    white = _grey(_read(cap.white))
    sure = truth.lit & (frac > 0.15) & (frac < 0.85) & (white > 40)
    assert sure.sum() > 20000
    assert (col[sure] == true_stripe[sure]).mean() > 0.995


@pytest.mark.slow
def test_full_size_bunny_decodes_to_truth(bunny_capture: Path) -> None:
    """At 2048x1536 a plain full-code decode agrees with the truth on almost every lit pixel."""
    cap = load_capture(bunny_capture)
    truth = load_truth(bunny_capture)
    assert truth.depth.shape == (1536, 2048)
    code = np.zeros(truth.depth.shape, np.int64)
    for e in cap.columns:
        code = (code << 1) | (_read(e.pattern) > _read(e.inverse))
    col = gray_decode(code, 10)
    lit = truth.lit
    err = col[lit] - np.floor(truth.proj_col[lit] + 0.5)
    assert (err == 0).mean() > 0.9
    assert (np.abs(err) <= 1).mean() > 0.995
    assert 0.8 < lit.mean() < 0.99  # the bunny shadows part of the wall and floor


def test_same_seed_same_files_other_seed_other_noise(tmp_path: Path) -> None:
    rig = make_rig(camera_size=(320, 240), seed=0)
    imaging = ImagingParams(rows=False)
    a = simulate_capture(build_scene("plane"), rig, tmp_path / "a", seed=1, imaging=imaging)
    b = simulate_capture(build_scene("plane"), rig, tmp_path / "b", seed=1, imaging=imaging)
    c = simulate_capture(build_scene("plane"), rig, tmp_path / "c", seed=2, imaging=imaging)
    for pa, pb in zip(a.image_paths(), b.image_paths(), strict=True):
        assert pa.read_bytes() == pb.read_bytes()
    assert a.rows == ()
    ia, ic = _read(a.white).astype(int), _read(c.white).astype(int)
    assert 0 < np.abs(ia - ic).mean() < 4  # only the noise differs
    with pytest.raises(InputError, match="not empty"):
        simulate_capture(build_scene("plane"), rig, tmp_path / "a", seed=1, imaging=imaging)
    # Without inverses: same pattern images (same noise), no inverse entries or files.
    d = simulate_capture(
        build_scene("plane"), rig, tmp_path / "d", seed=1, imaging=ImagingParams(rows=False, inverses=False)
    )
    assert all(e.inverse is None for e in d.columns) and len(list((tmp_path / "d").glob("*.png"))) == 12
    assert d.columns[4].pattern.read_bytes() == a.columns[4].pattern.read_bytes()


def test_colour_16_bit_and_specular_saturation() -> None:
    rig = make_rig(camera_size=SMALL, seed=0)
    images, truth = render_pattern_images(
        build_scene("spheres"), rig, imaging=ImagingParams(colour=True, bits=16), names={"white.png"}
    )
    white = images["white.png"]
    assert white.shape == (360, 480, 3) and white.dtype == np.uint16
    # The glossy sphere's highlight clips at full scale; the dark sphere stays dark.
    assert (white == 65535).all(axis=2).sum() >= 3
    # Colour: the orange sphere is redder than it is blue (BGR order).
    orange = truth.surface == 3
    assert orange.sum() > 500
    assert np.median(white[orange][:, 2]) > 1.5 * np.median(white[orange][:, 0])


def test_interreflection_lights_the_corner() -> None:
    rig = make_rig(camera_size=SMALL, seed=0)
    scene = build_scene("corner")
    kw = {"noise": False, "rows": False, "camera_blur": 0.0}
    names = {"white.png", "col_00.png", "col_00_inv.png"}
    with_ir, truth = render_pattern_images(scene, rig, imaging=ImagingParams(**kw), names=names)
    without, _ = render_pattern_images(scene, rig, imaging=ImagingParams(interreflection=False, **kw), names=names)
    walls = (truth.surface == 0) | (truth.surface == 1)
    gain = with_ir["white.png"].astype(float)[walls] - without["white.png"].astype(float)[walls]
    assert np.median(gain) > 3
    assert np.all(gain >= -1)
    # Indirect light reaches the pixels the projector cannot see as well: stripes of a coarse bit show there.
    unlit = cv2.erode((walls & ~truth.lit).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    if unlit.sum() > 200:
        d = np.abs(with_ir["col_00.png"].astype(float) - with_ir["col_00_inv.png"].astype(float))
        assert d[unlit].mean() > 0.5


def test_subsurface_scattering_blurs_the_stripes() -> None:
    rig = make_rig(camera_size=(320, 240), seed=0)
    contrast = []
    for sss in (0.0, 3.0):
        wall = TexturedPlane(np.eye(3), np.array([-600.0, -450.0, 1000.0]), np.full((4, 4), 0.8, np.float32), 300.0,
                             Material(albedo=(1.0, 1.0, 1.0), subsurface=sss))
        images, truth = render_pattern_images(Scene("wall", [wall]), rig,
                                              names={"white.png", "black.png", "col_06.png", "col_06_inv.png"})
        signal = images["white.png"].astype(float) - images["black.png"]
        diff = np.abs(images["col_06.png"].astype(float) - images["col_06_inv.png"])  # 16-pixel stripes
        contrast.append(float(np.mean(diff[truth.lit] / signal[truth.lit])))
    assert contrast[0] > 0.8
    assert contrast[1] < contrast[0] - 0.15


def test_chessboard_plane_renders_corners_where_the_pose_puts_them() -> None:
    rig = make_rig(camera_size=(1024, 768), seed=4)
    R = rotation_about([0, 1, 0], 20.0) @ rotation_about([1, 0, 0], -15.0)
    board = TexturedPlane.chessboard(R, np.zeros(3), inner_corners=(9, 7), square_size=30.0)
    w, h = board.size_mm
    board.t = np.array([0.0, 0.0, 950.0]) - R @ np.array([w / 2, h / 2, 0.0])
    images, _ = render_pattern_images(Scene("board", [board]), rig, names={"white.png"})
    white = images["white.png"]
    found, corners = cv2.findChessboardCornersSB(white, (9, 7), flags=cv2.CALIB_CB_ACCURACY)
    assert found
    truth_xyz = board.to_camera(board.chessboard_corners())
    uv, _ = cv2.projectPoints(truth_xyz, np.zeros(3), np.zeros(3), rig.camera.K, rig.camera.dist)
    d = np.linalg.norm(corners.reshape(-1, 2)[:, None, :] - uv.reshape(1, -1, 2), axis=2).min(axis=1)
    assert np.sqrt(np.mean(d**2)) < 0.15
    obj = board.chessboard_object_points()
    assert obj.shape == (63, 3) and np.allclose(obj[1] - obj[0], [30.0, 0, 0])


# ---------------------------------------------------------------------------------------------- CLI


def test_cli_simulate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cap"
    assert (
        cli_main(["simulate", "--scene", "plane", "--out", str(out), "--size", "320x240", "--no-rows"]) == 0
    )
    cap = load_capture(out)
    assert load_rig(out / "rig.json").camera.width == 320
    assert _read(cap.white).shape == (240, 320)
    assert cli_main(["simulate", "--scene", "plane", "--out", str(out), "--size", "320x240"]) == 1
    assert "not empty" in capsys.readouterr().err
    assert cli_main(["simulate", "--scene", "plane", "--out", str(tmp_path / "x"), "--size", "320by240"]) == 1
    assert "--size" in capsys.readouterr().err
    assert cli_main(["simulate", "--scene", "nope", "--out", str(tmp_path / "y")]) == 1
    assert "unknown scene" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
    # --force replaces an earlier capture, but never a folder that is not one.
    assert cli_main(["simulate", "--scene", "plane", "--out", str(out), "--size", "160x120", "--force"]) == 0
    assert _read(load_capture(out).white).shape == (120, 160)
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    assert cli_main(["simulate", "--scene", "plane", "--out", str(other), "--size", "160x120", "--force"]) == 1
    assert "does not hold a capture" in capsys.readouterr().err
    assert (other / "keep.txt").read_text() == "mine"
