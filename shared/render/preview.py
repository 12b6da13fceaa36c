"""Preview flythrough videos of Potree tiles, rendered headlessly and encoded to H.264 MP4.

In: a tiles folder (:mod:`shared.render.octree` output), a camera path ("orbit", "dolly" or a JSON
keyframe file, :mod:`shared.render.camera_path`), a frame size, duration and rate. Out: an MP4
(H.264, yuv420p, via the ffmpeg that ships with imageio-ffmpeg) and a poster PNG beside it
(same name, ``.png``), both written under temporary names and renamed when complete.

Per frame the octree nodes are chosen by projected size under a point budget
(:func:`shared.render.raster.select_nodes`) and drawn by the CPU software rasteriser (or by
OpenGL through moderngl when a hardware GPU is present: Mesa's llvmpipe is far slower than
the CPU rasteriser, so it is never picked automatically); nodes drawn
without all their children get splats at least as wide as their spacing, so coarse levels
close up as well. Encoding runs in ffmpeg's own process, overlapping the rendering.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from shared.compress import tilenode
from shared.core.errors import InputError
from shared.formats.potree import PotreeTiles, open_tiles, tight_bounds
from shared.render._shading import shade_kernel
from shared.render.camera_path import DEFAULT_UP, SCANNER, CameraPose, KeyframePath, make_path
from shared.render.mesh_preview import MeshRenderer, read_glb
from shared.render.options import PREVIEW_DEFAULTS, PreviewOptions
from shared.render.raster import Camera, GLRasterizer, NodeTable, Rasterizer, select_nodes

log = logging.getLogger(__name__)

#: Points drawn a frame: 1.5 M covers a 1280x720 frame about 1.6 times over.
DEFAULT_BUDGET = 1_500_000
#: Points held in memory for a preview; deeper nodes of a bigger cloud are left out.
MAX_LOADED = 40_000_000
BACKGROUND = (18, 18, 24)
#: Points the camera path frames (the coarse levels' sample of the object).
FRAMING_POINTS = 60_000
#: Eye-dome lighting strength of the CPU renderer's frames of a cloud without normals
#: (:func:`shared.render.raster.Rasterizer.render` sums four neighbours: 0.25 is Potree's EDL
#: at strength 1, which averages them): outlines and depth steps darken, so an object reads as
#: a shape. Clouds with normals are lit by them instead (:func:`shade_colours`), on the CPU
#: and in OpenGL alike.
DEFAULT_EDL = 0.25
#: Light a surface facing away from the key light still gets (of its colour).
AMBIENT = 0.35


@dataclass
class LoadedScene:
    """Points of the loaded nodes in one set of arrays, node after node (breadth-first).

    ``xyz`` (N, 3) float32 relative to ``origin`` (3,) float64; ``colour`` (N,) uint32
    0x00BBGGRR; ``size`` (N,) float32; ``ranges`` (M, 2) int64 per node; ``table`` for
    node selection; ``names`` the nodes' Potree names.
    """

    origin: np.ndarray
    xyz: np.ndarray
    colour: np.ndarray
    size: np.ndarray
    ranges: np.ndarray
    table: NodeTable
    names: list[str]
    bounds_min: np.ndarray
    bounds_max: np.ndarray
    lit: bool = False  # colours shaded by the normals (:func:`shade_colours`)

    @property
    def points(self) -> int:
        return int(self.xyz.shape[0])


def shade_colours(colour: np.ndarray, normal: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Colours (N,) packed 0x00BBGGRR lit by a distant light along ``light`` (3,) unit:
    ``AMBIENT + (1 - AMBIENT) * |n . light|`` (two-sided: a normal's sign is not trusted).
    Points whose normal is zero (none estimated) keep their colour. ``normal`` (N, 3) float32."""
    out = np.empty(colour.shape[0], np.uint32)
    shade_kernel(np.ascontiguousarray(colour, np.uint32), np.asarray(normal, np.float32),
                 np.asarray(light, np.float32), np.float32(AMBIENT), out)  # fmt: skip
    return out


