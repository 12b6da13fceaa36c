"""Calibration: the maths on synthetic points, the real session, bad sessions, and outputs.

Simulated whole sessions (rendered by the virtual rig) are in test_calibrate_simulated.py.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.calib.board import Board, parse_board
from shared.calib.calibrate import (
    ViewPoints,
    calibrate_camera,
    nearest_code_corners,
    projector_corners,
    triangulate_corners,
)
from shared.calib.session import (
    calibrate_camera_images,
    calibrate_session,
    default_decode,
    run_session,
    write_outputs,
)
from shared.core.datapaths import shared_data_dir
from shared.core.errors import InputError
from shared.formats.capture import Capture, numbered_frames, opencv_order_capture, write_capture
from shared.formats.rig import load_rig
from tests.support.links import place_file

REAL = shared_data_dir() / "procam-kamino410"
REAL_BOARD = {"kind": "chessboard", "inner_corners": [9, 7], "square_size": 75.0}
# The reference tool's reprojection RMS on this session (data README): ours must be lower.
REFERENCE_CAMERA_RMS = 0.316
REFERENCE_PROJECTOR_RMS = 0.203

needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="shared data not present")


# ---------------------------------------------------------------------------------------------
# Synthetic points: the maths alone


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    axis = np.asarray(axis, float)
    return cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(deg))[0]


def _synthetic_views(
    K: np.ndarray, dist: np.ndarray, tilts: list[float], noise: float, seed: int = 0
) -> list[ViewPoints]:
    board = Board("chessboard", (9, 7), 30.0)
    obj = board.object_points()
    rng = np.random.default_rng(seed)
    views = []
    for k, tilt in enumerate(tilts):
        phi = 2 * np.pi * k / len(tilts)
        R = _rotation([np.cos(phi), np.sin(phi), 0.0], tilt) @ _rotation([0, 0, 1], 7.0 * k)
        # Spread the board over the image: the principal point and distortion need the edges.
        centre = np.array([160.0 * np.cos(phi + 0.4), 110.0 * np.sin(phi + 0.4), 900.0 + 40 * k])
        t = centre - R @ np.array([120.0, 90.0, 0.0])
        uv, _ = cv2.projectPoints(obj.astype(np.float64), cv2.Rodrigues(R)[0], t, K, dist)
        uv = uv.reshape(-1, 2) + rng.normal(0, noise, (len(obj), 2))
        views.append(ViewPoints(f"v{k}", obj, uv))
    return views


K_TRUE = np.array([[2400.0, 0.0, 1010.0], [0.0, 2402.0, 770.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.08, 0.12, 3e-4, -2e-4, 0.0])
SIZE = (2048, 1536)


def test_calibrate_camera_recovers_truth_and_drops_a_bad_view(caplog: pytest.LogCaptureFixture) -> None:
    views = _synthetic_views(K_TRUE, DIST_TRUE, [20, 30, 25, 35, 22, 28, 32], noise=0.05)
    # Corrupt one view: its corners shifted irregularly by several pixels (a misdetected board).
    rng = np.random.default_rng(5)
    bad = views[3]
    views[3] = ViewPoints(
        bad.name, bad.object_points, bad.image_points + rng.normal(0, 3.0, bad.image_points.shape)
    )
    with caplog.at_level(logging.WARNING):
        cal = calibrate_camera(views, SIZE)
    assert "v3" in cal.rejected and "v3" not in cal.views
    assert any("v3" in r.message for r in caplog.records)
    assert cal.rms < 0.1
    K = cal.device.K
    assert abs(K[0, 0] / K_TRUE[0, 0] - 1) < 0.002 and abs(K[1, 1] / K_TRUE[1, 1] - 1) < 0.002
    # Small boards in mid-image leave the principal point trading off against tangential
    # distortion; the simulated sessions check the 2 px target with full-size boards.
    assert np.hypot(K[0, 2] - K_TRUE[0, 2], K[1, 2] - K_TRUE[1, 2]) < 8.0
    assert len(cal.per_view_rms) == len(cal.views) == 6


def test_calibrate_camera_refuses_degenerate_and_too_few_views() -> None:
    flat = _synthetic_views(K_TRUE, DIST_TRUE, [0.0] * 6, noise=0.05)
    with pytest.raises(InputError, match="degenerate"):
        calibrate_camera(flat, SIZE, where="session")
    # The same pose over and over: coplanar corners in one view, whatever its tilt.
    same = _synthetic_views(K_TRUE, DIST_TRUE, [25.0], noise=0.05)[0]
    with pytest.raises(InputError, match="degenerate"):
        calibrate_camera([ViewPoints(f"s{k}", same.object_points, same.image_points) for k in range(4)], SIZE)
    two = _synthetic_views(K_TRUE, DIST_TRUE, [20, 30], noise=0.05)
    with pytest.raises(InputError, match="at least 3"):
        calibrate_camera(two, SIZE)


def test_projector_corners_local_homography_beats_nearest_code() -> None:
    """Decoded maps from a known camera->projector homography with noise, holes and wrong codes."""
    rng = np.random.default_rng(1)
    h, w = 400, 500
    H = np.array([[0.62, 0.05, 40.0], [-0.03, 0.58, 25.0], [2e-5, -1e-5, 1.0]])
    ys, xs = np.mgrid[0:h, 0:w]
    m = cv2.perspectiveTransform(np.stack([xs, ys], -1).reshape(-1, 1, 2).astype(np.float64), H).reshape(
        h, w, 2
    )
    column = (m[..., 0] + rng.normal(0, 0.3, (h, w))).astype(np.float32)
    row = (m[..., 1] + rng.normal(0, 0.3, (h, w))).astype(np.float32)
    # An integer decode (what a plain decoder gives), 10 % wrong codes, 20 % undecoded pixels.
    column, row = np.round(column), np.round(row)
    wrong = rng.random((h, w)) < 0.10
    column[wrong] = rng.uniform(0, 400, wrong.sum())
    holes = rng.random((h, w)) < 0.20
    column[holes] = np.nan
    row[holes] = np.nan
    corners = rng.uniform([60, 60], [w - 60, h - 60], (30, 2))
    truth = cv2.perspectiveTransform(corners.reshape(-1, 1, 2), H).reshape(-1, 2)
    pc = projector_corners(corners, column, row)
    assert pc.valid.all()
    err = np.linalg.norm(pc.points - truth, axis=1)
    plain = np.linalg.norm(nearest_code_corners(corners, column, row) - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.05
    assert np.sqrt(np.nanmean(plain**2)) > 4 * np.sqrt(np.mean(err**2))
    # No decoded pixels around a corner (out of the projector's light): no estimate.
    dark = column.copy()
    dark[:, :200] = np.nan
    pc2 = projector_corners(np.array([[100.0, 200.0], [350.0, 200.0]]), dark, row)
    assert not pc2.valid[0] and pc2.valid[1]


def test_camera_only_charuco_images(tmp_path: Path) -> None:
    """Photos of a ChArUco board by a known camera (no distortion), one without the board."""
    board = parse_board(
        {
            "kind": "charuco",
            "squares": [9, 7],
            "square_size": 30.0,
            "marker_size": 22.0,
            "dictionary": "DICT_5X5_100",
        }
    )
    printed, to_board = board.render(2.5)
    K = np.array([[1500.0, 0.0, 655.0], [0.0, 1500.0, 478.0], [0.0, 0.0, 1.0]])
    size = (1280, 960)
    paths = []
    centre = np.array([4.5 * 30.0, 3.5 * 30.0, 0.0])
    tilts = [
        ((1, 0, 0), 25),
        ((0, 1, 0), 30),
        ((1, 1, 0), -28),
        ((1, -1, 0), 22),
        ((0, 1, 0), -20),
        ((1, 0, 0), -24),
        ((1, 2, 0), 26),
        ((2, -1, 0), -30),
    ]
    for k, (ax, tilt) in enumerate(tilts):
        R = _rotation(np.asarray(ax, float), tilt)
        phi = 2 * np.pi * k / len(tilts)
        t = np.array([70 * np.cos(phi), 50 * np.sin(phi), 700.0 + 15 * k]) - R @ centre
        H = K @ np.column_stack([R[:, 0], R[:, 1], t])
        img = cv2.warpPerspective(printed, H @ to_board, size, flags=cv2.INTER_LINEAR, borderValue=255)
        p = tmp_path / f"img_{k}.png"
        cv2.imwrite(str(p), img)
        paths.append(p)
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((size[1], size[0]), 128, np.uint8))
    result = calibrate_camera_images([*paths, blank], board)
    cal = result.calibration
    assert cal.rms < 0.3
    assert abs(cal.device.fx / 1500.0 - 1) < 0.005 and abs(cal.device.fy / 1500.0 - 1) < 0.005
    assert np.hypot(cal.device.cx - 655.0, cal.device.cy - 478.0) < 4.0
    doc = result.to_json()
    assert [i["used"] for i in doc["images"]] == [True] * len(tilts) + [False]
    assert doc["images"][-1]["reason"] == "board not found"
    # The wrong board: found in none of the images.
    other = parse_board({"kind": "chessboard", "inner_corners": [6, 4], "square_size": 30.0})
    with pytest.raises(InputError, match="board"):
        calibrate_camera_images([blank, blank], other)
    # Mixed image sizes: the odd one is named.
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((480, 640), 128, np.uint8))
    with pytest.raises(InputError, match="small.png"):
        calibrate_camera_images([paths[0], small], board)


# ---------------------------------------------------------------------------------------------
# The real session


def _link_pose(dst: Path, src: Path, frames: dict[int, int] | None = None) -> None:
    """A pose folder of hard links to ``src``'s frames (a symlink out of the folder is refused);
    ``frames`` maps a frame number to the one it shows."""
    dst.mkdir(parents=True)
    srcs = numbered_frames(src)
    for i, f in enumerate(srcs):
        target = srcs[frames.get(i, i)] if frames else f
        place_file(target, dst / f.name)
    write_capture(opencv_order_capture(dst, numbered_frames(dst), 1024, 768))


def make_real_session(
    root: Path,
    poses: dict[str, int],
    board: dict | None = None,
    dark_patterns: tuple[str, ...] = (),
    no_board: tuple[str, ...] = (),
) -> Path:
    """A session over the real captures: pose name -> capture index. ``dark_patterns`` poses show the
    black frame in place of every stripe pattern (projector off); ``no_board`` poses show black everywhere."""
    root.mkdir(parents=True)
    (root / "board.json").write_text(json.dumps(board or REAL_BOARD), encoding="utf-8")
    for name, idx in poses.items():
        frames = None
        if name in dark_patterns:
            frames = {i: 41 for i in range(40)}
        if name in no_board:
            frames = {i: 41 for i in range(42)}
        _link_pose(root / name, REAL / f"capture_{idx}", frames)
    return root


class CachedDecode:
    """Decodes each distinct frame set once per test process (the decoder itself is exercised on first use)."""

    def __init__(self) -> None:
        self.cache: dict[tuple[str, ...], tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, capture: Capture) -> tuple[np.ndarray, np.ndarray]:
        key = tuple(os.path.realpath(p) for p in capture.image_paths())
        if key not in self.cache:
            self.cache[key] = default_decode(capture)
        return self.cache[key]


@pytest.fixture(scope="module")
def decode_cache() -> CachedDecode:
    return CachedDecode()


@pytest.fixture(scope="module")
def real_result(tmp_path_factory: pytest.TempPathFactory, decode_cache: CachedDecode):
    root = make_real_session(
        tmp_path_factory.mktemp("real") / "session", {f"capture_{i}": i for i in range(5)}
    )
    return run_session(root, decode=decode_cache)


@needs_real
@pytest.mark.xdist_group("calibrate_real")
def test_real_session_beats_reference_tool(real_result) -> None:
    cal = real_result.calibration
    assert [p.used for p in cal.poses] == [True] * 5
    assert cal.camera_rms < REFERENCE_CAMERA_RMS, cal.camera_rms
    assert cal.projector_rms < REFERENCE_PROJECTOR_RMS, cal.projector_rms
    # The camera's intrinsics agree with the reference tool's (the data README: reproducible).
    K = cal.rig.camera.K
    assert abs(K[0, 0] / 3452.0 - 1) < 0.01 and abs(K[0, 2] - 587) < 30 and abs(K[1, 2] - 521) < 30
    for p in cal.poses:
        assert p.camera_residuals is not None and len(p.camera_residuals) >= 60
        assert p.camera_rms == pytest.approx(np.sqrt(np.mean(np.sum(p.camera_residuals**2, axis=1))))


@needs_real
@pytest.mark.xdist_group("calibrate_real")
def test_real_board_squares_measure_75_and_lie_on_a_plane(real_result) -> None:
    rig = real_result.calibration.rig
    board = real_result.session.board
    pairs = board.grid_neighbours()
    per_pose_mean = []
    all_rel = []
    for pose in real_result.poses:
        ok = np.isfinite(pose.projector_points).all(axis=1)
        X = np.full((len(ok), 3), np.nan)
        X[ok] = triangulate_corners(rig, pose.camera_points[ok], pose.projector_points[ok])
        d = np.linalg.norm(X[pairs[:, 0]] - X[pairs[:, 1]], axis=1)
        d = d[np.isfinite(d)]
        per_pose_mean.append(d.mean())
        all_rel.append(d / 75.0 - 1)
        # Flat: RMS distance from the best plane under 1 mm over a 600 mm board seen from 3.5 m.
        P = X[ok] - X[ok].mean(axis=0)
        flat_rms = np.linalg.svd(P, compute_uv=False)[-1] / np.sqrt(len(P))
        assert flat_rms < 1.0, (pose.name, flat_rms)
    size_err = np.asarray(per_pose_mean) / 75.0 - 1
    assert np.sqrt(np.mean(size_err**2)) < 0.002, size_err
    # Single squares carry the corner noise of both devices (~0.25 px at 3.5 m, ~0.25 mm).
    assert np.sqrt(np.mean(np.concatenate(all_rel) ** 2)) < 0.004
    check = real_result.board_check()
    assert check["square_rms_error_pct"] == pytest.approx(
        100 * np.sqrt(np.mean(np.concatenate(all_rel) ** 2))
    )


@needs_real
@pytest.mark.xdist_group("calibrate_real")
def test_outputs_rig_yaml_report_plot(tmp_path: Path, real_result) -> None:
    out = tmp_path / "out"
    report = write_outputs(
        real_result,
        rig_path=out / "rig.json",
        report_path=out / "calibration.json",
        yaml_path=out / "calibration.yaml",
        plot_path=out / "residuals.png",
    )
    rig = load_rig(out / "rig.json")
    assert np.allclose(rig.camera.K, real_result.calibration.rig.camera.K)
    assert rig.projector.width == 1024 and rig.camera.width == 1280
    doc = json.loads((out / "calibration.json").read_text())
    assert doc == json.loads(json.dumps(report))
    assert len(doc["poses"]) == 5 and all(
        p["camera_rms_px"] < 1 and p["projector_rms_px"] < 1 for p in doc["poses"]
    )
    assert doc["rms_px"]["camera"] == pytest.approx(real_result.calibration.camera_rms)
    fs = cv2.FileStorage(str(out / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode("camera_matrix").mat(), rig.camera.K)
    assert np.allclose(fs.getNode("projector_distortion").mat().ravel(), rig.projector.dist)
    assert np.allclose(fs.getNode("R").mat(), rig.R) and np.allclose(fs.getNode("T").mat().ravel(), rig.T)
    fs.release()
    png = (out / "residuals.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


@needs_real
@pytest.mark.xdist_group("calibrate_real")
def test_cli_calibrate(tmp_path: Path, real_result, monkeypatch, capsys) -> None:
    """The command's own work: arguments, output names, messages (the session's calibration is the fixture's)."""
    from services.cli.main import main

    seen = []

    def fake_run(path: Path, **kwargs):  # the calibration itself is tested above; this is the CLI layer
        seen.append((path, kwargs.get("k3")))
        return real_result

    monkeypatch.setattr("shared.calib.session.run_session", fake_run)
    out = tmp_path / "cli" / "rig.json"
    yaml = tmp_path / "cli" / "rig.yaml"
    session = real_result.session.root
    assert main(["calibrate", str(session), "--out", str(out), "--export-opencv", str(yaml)]) == 0
    assert main(["calibrate", str(session), "--out", str(tmp_path / "k3" / "rig.json"), "--k3"]) == 0
    assert seen == [(session, False), (session, True)]
    printed = capsys.readouterr().out
    assert "rig from 5 of 5 poses" in printed and str(out) in printed
    assert load_rig(out).baseline > 100
    assert (tmp_path / "cli" / "rig-report.json").is_file() and (
        tmp_path / "cli" / "rig-residuals.png"
    ).is_file()
    assert cv2.FileStorage(str(yaml), cv2.FILE_STORAGE_READ).getNode("projector_matrix").mat().shape == (3, 3)
    # Argument errors: one line, status 1, nothing written.
    assert main(["calibrate", str(session), "--out", str(tmp_path / "rig.txt")]) == 1
    assert main(["calibrate", str(session), str(session), "--out", str(tmp_path / "x.json")]) == 1
    assert main(["calibrate", "--camera-only", "a.png", "--out", str(tmp_path / "c.json")]) == 1
    err = capsys.readouterr().err
    assert "--out" in err and "SESSION_DIR" in err and "--board" in err
    assert not (tmp_path / "x.json").exists() and not (tmp_path / "c.json").exists()


