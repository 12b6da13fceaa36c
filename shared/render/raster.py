"""CPU software point rasteriser (the compute-style splatting of Schütz, Kerbl and Wimmer 2021).

In: points as float32 positions (N, 3) in a local world frame, packed 0x00BBGGRR colours
(N,) uint32 and world sample sizes (N,) float32, grouped into ranges (octree nodes, points in
Morton order inside each); a pinhole :class:`Camera` (OpenCV convention: x right, y down,
z forward; pixel centres at integer coordinates). Out: an (H, W, 3) uint8 RGB image.

Each point is projected once and written with a 64-bit min of ``depth_bits << 32 | colour``
into a per-pixel buffer (positive float32 depths order like their bit patterns), so the
nearest point wins in a single pass with no sorting. Splats are squares whose side in pixels
is the seed's H_v = (F_v / F_s) * (Z_s / Z_v) = fx * size / z (times :data:`SPLAT_SCALE`), so a scan's surface closes
without holes whatever the distance. Threads each fill their own buffer over a share of the
ranges (no write races), and the buffers are merged by the same min.

Also here: :func:`select_nodes`, the per-frame choice of octree nodes by projected size under
a point budget (Potree's rule), and :class:`GLRasterizer`, the same splats as OpenGL points
through moderngl, for machines with a GPU (and the bench's llvmpipe peer).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numba
import numpy as np

EMPTY = np.uint64(0xFFFFFFFFFFFFFFFF)
#: Largest splat half-side in pixels (a splat right in front of the lens stays bounded).
MAX_HALF = 12.0
#: Splats are drawn this much wider than the seed's H_v so that neighbours overlap.
SPLAT_SCALE = 1.25


@dataclass(frozen=True)
class Camera:
    """Pinhole camera. ``R`` (3, 3) and ``t`` (3,) map world to camera: X_c = R @ X_w + t."""

    R: np.ndarray
    t: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 1e-3

    @classmethod
    def look_at(
        cls,
        eye: np.ndarray,
        target: np.ndarray,
        up: np.ndarray,
        fov_y_deg: float,
        width: int,
        height: int,
        near: float = 1e-3,
    ) -> Camera:
        """Camera at ``eye`` looking at ``target``; ``up`` is the world direction drawn upwards."""
        eye = np.asarray(eye, np.float64)
        fwd = np.asarray(target, np.float64) - eye
        n = np.linalg.norm(fwd)
        if n == 0:
            raise ValueError("camera eye and target coincide")
        fwd /= n
        up = np.asarray(up, np.float64)
        right = np.cross(-up, fwd)  # image x; image y points down, against ``up``
        if np.linalg.norm(right) < 1e-9:
            right = np.cross(fwd, [1.0, 0.0, 0.0] if abs(fwd[0]) < 0.9 else [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])
        f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
        return cls(R=R, t=-R @ eye, fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2,
                   width=int(width), height=int(height), near=near)  # fmt: skip

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def eye(self) -> np.ndarray:
        return -self.R.T @ self.t


def pack_colours(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB -> (N,) uint32 0x00BBGGRR."""
    rgb = rgb.astype(np.uint32)
    return rgb[:, 0] | (rgb[:, 1] << 8) | (rgb[:, 2] << 16)