def key_light(centre: np.ndarray, viewpoint=SCANNER, up=DEFAULT_UP) -> np.ndarray:
    """Unit direction towards the key light: from the object towards the scanner, raised by
    about 30 degrees and moved a little to the side, as a photographer's key light."""
    home = np.asarray(viewpoint, np.float64) - np.asarray(centre, np.float64)
    home = home / np.linalg.norm(home) if np.linalg.norm(home) > 0 else np.array([0.0, 0.0, -1.0])
    up = np.asarray(up, np.float64)
    side = np.cross(up, home)
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 0 else np.zeros(3)
    d = home + 0.6 * up + 0.35 * side
    return d / np.linalg.norm(d)


def load_scene(tiles: PotreeTiles, max_points: int = MAX_LOADED, shade: bool = True) -> LoadedScene:
    """Decode nodes breadth-first until ``max_points`` would be exceeded (children of
    skipped nodes are skipped too). With ``shade`` and normals in the tiles, colours are lit
    by :func:`key_light` (:func:`shade_colours`) so that a grey object shows its shape."""
    chosen = []
    total = 0
    loaded: set[str] = set()
    for name, node in tiles.nodes.items():
        if name != "r" and name[:-1] not in loaded:
            continue
        if total + node.num_points > max_points:
            continue
        chosen.append(node)
        loaded.add(name)
        total += node.num_points
    if total == 0:
        raise InputError(tiles.root, "the tiles hold no points")
    lo, hi = tight_bounds(tiles)
    origin = (lo + hi) / 2
    light = key_light(origin)
    lit = shade and {"NormalX", "NormalY", "NormalZ"} <= set(tiles.point_dtype.names or ())
    xyz = np.empty((total, 3), np.float32)
    colour = np.empty(total, np.uint32)
    size = np.zeros(total, np.float32)
    ranges = np.empty((len(chosen), 2), np.int64)
    shift = (tiles.offset - origin).astype(np.float64)
    mm = np.memmap(tiles.root / "octree.bin", dtype=np.uint8, mode="r")
    item = tiles.point_dtype.itemsize
    names_in = tiles.point_dtype.names or ()
    pos = 0
    for j, node in enumerate(chosen):
        n = node.num_points
        if tiles.decoder is not None:  # coded nodes (tiles opened with their decoder)
            rec = tiles.records(node.name)
        elif node.byte_offset + n * item > mm.size or node.byte_size != n * item:
            raise InputError(tiles.root / "octree.bin", f"node {node.name} lies outside the file")
        else:
            rec = np.frombuffer(mm[node.byte_offset : node.byte_offset + n * item], tiles.point_dtype)
        xyz[pos : pos + n] = rec["position"] * tiles.scale + shift
        if "rgb" in names_in:
            c = rec["rgb"].astype(np.uint32)
            c = np.where(c > 255, c >> 8, c)
            colour[pos : pos + n] = c[:, 0] | (c[:, 1] << 8) | (c[:, 2] << 16)
        else:
            colour[pos : pos + n] = 0xFFFFFF
        if "size" in names_in:
            size[pos : pos + n] = rec["size"]
        if lit:
            normal = np.stack([rec["NormalX"], rec["NormalY"], rec["NormalZ"]], axis=1)
            colour[pos : pos + n] = shade_colours(colour[pos : pos + n], normal, light)
        ranges[j] = pos, pos + n
        pos += n
    index = {node.name: j for j, node in enumerate(chosen)}
    centre = np.stack([(nd.box_min + nd.box_max) / 2 - origin for nd in chosen])
    radius = np.array([np.linalg.norm(nd.box_max - nd.box_min) / 2 for nd in chosen])
    parent = np.array([index.get(nd.name[:-1], -1) if nd.name != "r" else -1 for nd in chosen])
    table = NodeTable(
        center=centre,
        radius=radius,
        parent=parent,
        points=np.array([nd.num_points for nd in chosen], np.int64),
        spacing=np.array([nd.spacing for nd in chosen]),
    )
    return LoadedScene(origin=origin, xyz=xyz, colour=colour, size=size, ranges=ranges, table=table,
                       names=[nd.name for nd in chosen], bounds_min=lo, bounds_max=hi, lit=lit)  # fmt: skip