def test_cli_camera_only(tmp_path: Path, capsys) -> None:
    from services.cli.main import main

    board = Board("chessboard", (9, 6), 25.0)
    printed, to_board = board.render(2.5)
    K = np.array([[1400.0, 0.0, 639.5], [0.0, 1400.0, 479.5], [0.0, 0.0, 1.0]])
    paths = []
    for k, (ax, tilt) in enumerate([((1, 0, 0), 25), ((0, 1, 0), 30), ((1, 1, 0), -28), ((1, -1, 0), 22)]):
        R = _rotation(np.asarray(ax, float), tilt)
        t = np.array([0.0, 0.0, 650.0]) - R @ np.array([100.0, 62.5, 0.0])
        H = K @ np.column_stack([R[:, 0], R[:, 1], t])
        p = tmp_path / f"board_{k}.png"
        cv2.imwrite(str(p), cv2.warpPerspective(printed, H @ to_board, (1280, 960), borderValue=255))
        paths.append(str(p))
    (tmp_path / "board.json").write_text(json.dumps(board.to_json()))
    out = tmp_path / "camera.json"
    yaml = tmp_path / "camera.yaml"
    args = ["calibrate", "--camera-only", *paths, "--board", str(tmp_path / "board.json"), "--out", str(out)]
    assert main([*args, "--export-opencv", str(yaml)]) == 0
    doc = json.loads(out.read_text())
    assert abs(doc["camera"]["K"][0][0] / 1400.0 - 1) < 0.01 and doc["rms_px"] < 0.5
    assert len(doc["images"]) == 4 and all(i["used"] for i in doc["images"])
    assert np.allclose(
        cv2.FileStorage(str(yaml), cv2.FILE_STORAGE_READ).getNode("camera_matrix").mat(), doc["camera"]["K"]
    )
    assert "camera from 4 of 4 images" in capsys.readouterr().out
    # k3 is held at exactly 0 unless --k3 frees it.
    assert doc["camera"]["dist"][4] == 0.0
    assert main([*args[:-1], str(tmp_path / "k3.json"), "--k3"]) == 0
    assert json.loads((tmp_path / "k3.json").read_text())["camera"]["dist"][4] != 0.0