@numba.njit(parallel=True, cache=True, fastmath=True)
def _splat(xyz, colour, size, starts, stops, min_size, task_bounds, Rts, Ks, buffers):
    """Task t draws ranges task_bounds[t]:task_bounds[t+1] with camera Rts[t] (3, 4),
    Ks[t] = (fx, fy, cx, cy, near) into buffers[t]: one frame split over threads, or one
    frame a thread."""
    width = buffers.shape[2]
    height = buffers.shape[1]
    ntasks = task_bounds.shape[0] - 1
    for task in numba.prange(ntasks):
        buf = buffers[task]
        Rt = Rts[task]
        fx = Ks[task, 0]
        fy = Ks[task, 1]
        cx = Ks[task, 2]
        cy = Ks[task, 3]
        near = Ks[task, 4]
        for r in range(task_bounds[task], task_bounds[task + 1]):
            ms = min_size[r]
            for i in range(starts[r], stops[r]):
                x = xyz[i, 0]
                y = xyz[i, 1]
                z = xyz[i, 2]
                zc = Rt[2, 0] * x + Rt[2, 1] * y + Rt[2, 2] * z + Rt[2, 3]
                if zc <= near:
                    continue
                xc = Rt[0, 0] * x + Rt[0, 1] * y + Rt[0, 2] * z + Rt[0, 3]
                yc = Rt[1, 0] * x + Rt[1, 1] * y + Rt[1, 2] * z + Rt[1, 3]
                inv = 1.0 / zc
                u = fx * xc * inv + cx
                v = fy * yc * inv + cy
                # Seed sizing: side in pixels = fx * world size / depth, a little enlarged so
                # neighbours overlap; the splat covers the pixel centres within half a side.
                half = min(max(size[i], ms) * fx * inv * (0.5 * SPLAT_SCALE), MAX_HALF)
                if not (-half - 1 < u < width + half and -half - 1 < v < height + half):
                    continue
                d = np.float32(zc)
                key = (np.uint64(d.view(np.uint32)) << np.uint64(32)) | np.uint64(colour[i])
                if half < 0.5:
                    ui = np.int64(math.floor(u + 0.5))
                    vi = np.int64(math.floor(v + 0.5))
                    if 0 <= ui < width and 0 <= vi < height and key < buf[vi, ui]:
                        buf[vi, ui] = key
                    continue
                x0 = max(np.int64(math.ceil(u - half)), 0)
                x1 = min(np.int64(math.floor(u + half)), width - 1)
                y0 = max(np.int64(math.ceil(v - half)), 0)
                y1 = min(np.int64(math.floor(v + half)), height - 1)
                for yy in range(y0, y1 + 1):
                    for xx in range(x0, x1 + 1):
                        if key < buf[yy, xx]:
                            buf[yy, xx] = key


@numba.njit(parallel=True, cache=True)
def _resolve(buffers, background, out_rgb, out_depth):
    height = buffers.shape[1]
    width = buffers.shape[2]
    for yy in numba.prange(height):
        for xx in range(width):
            k = buffers[0, yy, xx]
            for t in range(1, buffers.shape[0]):
                if buffers[t, yy, xx] < k:
                    k = buffers[t, yy, xx]
            if k == EMPTY:
                out_rgb[yy, xx, 0] = background[0]
                out_rgb[yy, xx, 1] = background[1]
                out_rgb[yy, xx, 2] = background[2]
                out_depth[yy, xx] = np.inf
            else:
                c = np.uint32(k & np.uint64(0xFFFFFFFF))
                out_rgb[yy, xx, 0] = c & 0xFF
                out_rgb[yy, xx, 1] = (c >> 8) & 0xFF
                out_rgb[yy, xx, 2] = (c >> 16) & 0xFF
                out_depth[yy, xx] = np.uint32(k >> np.uint64(32)).view(np.float32)


@numba.njit(parallel=True, cache=True)
def _edl(rgb, depth, strength, radius):
    """Eye-dome lighting: darken pixels lying behind their neighbours (log-depth obscurance)."""
    height, width = depth.shape
    out = rgb.copy()
    for yy in numba.prange(height):
        for xx in range(width):
            d = depth[yy, xx]
            if not np.isfinite(d):
                continue
            ld = math.log2(d)
            acc = 0.0
            for dy, dx in ((-radius, 0), (radius, 0), (0, -radius), (0, radius)):
                y2 = yy + dy
                x2 = xx + dx
                if 0 <= y2 < height and 0 <= x2 < width:
                    n = depth[y2, x2]
                    acc += max(0.0, ld - math.log2(n)) if np.isfinite(n) else 0.0
            shade = math.exp(-acc * 300.0 * strength)
            for c in range(3):
                out[yy, xx, c] = np.uint8(rgb[yy, xx, c] * shade)
    return out


@dataclass
class Frame:
    """A rendered frame: ``rgb`` (H, W, 3) uint8 and ``depth`` (H, W) float32 (inf = empty)."""

    rgb: np.ndarray
    depth: np.ndarray