def frame_sample(scene: LoadedScene, points: int = FRAMING_POINTS) -> np.ndarray:
    """(M, 3) float64 world positions for framing the camera path: the first ``points`` of the
    loaded nodes, breadth first, so the coarse levels' even grid sample of the whole object."""
    return scene.xyz[: min(points, scene.points)].astype(np.float64) + scene.origin


def frame_camera(pose: CameraPose, scene: LoadedScene, width: int, height: int) -> Camera:
    """The rasteriser camera of a pose (moved into the scene's local frame)."""
    diag = float(np.linalg.norm(scene.bounds_max - scene.bounds_min)) or 1.0
    return Camera.look_at(pose.eye - scene.origin, pose.target - scene.origin, pose.up, pose.fov_y,
                          width, height, near=diag * 1e-4)  # fmt: skip


def frame_selection(scene: LoadedScene, camera: Camera, budget: int) -> tuple[np.ndarray, np.ndarray]:
    """Ranges and per-range smallest splat size for one frame (see module docstring)."""
    chosen, visible = select_nodes(scene.table, camera, budget)
    picked = np.zeros(len(scene.names), bool)
    picked[chosen] = True
    min_size = np.zeros(chosen.size, np.float32)
    for k, i in enumerate(chosen):
        # A visible child left out (budget) leaves gaps of about this node's spacing.
        if any(visible[c] and not picked[c] for c in scene.table.children[i]):
            min_size[k] = scene.table.spacing[i]
    return scene.ranges[chosen], min_size


def hardware_gl(width: int, height: int) -> GLRasterizer | None:
    """An OpenGL rasteriser when a real GPU drives it, else None (Mesa's llvmpipe draws
    points several times slower than the CPU rasteriser, so it is never chosen)."""
    if not any(Path("/dev/dri").glob("renderD*")):  # no GPU render node: do not even probe EGL
        return None
    try:
        gl = GLRasterizer(width, height)
    except Exception as exc:  # no EGL, no driver: the CPU path is the normal case
        log.info("no OpenGL context (%s); rendering on the CPU", exc)
        return None
    if gl.hardware:
        log.info("rendering with OpenGL on %s", gl.renderer)
        return gl
    gl.release()
    return None


def render_frames(
    scene: LoadedScene,
    poses: list[CameraPose],
    width: int,
    height: int,
    budget: int = DEFAULT_BUDGET,
    edl: float = 0.0,
    gl: GLRasterizer | None = None,
):
    """Yield (rgb (H, W, 3) uint8, points drawn) for every pose, with the CPU rasteriser or,
    when ``gl`` is given, with OpenGL (the caller releases it)."""
    far = 1e3 * float(np.linalg.norm(scene.bounds_max - scene.bounds_min) or 1.0)
    if gl is not None:
        gl.upload(scene.xyz, scene.colour, scene.size)
        for pose in poses:
            cam = frame_camera(pose, scene, width, height)
            ranges, min_size = frame_selection(scene, cam, budget)
            yield gl.render(cam, ranges, min_size, far, BACKGROUND), int((ranges[:, 1] - ranges[:, 0]).sum())
        return
    # CPU: a batch of frames at once, one a thread.
    rz = Rasterizer(width, height)
    for start in range(0, len(poses), rz.threads):
        cams = [frame_camera(p, scene, width, height) for p in poses[start : start + rz.threads]]
        sel = [frame_selection(scene, c, budget) for c in cams]
        frames = rz.render_batch(cams, scene.xyz, scene.colour, scene.size, [r for r, _ in sel],
                                 [m for _, m in sel], BACKGROUND, edl)  # fmt: skip
        for frame, (ranges, _) in zip(frames, sel, strict=True):
            yield frame.rgb, int((ranges[:, 1] - ranges[:, 0]).sum())