@needs_real
@pytest.mark.xdist_group("calibrate_real")
def test_k3_can_be_estimated_on_the_real_session(real_result, decode_cache) -> None:
    free = run_session(real_result.session.root, decode=decode_cache, k3=True).calibration
    held = real_result.calibration
    assert held.rig.camera.dist[4] == 0.0 and held.rig.projector.dist[4] == 0.0
    assert free.rig.camera.dist[4] != 0.0 and free.rig.projector.dist[4] != 0.0
    # One more free parameter: the fit can only come out about as good or better.
    assert free.camera_rms <= held.camera_rms * 1.02 and free.projector_rms <= held.projector_rms * 1.02
    assert abs(free.rig.baseline / held.rig.baseline - 1) < 0.01


# ---------------------------------------------------------------------------------------------
# Bad sessions


@needs_real
@pytest.mark.xdist_group("calibrate_real")
def test_unusable_poses_are_skipped_with_a_warning(tmp_path: Path, decode_cache, caplog) -> None:
    root = make_real_session(
        tmp_path / "s",
        {"a_good": 0, "b_dark": 1, "c_good": 2, "d_noboard": 3, "e_good": 4},
        dark_patterns=("b_dark",),
        no_board=("d_noboard",),
    )
    with caplog.at_level(logging.WARNING):
        result = run_session(root, decode=decode_cache)
    by_name = {p.name: p for p in result.calibration.poses}
    assert [n for n, p in by_name.items() if p.used] == ["a_good", "c_good", "e_good"]
    assert "projector" in by_name["b_dark"].reason and "not found" in by_name["d_noboard"].reason
    messages = " ".join(r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING)
    assert "b_dark" in messages and "d_noboard" in messages
    assert result.calibration.camera_rms < 0.5 and result.calibration.projector_rms < 0.5


