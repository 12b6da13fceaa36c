"""Preview videos: frame count, size, duration, non-blank frames, poster; camera paths; bad
input leaves no finished-looking artifact; the render stages and CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.ply import read_header
from shared.render.camera_path import dolly_path, load_path_file, orbit_path
from shared.render.octree import build_tiles
from shared.render.options import PreviewOptions
from shared.render.preview import BACKGROUND, render_preview
from shared.render.stages import preview_stage, tiles_stage
from tests.support.clouds import synthetic_scan

# One worker builds the module's tiles once and runs every test on them.
pytestmark = pytest.mark.xdist_group("preview")


@pytest.fixture(scope="module")
def tiles(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("preview")
    cloud = synthetic_scan(folder / "scan.ply", 30_000, seed=7)
    out = folder / "tiles"
    build_tiles(cloud, out, workers=1, max_leaf=2_000)
    return out


def _read_video(path: Path) -> tuple[dict, list[np.ndarray]]:
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in gen]
    return meta, frames


def test_video_has_the_asked_frames_size_and_duration(tiles: Path, tmp_path: Path) -> None:
    out = tmp_path / "v" / "preview.mp4"
    report = render_preview(tiles, out, size=(192, 108), seconds=1.5, fps=16)
    meta, frames = _read_video(out)
    assert len(frames) == report["frames"] == 24
    assert meta["size"] == (192, 108)
    assert meta["codec"] == "h264"
    assert meta["fps"] == pytest.approx(16)
    assert meta["duration"] == pytest.approx(1.5, abs=0.07)
    bg = np.array(BACKGROUND, float)
    for f in frames:
        covered = np.abs(f.astype(float) - bg).sum(axis=2) > 30
        assert covered.mean() > 0.05  # the scene is on screen in every frame
        assert f.std() > 10
    # An orbit turns: first and middle frames differ.
    assert np.abs(frames[0].astype(int) - frames[12].astype(int)).mean() > 5
    poster = cv2.imread(str(out.with_suffix(".png")))
    assert poster is not None and poster.shape == (108, 192, 3)
    assert sorted(p.name for p in out.parent.iterdir()) == ["preview.mp4", "preview.png"]


def test_dolly_and_keyframe_file(tiles: Path, tmp_path: Path) -> None:
    meta = json.loads((tiles / "metadata.json").read_text())
    pos = meta["attributes"][0]
    lo, hi = np.array(pos["min"]), np.array(pos["max"])
    c = (lo + hi) / 2
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"fov": 60, "keyframes": [
        {"eye": (c - [0, 0, 3000]).tolist(), "target": c.tolist()},
        {"eye": (c - [500, 0, 2000]).tolist(), "target": c.tolist()}]}))  # fmt: skip
    for spec in ("dolly", str(path)):
        out = tmp_path / f"{Path(spec).stem}.mp4"
        report = render_preview(tiles, out, path=spec, size=(128, 96), seconds=0.5, fps=10)
        _, frames = _read_video(out)
        assert len(frames) == report["frames"] == 5
        assert max(f.std() for f in frames) > 10


def test_camera_paths() -> None:
    lo, hi = np.array([-100.0, -50, 400]), np.array([100.0, 50, 900])
    c = (lo + hi) / 2
    orbit = orbit_path(lo, hi, 12)
    d = [np.linalg.norm(p.eye - c) for p in orbit]
    assert np.allclose(d, d[0]) and d[0] > np.linalg.norm(hi - lo) / 2
    assert orbit[0].eye[2] < lo[2]  # starts on the scanner's side
    assert np.linalg.norm(orbit[6].eye - orbit[0].eye) > d[0]  # half a turn later: opposite side
    dolly = dolly_path(lo, hi, 10)
    z = [p.eye[2] for p in dolly]
    assert np.all(np.diff(z) > 0) and z[0] < lo[2] and lo[2] < z[-1] <= hi[2]


@pytest.mark.parametrize(
    "doc, needle",
    [
        ({"keyframes": [{"eye": [0, 0, -1e7], "target": [0, 0, 600]}]}, "outside the scene"),
        ({"keyframes": []}, "keyframes"),
        ({"keyframes": [{"eye": [0, 0], "target": [0, 0, 1]}]}, "eye"),
        ({"keyframes": [{"eye": [0, 0, 0], "target": [0, 0, 1]}], "fov": 500}, "fov"),
    ],
)
def test_bad_path_files(tmp_path: Path, doc: dict, needle: str) -> None:
    path = tmp_path / "p.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        load_path_file(path, 10, [-100, -100, 400], [100, 100, 900])
    assert needle in str(err.value) and "p.json" in str(err.value)


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"size": (7680, 4320)}, "too large"),
        ({"size": (129, 96)}, "even"),
        ({"seconds": 0}, "seconds"),
        ({"fps": 1000}, "fps"),
        ({"path": "FILE"}, "outside the scene"),
    ],
)
def test_bad_preview_requests_leave_nothing(tiles: Path, tmp_path: Path, kwargs: dict, needle: str) -> None:
    if kwargs.get("path") == "FILE":
        far = tmp_path / "far.json"
        far.write_text(json.dumps({"keyframes": [{"eye": [0, 0, -1e8], "target": [0, 0, 1000]}]}))
        kwargs = {"path": str(far)}
    out = tmp_path / "out" / "p.mp4"
    with pytest.raises(InputError) as err:
        render_preview(tiles, out, **{"seconds": 0.2, "fps": 10, "size": (64, 48), **kwargs})
    assert needle in str(err.value)
    assert not out.exists() and not out.with_suffix(".png").exists()
    assert not out.parent.exists() or list(out.parent.iterdir()) == []


def test_missing_tiles_is_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="metadata.json"):
        render_preview(tmp_path / "nope", tmp_path / "p.mp4", seconds=0.2, fps=10, size=(64, 48))


def test_stages_and_cli(tmp_path: Path) -> None:
    from services.cli.main import main as cli_main

    cloud = synthetic_scan(tmp_path / "c.ply", 8_000, seed=1)
    rep = tiles_stage(cloud, tmp_path / "t", workers=1)
    assert rep["points"] == read_header(cloud).count
    rep = preview_stage(tmp_path / "t", tmp_path / "p.mp4", PreviewOptions(size=(64, 48), seconds=0.5, fps=8))
    assert rep["frames"] == 4 and Path(rep["poster"]).is_file()
    assert cli_main(["tiles", str(cloud), "--out", str(tmp_path / "t2"), "--workers", "1"]) == 0
    assert (tmp_path / "t2" / "octree.bin").is_file()
    assert cli_main(["preview", str(tmp_path / "t2"), "--out", str(tmp_path / "q.mp4"), "--size", "64x48",
                     "--seconds", "0.5", "--fps", "8"]) == 0  # fmt: skip
    assert cli_main(["preview", str(tmp_path / "t2"), "--out", str(tmp_path / "r.mp4"), "--size", "big"]) == 1
    assert not (tmp_path / "r.mp4").exists()


def test_opengl_renderer_makes_the_same_video(tiles: Path, tmp_path: Path) -> None:
    from shared.render.raster import GLRasterizer

    try:
        GLRasterizer(16, 16).release()
    except Exception as exc:
        pytest.fail(f"no OpenGL context ({exc!r}): make setup installs libegl1 and libgl1-mesa-dri")
    kw = {"size": (128, 96), "seconds": 0.4, "fps": 10, "path": "dolly"}
    rep_gl = render_preview(tiles, tmp_path / "gl.mp4", renderer="gl", **kw)
    rep_cpu = render_preview(tiles, tmp_path / "cpu.mp4", renderer="cpu", **kw)
    assert rep_gl["renderer"].startswith("opengl") and rep_cpu["renderer"] == "cpu"
    _, a = _read_video(tmp_path / "gl.mp4")
    _, b = _read_video(tmp_path / "cpu.mp4")
    assert len(a) == len(b) == 4
    for x, y in zip(a, b, strict=True):
        assert np.abs(x.astype(int) - y.astype(int)).mean() < 12


def test_unknown_renderer_is_input_error(tiles: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="renderer"):
        render_preview(tiles, tmp_path / "x.mp4", size=(64, 48), seconds=0.2, fps=10, renderer="vulkan")
    assert list(tmp_path.iterdir()) == []