class Rasterizer:
    """Reusable per-size buffers; ``threads`` buffers, one per worker thread."""

    def __init__(self, width: int, height: int, threads: int | None = None) -> None:
        self.width = int(width)
        self.height = int(height)
        self.threads = int(threads or numba.get_num_threads())
        self._buffers = np.empty((self.threads, self.height, self.width), np.uint64)

    def render(
        self,
        camera: Camera,
        xyz: np.ndarray,
        colour: np.ndarray,
        size: np.ndarray,
        ranges: np.ndarray | None = None,
        min_size: np.ndarray | None = None,
        background: tuple[int, int, int] = (0, 0, 0),
        edl: float = 0.0,
    ) -> Frame:
        """Draw points.

        Parameters
        ----------
        camera : the view; its width and height must match this rasteriser.
        xyz : (N, 3) float32 world positions (keep them near the origin for float32 precision).
        colour : (N,) uint32 packed 0x00BBGGRR (:func:`pack_colours`).
        size : (N,) float32 world sample size (0 draws one pixel).
        ranges : (M, 2) int64 [start, stop) ranges of points to draw (default: all).
        min_size : (M,) float32 smallest world splat size per range (coarse LOD nodes).
        edl : eye-dome lighting strength (0 = off).
        """
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError("camera size differs from the rasteriser's")
        if ranges is None:
            ranges = np.array([[0, xyz.shape[0]]], np.int64)
        ranges = np.asarray(ranges, np.int64).reshape(-1, 2)
        if min_size is None:
            min_size = np.zeros(ranges.shape[0], np.float32)
        # Split ranges into one contiguous share a thread, balanced by point count.
        counts = ranges[:, 1] - ranges[:, 0]
        cum = np.concatenate([[0], np.cumsum(counts)])
        goals = cum[-1] * np.arange(self.threads + 1) / self.threads
        task_bounds = np.searchsorted(cum, goals, side="left").astype(np.int64)
        task_bounds[0], task_bounds[-1] = 0, ranges.shape[0]
        task_bounds = np.maximum.accumulate(task_bounds)
        Rts, Ks = _camera_arrays([camera] * self.threads)
        self._buffers.fill(EMPTY)
        _splat(xyz, colour, size, np.ascontiguousarray(ranges[:, 0]), np.ascontiguousarray(ranges[:, 1]),
               np.asarray(min_size, np.float32), task_bounds, Rts, Ks, self._buffers)  # fmt: skip
        rgb = np.empty((self.height, self.width, 3), np.uint8)
        depth = np.empty((self.height, self.width), np.float32)
        _resolve(self._buffers, np.asarray(background, np.uint8), rgb, depth)
        if edl > 0:
            rgb = _edl(rgb, depth, float(edl), 1)
        return Frame(rgb=rgb, depth=depth)

    def render_batch(
        self,
        cameras: list[Camera],
        xyz: np.ndarray,
        colour: np.ndarray,
        size: np.ndarray,
        ranges: list[np.ndarray],
        min_size: list[np.ndarray],
        background: tuple[int, int, int] = (0, 0, 0),
        edl: float = 0.0,
    ) -> list[Frame]:
        """Draw up to :attr:`threads` frames at once, one a thread (for video: no merging of
        per-thread buffers, and each thread keeps to one frame's buffer). Arguments as
        :meth:`render`, one camera, ranges array and min_size array a frame."""
        if not 0 < len(cameras) <= self.threads:
            raise ValueError(f"a batch holds 1 to {self.threads} frames, got {len(cameras)}")
        if len(ranges) != len(cameras) or len(min_size) != len(cameras):
            raise ValueError("one ranges and one min_size array a camera")
        for cam in cameras:
            if (cam.width, cam.height) != (self.width, self.height):
                raise ValueError("camera size differs from the rasteriser's")
        rs = [np.asarray(r, np.int64).reshape(-1, 2) for r in ranges]
        all_ranges = np.concatenate(rs) if rs else np.empty((0, 2), np.int64)
        all_min = np.concatenate([np.asarray(m, np.float32) for m in min_size])
        task_bounds = np.concatenate([[0], np.cumsum([len(r) for r in rs])]).astype(np.int64)
        Rts, Ks = _camera_arrays(list(cameras))
        buffers = self._buffers[: len(cameras)]
        buffers.fill(EMPTY)
        _splat(xyz, colour, size, np.ascontiguousarray(all_ranges[:, 0]), np.ascontiguousarray(all_ranges[:, 1]),
               all_min, task_bounds, Rts, Ks, buffers)  # fmt: skip
        frames = []
        bg = np.asarray(background, np.uint8)
        for k in range(len(cameras)):
            rgb = np.empty((self.height, self.width, 3), np.uint8)
            depth = np.empty((self.height, self.width), np.float32)
            _resolve(buffers[k : k + 1], bg, rgb, depth)
            if edl > 0:
                rgb = _edl(rgb, depth, float(edl), 1)
            frames.append(Frame(rgb=rgb, depth=depth))
        return frames