@needs_real
@pytest.mark.xdist_group("calibrate_real")
@pytest.mark.parametrize(
    ("poses", "board", "match"),
    [
        ({"p0": 0, "p1": 1}, None, "at least 3"),
        (
            {"p0": 0, "p1": 1, "p2": 2},
            {"kind": "chessboard", "inner_corners": [10, 8], "square_size": 75.0},
            "board.json",
        ),
        ({"p0": 0, "p0_again": 0, "p0_third": 0}, None, "degenerate"),
        ({"p0": 0, "p1": 1, "p2": 2}, {"kind": "chessboard", "inner_corners": [9, 7]}, '"square_size"'),
    ],
    ids=["two-poses", "wrong-board", "one-view-repeated", "bad-board-json"],
)
def test_bad_sessions_fail_cleanly_and_write_no_rig(
    tmp_path: Path, decode_cache: Callable, poses: dict, board: dict | None, match: str
) -> None:
    root = make_real_session(tmp_path / "s", poses, board)
    out = tmp_path / "out"
    with pytest.raises(InputError, match=match) as e:
        calibrate_session(root, out, decode=decode_cache)
    assert "\n" not in str(e.value)
    assert not (out / "rig.json").exists()


def test_session_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        run_session(tmp_path / "missing")
    (tmp_path / "board.json").write_text(json.dumps(REAL_BOARD))
    with pytest.raises(InputError, match="no poses"):
        run_session(tmp_path)