def check_video_args(size: tuple[int, int], seconds: float, fps: float) -> tuple[int, int, int]:
    """Validate the video request; returns (width, height, frames). InputError names the field."""
    opts = PreviewOptions(size=size, seconds=seconds, fps=fps).checked()
    return opts.size[0], opts.size[1], opts.frames


def render_preview(
    tiles_dir: Path,
    out_path: Path,
    *,
    path: str | Path = PREVIEW_DEFAULTS.path,
    size: tuple[int, int] = PREVIEW_DEFAULTS.size,
    seconds: float = PREVIEW_DEFAULTS.seconds,
    fps: float = PREVIEW_DEFAULTS.fps,
    budget: int = DEFAULT_BUDGET,
    edl: float | None = None,
    renderer: str = "auto",
    progress: Callable[[float], None] | None = None,
    camera: KeyframePath | None = None,
    camera_where: str = "params.preview.camera",
    mesh: Path | None = None,
    up: np.ndarray | None = None,
) -> dict:
    """Render a flythrough of ``tiles_dir`` to ``out_path`` (MP4) and its poster PNG.

    ``camera`` (validated keyframes) wins over ``path``; its errors name ``camera_where``.
    ``mesh``: a textured derivative GLB of the same object (:mod:`shared.render.mesh_preview`)
    drawn as triangles with OpenGL instead of the tiles' points; ``up`` (3,) the object's up
    (the turntable axis), which the orbit turns around and keeps up on screen (default: -y,
    view 0's image up). The mesh's path is the orbit unless ``path`` or ``camera`` says otherwise.

    ``renderer`` is "auto" (OpenGL when a hardware GPU is there, else the CPU rasteriser),
    "cpu" or "gl". ``edl``: eye-dome lighting strength of the CPU frames (None: 0 when the
    tiles' normals light the colours, else :data:`DEFAULT_EDL`; OpenGL frames have none).
    ``progress`` is called with the fraction of frames written. Returns a report: video, poster, frames, width, height, fps, seconds,
    points (loaded), mean_points_per_frame, render_seconds, render_fps, elapsed_seconds.
    """
    t0 = time.perf_counter()
    width, height, frames = check_video_args(size, seconds, fps)
    if budget < 1:
        raise InputError("budget", f"must be at least 1 point, got {budget}")
    if renderer not in ("auto", "cpu", "gl"):
        raise InputError("renderer", f"must be auto, cpu or gl, got {renderer!r}")
    out_path = Path(out_path)
    up = np.asarray(DEFAULT_UP if up is None else up, np.float64)
    if mesh is not None:
        return _render_mesh_preview(Path(mesh), out_path, str(path), width, height, frames, fps, up, progress, camera,
                                    camera_where, t0)  # fmt: skip
    tiles = open_tiles(Path(tiles_dir), decoders=tilenode.DECODERS)  # plain or octree-coded nodes
    scene = load_scene(tiles)
    if edl is None:  # shading: the normals when the tiles have them, else eye-dome lighting
        edl = 0.0 if scene.lit else DEFAULT_EDL
    poses = make_path(path, scene.bounds_min, scene.bounds_max, frames, points=frame_sample(scene),
                      aspect=width / height, camera=camera, camera_where=camera_where, up=up)  # fmt: skip
    gl = None
    if renderer == "gl":
        gl = GLRasterizer(width, height)
    elif renderer == "auto":
        gl = hardware_gl(width, height)
    used = "cpu" if gl is None else f"opengl: {gl.renderer}"
    try:
        drawn, render_s = encode_frames(render_frames(scene, poses, width, height, budget, edl, gl), out_path,
                                        width, height, frames, fps, progress)  # fmt: skip
    finally:
        if gl is not None:
            gl.release()
    return {
        "video": str(out_path),
        "poster": str(out_path.with_suffix(".png")),
        "frames": frames,
        "width": width,
        "height": height,
        "fps": fps,
        "seconds": frames / fps,
        "points": scene.points,
        "renderer": used,
        "mean_points_per_frame": drawn / frames,
        "render_seconds": render_s,
        "render_fps": frames / render_s if render_s > 0 else 0.0,
        "elapsed_seconds": time.perf_counter() - t0,
    }