def _camera_arrays(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3, 4) float32 [R | t] and (T, 5) float32 (fx, fy, cx, cy, near) of the cameras."""
    Rts = np.stack([np.hstack([c.R, c.t[:, None]]) for c in cameras]).astype(np.float32)
    Ks = np.array([[c.fx, c.fy, c.cx, c.cy, c.near] for c in cameras], np.float32)
    return Rts, Ks


@dataclass
class NodeTable:
    """Octree nodes as arrays for :func:`select_nodes`: ``center`` (M, 3) and ``radius`` (M,) of
    each node's bounding sphere (local frame), ``parent`` (M,) index (-1 for the root, which is
    row 0), ``points`` (M,) counts, ``spacing`` (M,) world spacing."""

    center: np.ndarray
    radius: np.ndarray
    parent: np.ndarray
    points: np.ndarray
    spacing: np.ndarray

    def __post_init__(self) -> None:
        self.children: list[list[int]] = [[] for _ in range(len(self.parent))]
        for i, p in enumerate(self.parent):
            if p >= 0:
                self.children[int(p)].append(i)


def select_nodes(table: NodeTable, camera: Camera, budget: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the nodes to draw: visible nodes by decreasing projected size (radius over
    distance) from the root down, while their points fit ``budget`` (Potree's rule).
    Also returns the (M,) bool mask of nodes whose bounding sphere meets the view frustum."""
    cam = table.center @ camera.R.T + camera.t  # (M, 3) camera-frame centres
    dist = np.linalg.norm(cam, axis=1)
    r = table.radius
    half_w = (camera.width / 2) / camera.fx
    half_h = (camera.height / 2) / camera.fy
    # Sphere against the four side planes and the near plane of the frustum.
    nw = 1.0 / math.sqrt(1 + half_w * half_w)
    nh = 1.0 / math.sqrt(1 + half_h * half_h)
    visible = (
        (cam[:, 2] > -r)
        & ((half_w * cam[:, 2] - np.abs(cam[:, 0])) * nw > -r)
        & ((half_h * cam[:, 2] - np.abs(cam[:, 1])) * nh > -r)
    )
    priority = r / np.maximum(dist - r, 1e-9)
    inside = dist <= r
    priority[inside] = np.inf
    chosen: list[int] = []
    total = 0
    heap = [(-priority[0], 0)] if visible[0] else []
    while heap:
        _, i = heapq.heappop(heap)
        n = int(table.points[i])
        if total + n > budget:
            break
        chosen.append(i)
        total += n
        for c in table.children[i]:
            if visible[c]:
                heapq.heappush(heap, (-priority[c], c))
    return np.asarray(chosen, np.int64), visible


_GL_VERTEX = """
#version 330
uniform mat4 mvp;
uniform vec4 rt_z;
uniform float fx;
uniform float min_size;
uniform float splat_scale;
uniform float max_side;
in vec3 in_pos;
in uint in_col;
in float in_size;
out vec3 v_col;
void main() {
    float z = dot(rt_z.xyz, in_pos) + rt_z.w;
    gl_Position = mvp * vec4(in_pos, 1.0);
    gl_PointSize = clamp(fx * max(in_size, min_size) * splat_scale / z, 1.0, max_side);
    v_col = vec3(float(in_col & 255u), float((in_col >> 8) & 255u), float((in_col >> 16) & 255u)) / 255.0;
}
"""
_GL_FRAGMENT = """
#version 330
in vec3 v_col;
out vec4 f_col;
void main() { f_col = vec4(v_col, 1.0); }
"""