def _synthetic_rig_poses(seed: int, n: int = 8, cam_noise: float = 0.04, proj_noise: float = 0.02):
    """Corners of n board poses seen by a true virtual rig, with detection noise (no rendering)."""
    from shared.calib.calibrate import PoseCorners
    from shared.sim.calibration import random_board_poses
    from shared.sim.simulate import make_rig

    rig = make_rig(seed=seed)
    board = Board("chessboard", (14, 10), 25.0)
    rng = np.random.default_rng(seed)
    out = []
    for p in random_board_poses(rig, board, n, seed=seed, tilt_deg=(20.0, 45.0), distance=(0.95, 1.25)):
        X = board.object_points().astype(np.float64) @ p.R.T + p.t
        cam, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), rig.camera.K, rig.camera.dist)
        prj, _ = cv2.projectPoints(X @ rig.R.T + rig.T, np.zeros(3), np.zeros(3), rig.projector.K, rig.projector.dist)
        out.append(PoseCorners(p.name, board.object_points(),
                               cam.reshape(-1, 2) + rng.normal(0, cam_noise, (len(X), 2)),
                               prj.reshape(-1, 2) + rng.normal(0, proj_noise, (len(X), 2))))
    return rig, out


def test_calibrate_rig_tolerates_bad_pairs_and_a_bad_pose(caplog) -> None:
    from shared.calib.calibrate import PoseCorners, calibrate_rig

    true, poses = _synthetic_rig_poses(seed=5)
    rng = np.random.default_rng(9)
    # A shiny patch: a cluster of corners of one pose decoded several projector pixels off.
    p = poses[2]
    bad = p.projector_points.copy()
    bad[:12] += rng.normal(0, 4.0, (12, 2))
    poses[2] = PoseCorners(p.name, p.object_points, p.camera_points, bad)
    # A pose whose projector corners are all wrong (another pose's decode mixed in, say).
    q = poses[5]
    poses[5] = PoseCorners(q.name, q.object_points, q.camera_points, q.projector_points[::-1].copy())
    with caplog.at_level(logging.WARNING):
        cal = calibrate_rig(poses, (2048, 1536), (1024, 768))
    used = {r.name: r.used for r in cal.poses}
    assert not used[q.name] and used[p.name]
    assert q.name in " ".join(r.getMessage() for r in caplog.records)
    by_name = {r.name: r for r in cal.poses}
    assert by_name[p.name].projector_corners <= len(p.object_points) - 10  # the shiny corners were left out
    rig = cal.rig
    for got, want in ((rig.camera, true.camera), (rig.projector, true.projector)):
        assert abs(got.fx / want.fx - 1) < 0.002 and np.hypot(got.cx - want.cx, got.cy - want.cy) < 2.0
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(rig.R @ true.R.T)[0])) < 0.05
    assert abs(rig.baseline / true.baseline - 1) < 0.003
    assert cal.projector_rms < 0.1


def test_calibrate_rig_is_reproducible() -> None:
    """The same corners give the same rig to the last bit, run after run (OpenCV's solvers
    summed over threads in a varying order: K differed in the 10th digit between runs)."""
    from shared.calib.calibrate import calibrate_rig

    _, poses = _synthetic_rig_poses(seed=3, n=10)
    rigs = [calibrate_rig(poses, (2048, 1536), (1024, 768)).rig for _ in range(4)]
    for rig in rigs[1:]:
        for name in ("camera", "projector"):
            a, b = getattr(rigs[0], name), getattr(rig, name)
            assert a.K.tobytes() == b.K.tobytes() and a.dist.tobytes() == b.dist.tobytes(), name
        assert rig.R.tobytes() == rigs[0].R.tobytes() and rig.T.tobytes() == rigs[0].T.tobytes()