def encode_frames(it, out_path: Path, width: int, height: int, frames: int, fps: float,
                  progress: Callable[[float], None] | None) -> tuple[int, float]:
    """Encode ``frames`` (rgb (H, W, 3) uint8, count drawn) pairs of ``it`` to ``out_path``
    (H.264 MP4) and the first as its poster PNG, both under temporary names renamed when
    complete; returns (total drawn, seconds spent rendering)."""
    import imageio_ffmpeg

    out_path.parent.mkdir(parents=True, exist_ok=True)
    poster_path = out_path.with_suffix(".png")
    tmp_video = out_path.with_name(f".{out_path.stem}.{os.getpid()}.tmp.mp4")
    tmp_poster = out_path.with_name(f".{out_path.stem}.{os.getpid()}.tmp.png")
    render_s = 0.0
    drawn = 0
    try:
        writer = imageio_ffmpeg.write_frames(
            str(tmp_video), (width, height), fps=fps, codec="libx264", pix_fmt_in="rgb24",
            pix_fmt_out="yuv420p", macro_block_size=1, quality=None, ffmpeg_log_level="error",
            output_params=["-preset", "veryfast", "-crf", "23", "-movflags", "+faststart"],
        )  # fmt: skip
        writer.send(None)
        try:
            for k in range(frames):
                t1 = time.perf_counter()
                rgb, n = next(it)
                render_s += time.perf_counter() - t1
                drawn += n
                if k == 0:
                    if not cv2.imwrite(str(tmp_poster), rgb[:, :, ::-1]):
                        raise OSError(f"could not write {tmp_poster}")
                writer.send(np.ascontiguousarray(rgb))
                if progress is not None:
                    progress((k + 1) / frames)
        finally:
            it.close()
            writer.close()
        os.replace(tmp_video, out_path)
        os.replace(tmp_poster, poster_path)
    except BaseException:
        tmp_video.unlink(missing_ok=True)
        tmp_poster.unlink(missing_ok=True)
        raise
    return drawn, render_s


def _render_mesh_preview(glb: Path, out_path: Path, path: str, width: int, height: int, frames: int, fps: float,
                         up: np.ndarray, progress, camera: KeyframePath | None, camera_where: str, t0: float) -> dict:
    """:func:`render_preview` of a textured mesh (see there)."""
    tm = read_glb(glb)
    lo, hi = tm.vertices.min(axis=0), tm.vertices.max(axis=0)
    sample = tm.vertices[:: max(1, len(tm.vertices) // FRAMING_POINTS)]
    # "auto" is the orbit: a derivative is of a merged model, seen from all around.
    poses = make_path("orbit" if path == "auto" else path, lo, hi, frames, points=sample, aspect=width / height,
                      camera=camera, camera_where=camera_where, up=up)  # fmt: skip
    mr = MeshRenderer(tm, width, height)
    try:
        _, render_s = encode_frames(((rgb, 0) for rgb in mr.frames(poses)), out_path, width, height, frames, fps,
                                    progress)  # fmt: skip
    finally:
        mr.release()
    return {
        "video": str(out_path), "poster": str(out_path.with_suffix(".png")), "frames": frames, "width": width,
        "height": height, "fps": fps, "seconds": frames / fps, "points": 0, "mesh": glb.name,
        "triangles": int(len(tm.faces)), "up": [round(float(v), 6) for v in up], "renderer": f"opengl mesh: {mr.renderer}",
        "mean_points_per_frame": 0.0, "render_seconds": render_s, "render_fps": frames / render_s if render_s > 0 else 0.0,
        "elapsed_seconds": time.perf_counter() - t0,
    }
