"""The preview of a merged model draws its textured derivative (shared.render.mesh_preview):
orbiting the turntable axis with that axis up, the whole object framed in every frame.

The object is a textured cylinder in a merge's frame (view 0's camera, y down) whose axis is the
turntable's, tilted as a real rig's is (the bunny's: 19 degrees towards the camera), written as
a Draco GLB by shared.derive's writer: its top half (away from the table) red, its bottom half
blue, by texture alone (the vertices carry no colour). Every frame of the video is read back.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from shared.service.jobs import graph_for
from tests.support.turntable_object import AXIS, write_cylinder_glb

CENTRE = np.array([10.0, -5.0, 900.0])
BG = np.array([18, 18, 24])


def _cylinder(folder: Path) -> Path:
    glb = folder / "mesh_low.glb"
    write_cylinder_glb(glb, CENTRE, (220, 30, 30), (30, 30, 220))
    (folder / "registration.json").write_text(json.dumps(
        {"turntable_axis": {"direction": AXIS.tolist(), "point_mm": CENTRE.tolist()}}))  # fmt: skip
    return glb


def _frames(video: Path, size: tuple[int, int]) -> list[np.ndarray]:
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(video))
    next(gen)  # metadata
    return [np.frombuffer(f, np.uint8).reshape(size[1], size[0], 3) for f in gen]


def test_merged_preview_draws_the_textured_derivative_axis_up_and_framed(tmp_path: Path) -> None:
    from shared.render.options import PreviewOptions
    from shared.render.stages import preview_stage

    _cylinder(tmp_path)
    size = (320, 180)
    t0 = time.perf_counter()
    report = preview_stage(tmp_path / "no-tiles", tmp_path / "out" / "preview.mp4",
                           PreviewOptions(size=size, seconds=1.0, fps=12).checked(), merge_dir=tmp_path,
                           derivatives_dir=tmp_path)  # fmt: skip
    seconds = time.perf_counter() - t0
    assert report["mesh"] == "mesh_low.glb" and report["triangles"] > 1000
    assert report["renderer"].startswith("opengl mesh")
    frames = _frames(tmp_path / "out" / "preview.mp4", size)
    assert len(frames) == report["frames"] == 12
    import cv2

    poster = cv2.imread(str(tmp_path / "out" / "preview.png"))[:, :, ::-1]
    for k, img in enumerate([poster, *frames]):
        rgb = img.astype(int)
        red = (rgb[..., 0] > 120) & (rgb[..., 2] < 90)
        blue = (rgb[..., 2] > 120) & (rgb[..., 0] < 90)
        obj = np.abs(rgb - BG).sum(axis=2) > 40
        assert red.sum() > 200 and blue.sum() > 200, f"frame {k}: both halves visible"
        rows = np.nonzero(obj.any(axis=1))[0]
        cols = np.nonzero(obj.any(axis=0))[0]
        # Axis up: the top half (red) is above the bottom half (blue) on screen, and the
        # cylinder stands upright (its silhouette taller than the disc of a cap would be).
        assert np.nonzero(red)[0].mean() < np.nonzero(blue)[0].mean() - 10, f"frame {k}: upside down"
        red_cols = np.nonzero(red)[1]
        blue_cols = np.nonzero(blue)[1]
        assert abs(red_cols.mean() - blue_cols.mean()) < 0.1 * size[0], f"frame {k}: axis not vertical"
        # Framed: the whole object inside the frame, not touching an edge, and large in it.
        assert rows[0] > 0 and rows[-1] < size[1] - 1 and cols[0] > 0 and cols[-1] < size[0] - 1, f"frame {k}"
        assert rows[-1] - rows[0] > 0.7 * size[1], f"frame {k}: object {rows[-1] - rows[0]} px of {size[1]}"
    print(f"mesh preview {size} 12 frames in {seconds:.1f} s ({report['render_fps']:.1f} frames/s rendered)")


def test_multiview_preview_reads_the_derivatives_only_when_the_job_makes_them() -> None:
    with_derivatives = {s.name: s for s in graph_for("multiview", {})}
    assert with_derivatives["preview"].inputs == ("tiles", "mv_merge", "derivatives")
    without = {s.name: s for s in graph_for("multiview", {"derivatives": False})}
    assert "derivatives" not in without and without["preview"].inputs == ("tiles", "mv_merge")
    assert {s.name: s for s in graph_for("scan", {})}["preview"].inputs == ("tiles",)


@pytest.mark.parametrize("problem", ["not glb", "no triangles"])
def test_a_broken_derivative_is_a_one_line_error_naming_it(tmp_path: Path, problem: str) -> None:
    from shared.core.errors import InputError
    from shared.render.mesh_preview import read_glb

    glb = tmp_path / "mesh_low.glb"
    if problem == "not glb":
        glb.write_bytes(b"PK\x03\x04 a zip, not a glTF")
    else:
        js = json.dumps({"asset": {"version": "2.0"}, "meshes": [{"primitives": [{"mode": 1, "attributes": {}}]}]})
        body = js.encode() + b" " * (-len(js) % 4)
        glb.write_bytes(b"glTF" + (2).to_bytes(4, "little") + (20 + len(body)).to_bytes(4, "little")
                        + len(body).to_bytes(4, "little") + b"JSON" + body)  # fmt: skip
    with pytest.raises(InputError) as err:
        read_glb(glb)
    assert "mesh_low.glb" in str(err.value) and "\n" not in str(err.value)


def test_the_preview_stage_adapter_reads_the_merge_and_the_derivatives_when_given(tmp_path: Path) -> None:
    """workers.stages.run_preview: a multi-view job's inputs (tiles, mv_merge, derivatives) give
    the textured preview; without the derivatives input it renders the tiles' points."""
    from shared.render.octree import build_tiles
    from tests.support.turntable_object import write_cylinder_cloud
    from workers.stages import StageContext, run_preview

    merge, derived = tmp_path / "mv_merge", tmp_path / "derivatives"
    derived.mkdir()
    merge.mkdir()
    write_cylinder_glb(derived / "mesh_low.glb", CENTRE, (220, 30, 30), (30, 30, 220))
    (merge / "registration.json").write_text(json.dumps({"turntable_axis": {"direction": AXIS.tolist()}}))
    write_cylinder_cloud(tmp_path / "merged.ply", CENTRE, (220, 30, 30), (30, 30, 220), n=20_000)
    build_tiles(tmp_path / "merged.ply", tmp_path / "tiles", workers=1)
    params = {"preview": {"size": [160, 90], "seconds": 0.25, "fps": 8}}
    inputs = {"tiles": tmp_path / "tiles", "mv_merge": merge, "derivatives": derived}
    textured = run_preview(StageContext("j", "multiview", "preview", params, None, inputs, tmp_path / "a"))
    assert textured["mesh"] == "mesh_low.glb" and textured["up"] == [round(float(v), 6) for v in -AXIS]
    del inputs["derivatives"]
    points = run_preview(StageContext("j", "multiview", "preview", params, None, inputs, tmp_path / "b"))
    assert "mesh" not in points and points["points"] > 0