def gl_projection(camera: Camera, far: float) -> np.ndarray:
    """(4, 4) OpenGL clip matrix of an OpenCV-convention camera (world to clip)."""
    w, h, n = camera.width, camera.height, camera.near
    P = np.array([[2 * camera.fx / w, 0, 2 * (camera.cx + 0.5) / w - 1, 0],
                  [0, -2 * camera.fy / h, 1 - 2 * (camera.cy + 0.5) / h, 0],
                  [0, 0, (far + n) / (far - n), -2 * far * n / (far - n)],
                  [0, 0, 1, 0]])  # fmt: skip
    Rt = np.eye(4)
    Rt[:3, :3], Rt[:3, 3] = camera.R, camera.t
    return P @ Rt


class GLRasterizer:
    """The same splats drawn as OpenGL points through moderngl (a GPU when there is one).

    The points are uploaded once (:meth:`upload`); :meth:`render` takes the same ranges and
    per-range smallest sizes as :class:`Rasterizer` and returns an (H, W, 3) uint8 image.
    """

    def __init__(self, width: int, height: int, backend: str | None = "egl") -> None:
        import moderngl

        self._gl = moderngl
        self.ctx = (
            moderngl.create_standalone_context(backend=backend)
            if backend
            else moderngl.create_standalone_context()
        )
        self.width, self.height = int(width), int(height)
        self.prog = self.ctx.program(vertex_shader=_GL_VERTEX, fragment_shader=_GL_FRAGMENT)
        self.prog["splat_scale"].value = SPLAT_SCALE
        self.prog["max_side"].value = 2 * MAX_HALF + 1
        self.fbo = self.ctx.simple_framebuffer((self.width, self.height))
        self.vao = None

    @property
    def renderer(self) -> str:
        """The OpenGL renderer string (``llvmpipe`` is Mesa's CPU rasteriser)."""
        return str(self.ctx.info.get("GL_RENDERER", ""))

    @property
    def hardware(self) -> bool:
        r = self.renderer.lower()
        return not any(s in r for s in ("llvmpipe", "softpipe", "swrast", "software"))

    def upload(self, xyz: np.ndarray, colour: np.ndarray, size: np.ndarray) -> None:
        """Put the points on the device: (N, 3) float32, (N,) uint32, (N,) float32."""
        self.vao = self.ctx.vertex_array(
            self.prog,
            [
                (self.ctx.buffer(np.ascontiguousarray(xyz, np.float32).tobytes()), "3f", "in_pos"),
                (self.ctx.buffer(np.ascontiguousarray(colour, np.uint32).tobytes()), "1u", "in_col"),
                (self.ctx.buffer(np.ascontiguousarray(size, np.float32).tobytes()), "1f", "in_size"),
            ],
        )

    def render(self, camera: Camera, ranges: np.ndarray, min_size: np.ndarray, far: float,
               background: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:  # fmt: skip
        """Draw the uploaded points of ``ranges``; ``far`` bounds the depth range (world units)."""
        if self.vao is None:
            raise RuntimeError("upload points before rendering")
        gl = self._gl
        self.ctx.enable(gl.DEPTH_TEST | gl.PROGRAM_POINT_SIZE)
        self.fbo.use()
        mvp = gl_projection(camera, far)
        Rt_z = np.append(camera.R[2], camera.t[2])
        self.prog["mvp"].write(mvp.T.astype("f4").tobytes())
        self.prog["rt_z"].value = tuple(float(v) for v in Rt_z)
        self.prog["fx"].value = float(camera.fx)
        self.fbo.clear(*(c / 255 for c in background), 1.0)
        for (a, b), m in zip(np.asarray(ranges).reshape(-1, 2), min_size, strict=True):
            self.prog["min_size"].value = float(m)
            self.vao.render(gl.POINTS, vertices=int(b - a), first=int(a))
        img = np.frombuffer(self.fbo.read(components=3), np.uint8).reshape(self.height, self.width, 3)
        return img[::-1].copy()

    def release(self) -> None:
        self.ctx.release()
