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

The kernel works in batches of :data:`_BATCH` points: first it projects the batch in one
vectorised loop (no branches: each point gets its pixel index, the spare slot past the frame
when it is not drawn, or -1 for a splat wider than a pixel), then writes the batch's keys one
by one; the wide splats (about 5 % of a preview's points) are drawn as before. Software
prefetches run :data:`_AHEAD` batches ahead through the ranges, so the points' cache lines
arrive before the projection needs them (the projection was waiting on memory: at 1.5 M
points a frame the scalar one-pass kernel took 20 ms of CPU, this one 7 ms on the same frames,
with the same frames out bit for bit). Each task also keeps the bounding box of the pixels it
wrote; the resolve reads the keys inside it only (clearing them as it goes: no separate
clearing pass) and fills the rest of the frame with the background (at 1280x720, 2.7 -> 1.4 ms
a frame on the preview's orbit, whose object fills about half the rows).

Also here: :func:`select_nodes`, the per-frame choice of octree nodes by projected size under
a point budget (Potree's rule), and :class:`GLRasterizer`, the same splats as OpenGL points
through moderngl, for machines with a GPU (and the bench's llvmpipe peer).
"""

from __future__ import annotations

import heapq
import math
import sys
from dataclasses import dataclass

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from shared.core.jit import empty
from shared.core.threads import cpu_budget, pin_threading_layer

# The scan's threading policy, for processes that render without scanning.
pin_threading_layer()

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


#: Points projected together (one vectorised loop) before their keys are written.
_BATCH = 256
#: Batches ahead of the projection that the prefetches request (measured: 1 or 2 best).
_AHEAD = 2
#: Points whose cache lines one round of prefetches covers (16 float32 = one 64-byte line).
_LINE = 16


@intrinsic
def _prefetch(typingctx, arr, idx):  # pragma: no cover - compiled
    """Ask the CPU to fetch the cache line of ``arr[idx]`` (1-D array, int index): llvm.prefetch,
    read, keep in all cache levels. A hint only: no fault, no effect on results."""
    if not (isinstance(arr, types.Array) and arr.ndim == 1 and isinstance(idx, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
        i8p = ir.PointerType(ir.IntType(8))
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return types.void(arr, idx), codegen


@numba.njit(inline="always")
def _prefetch_points(fxyz, colour, size, starts, stops, r, q, count, r_end):  # pragma: no cover
    """Prefetch the cache lines of the next ``count`` points from point ``q`` of range ``r``
    on, crossing into the following ranges (up to ``r_end``); returns the cursor after them."""
    while count > 0 and r < r_end:
        take = min(count, stops[r] - q)
        for k in range(q, q + take, _LINE):
            _prefetch(fxyz, 3 * k)
            _prefetch(fxyz, 3 * k + _LINE)
            _prefetch(fxyz, 3 * k + 2 * _LINE)
            _prefetch(size, k)
            _prefetch(colour, k)
        q += take
        count -= take
        if q >= stops[r]:
            r += 1
            if r < r_end:
                q = starts[r]
    return r, q


@numba.njit(inline="always", fastmath=True, error_model="numpy")
def _project_batch(
    fxyz, size, n, ms, Rt, fx, fy, cx, cy, near, width, height, pix, depth
):  # pragma: no cover
    """Project points 0..n of ``fxyz`` ((3n,) float32 x, y, z) with sizes ``size`` (n,): ``pix[j]``
    (int64) is the pixel index y * width + x of a one-pixel splat, width * height (the spare
    slot) when the point is not drawn (behind the near plane, off the frame), or -1 for a splat
    wider than a pixel; ``depth[j]`` (float32) its camera z. No branches: the loop vectorises
    (the one-pass kernel's arithmetic, expression for expression, so the same pixels and keys).
    Returns the bounding box (x0, x1, y0, y1), inclusive, of the one-pixel splats drawn
    (x0 > x1 when none is)."""
    r00, r01, r02, r03 = Rt[0, 0], Rt[0, 1], Rt[0, 2], Rt[0, 3]
    r10, r11, r12, r13 = Rt[1, 0], Rt[1, 1], Rt[1, 2], Rt[1, 3]
    r20, r21, r22, r23 = Rt[2, 0], Rt[2, 1], Rt[2, 2], Rt[2, 3]
    spare = width * height
    x0 = width
    x1 = -1
    y0 = height
    y1 = -1
    for j in range(n):
        x = fxyz[3 * j]
        y = fxyz[3 * j + 1]
        z = fxyz[3 * j + 2]
        zc = r20 * x + r21 * y + r22 * z + r23
        front = zc > near
        zs = zc if front else np.float32(1.0)  # no inf or NaN from the points not drawn
        xc = r00 * x + r01 * y + r02 * z + r03
        yc = r10 * x + r11 * y + r12 * z + r13
        inv = 1.0 / zs
        u = fx * xc * inv + cx
        v = fy * yc * inv + cy
        # Seed sizing: side in pixels = fx * world size / depth, a little enlarged so neighbours
        # overlap; the splat covers the pixel centres within half a side.
        half = min(max(size[j], ms) * fx * inv * (0.5 * SPLAT_SCALE), MAX_HALF)
        seen = front & (-half - 1 < u) & (u < width + half) & (-half - 1 < v) & (v < height + half)
        ui = np.int64(math.floor(u + 0.5))
        vi = np.int64(math.floor(v + 0.5))
        inside = (ui >= 0) & (ui < width) & (vi >= 0) & (vi < height)
        p = vi * width + ui if inside else spare
        p = p if half < 0.5 else -1
        pix[j] = p if seen else spare
        depth[j] = zc
        drawn = seen & inside & (half < 0.5)
        x0 = min(x0, ui if drawn else width)
        x1 = max(x1, ui if drawn else -1)
        y0 = min(y0, vi if drawn else height)
        y1 = max(y1, vi if drawn else -1)
    return x0, x1, y0, y1


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _splat(
    xyz, colour, size, starts, stops, min_size, task_bounds, Rts, Ks, buffers, width, boxes
):  # pragma: no cover
    """Task t draws ranges task_bounds[t]:task_bounds[t+1] with camera Rts[t] (3, 4),
    Ks[t] = (fx, fy, cx, cy, near) into buffers[t] ((H * W + 1,) uint64: the frame's pixels
    row by row, then a spare slot that takes the points not drawn): one frame split over
    threads, or one frame a thread. ``xyz`` (N, 3) float32 C-contiguous. ``boxes[t]`` (T, 4)
    int64 gets the bounding box (x0, x1, y0, y1), inclusive, of the pixels task t wrote."""
    npix = buffers.shape[1] - 1
    height = npix // width
    fxyz = xyz.reshape(-1)
    ntasks = task_bounds.shape[0] - 1
    for task in numba.prange(ntasks):
        buf = buffers[task]
        Rt = Rts[task]
        fx = Ks[task, 0]
        fy = Ks[task, 1]
        cx = Ks[task, 2]
        cy = Ks[task, 3]
        near = Ks[task, 4]
        pix = empty(_BATCH, np.int64)
        dbits = empty(_BATCH, np.uint32)
        depth = dbits.view(np.float32)
        r_end = task_bounds[task + 1]
        bx0 = width
        bx1 = -1
        by0 = height
        by1 = -1
        pr = task_bounds[task]
        pq = starts[pr] if pr < r_end else 0
        pr, pq = _prefetch_points(fxyz, colour, size, starts, stops, pr, pq, _AHEAD * _BATCH, r_end)
        for r in range(task_bounds[task], r_end):
            ms = min_size[r]
            for a in range(starts[r], stops[r], _BATCH):
                n = min(_BATCH, stops[r] - a)
                pr, pq = _prefetch_points(fxyz, colour, size, starts, stops, pr, pq, n, r_end)
                x0, x1, y0, y1 = _project_batch(fxyz[3 * a : 3 * (a + n)], size[a : a + n], n, ms, Rt, fx, fy,
                                                cx, cy, near, width, height, pix, depth)  # fmt: skip
                bx0 = min(bx0, x0)
                bx1 = max(bx1, x1)
                by0 = min(by0, y0)
                by1 = max(by1, y1)
                for j in range(n):
                    p = pix[j]
                    if p >= 0:
                        if p <= npix:  # always (the projection's indices); keeps a write in bounds
                            key = (np.uint64(dbits[j]) << np.uint64(32)) | np.uint64(colour[a + j])
                            b = buf[p]
                            buf[p] = key if key < b else b
                        continue
                    # A splat wider than a pixel: the square of pixel centres within half a side.
                    i = a + j
                    x = xyz[i, 0]
                    y = xyz[i, 1]
                    z = xyz[i, 2]
                    xc = Rt[0, 0] * x + Rt[0, 1] * y + Rt[0, 2] * z + Rt[0, 3]
                    yc = Rt[1, 0] * x + Rt[1, 1] * y + Rt[1, 2] * z + Rt[1, 3]
                    inv = 1.0 / depth[j]
                    u = fx * xc * inv + cx
                    v = fy * yc * inv + cy
                    half = min(max(size[i], ms) * fx * inv * (0.5 * SPLAT_SCALE), MAX_HALF)
                    key = (np.uint64(dbits[j]) << np.uint64(32)) | np.uint64(colour[i])
                    x0 = max(np.int64(math.ceil(u - half)), 0)
                    x1 = min(np.int64(math.floor(u + half)), width - 1)
                    y0 = max(np.int64(math.ceil(v - half)), 0)
                    y1 = min(np.int64(math.floor(v + half)), height - 1)
                    if x0 <= x1 and y0 <= y1:
                        bx0 = min(bx0, x0)
                        bx1 = max(bx1, x1)
                        by0 = min(by0, y0)
                        by1 = max(by1, y1)
                    for yy in range(y0, y1 + 1):
                        row = yy * width
                        for xx in range(x0, x1 + 1):
                            b = buf[row + xx]
                            buf[row + xx] = key if key < b else b
        boxes[task, 0] = bx0
        boxes[task, 1] = bx1
        boxes[task, 2] = by0
        boxes[task, 3] = by1


#: Frame rows a resolve task takes (its scratch row is allocated once a task).
_ROWS = 16


@numba.njit(parallel=True, cache=True)
def _resolve(buffers, boxes, background, out_rgb, words, packed, out_depth):  # pragma: no cover
    """Frame f of ``out_rgb`` (F, H, W, 3) uint8 and ``out_depth`` (F, H, W) uint32 (float32
    bits) from buffers f * g .. (f + 1) * g - 1 of ``buffers`` (T, H * W + 1) uint64, g = T // F,
    merged by their min; empty pixels get ``background`` and +inf. Only the box ``boxes[f]``
    (x0, x1, y0, y1, inclusive: where those buffers were written) is read, and every key read
    is reset to empty, ready for the next frame; the rest of the frame is background.

    With ``packed`` (W a multiple of 4, a little-endian CPU), ``words`` is ``out_rgb`` seen as
    (F * H * W * 3 / 4,) uint32 and each 4 pixels' colours go out as 3 words instead of 12 bytes."""
    nf, height, width = out_depth.shape
    g = buffers.shape[0] // nf
    bg = np.uint32(background[0]) | (np.uint32(background[1]) << 8) | (np.uint32(background[2]) << 16)
    inf_bits = np.uint32(0x7F800000)
    nrows = nf * height
    row_words = 3 * width // 4
    for task in numba.prange((nrows + _ROWS - 1) // _ROWS):
        cols = empty(width, np.uint32)  # the row's colours, 0x00BBGGRR
        for row in range(task * _ROWS, min(nrows, (task + 1) * _ROWS)):
            f = row // height
            yy = row - f * height
            x0 = max(boxes[f, 0], 0)
            x1 = min(boxes[f, 1], width - 1)
            if yy < boxes[f, 2] or yy > boxes[f, 3] or x0 > x1:
                x0 = width
                x1 = width - 1
            for xx in range(x0):
                cols[xx] = bg
                out_depth[f, yy, xx] = inf_bits
            base = yy * width
            for xx in range(x0, x1 + 1):
                p = base + xx
                k = buffers[f * g, p]
                buffers[f * g, p] = EMPTY
                for t in range(f * g + 1, (f + 1) * g):
                    kt = buffers[t, p]
                    buffers[t, p] = EMPTY
                    k = kt if kt < k else k
                vacant = k == EMPTY
                cols[xx] = bg if vacant else np.uint32(k & np.uint64(0xFFFFFF))
                out_depth[f, yy, xx] = inf_bits if vacant else np.uint32(k >> np.uint64(32))
            for xx in range(x1 + 1, width):
                cols[xx] = bg
                out_depth[f, yy, xx] = inf_bits
            if packed:
                w = row * row_words
                for m in range(width // 4):
                    c0 = cols[4 * m]
                    c1 = cols[4 * m + 1]
                    c2 = cols[4 * m + 2]
                    c3 = cols[4 * m + 3]
                    words[w + 3 * m] = c0 | (c1 << 24)
                    words[w + 3 * m + 1] = (c1 >> 8) | (c2 << 16)
                    words[w + 3 * m + 2] = (c2 >> 16) | (c3 << 8)
            else:
                for xx in range(width):
                    c = cols[xx]
                    out_rgb[f, yy, xx, 0] = np.uint8(c & 0xFF)
                    out_rgb[f, yy, xx, 1] = np.uint8((c >> 8) & 0xFF)
                    out_rgb[f, yy, xx, 2] = np.uint8((c >> 16) & 0xFF)


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
    """Reusable per-size buffers; ``threads`` buffers, one per worker thread (default: the
    process's CPU budget, at most numba's threads)."""

    def __init__(self, width: int, height: int, threads: int | None = None) -> None:
        self.width = int(width)
        self.height = int(height)
        self.threads = int(threads or min(cpu_budget(), numba.get_num_threads()))
        # One (H * W + 1,) key buffer a thread: the pixels, then the spare slot (see _splat).
        # Empty between frames: the resolve clears what it reads.
        self._buffers = np.full((self.threads, self.height * self.width + 1), EMPTY, np.uint64)
        self._dirty = False

    def _draw(self, cameras: list[Camera], xyz: np.ndarray, colour: np.ndarray, size: np.ndarray,
              ranges: np.ndarray, min_size: np.ndarray, task_bounds: np.ndarray, frames: int,
              background: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Splat ``ranges`` ((M, 2) int64) into the first ``len(cameras)`` buffers (task t: ranges
        task_bounds[t]:task_bounds[t+1] with cameras[t]) and resolve them into ``frames``
        frames: (F, H, W, 3) uint8 RGB and (F, H, W) float32 depth (inf = empty)."""
        buffers = self._buffers[: len(cameras)]
        if self._dirty:  # a draw that did not reach its resolve (an exception) left keys behind
            self._buffers.fill(EMPTY)
        Rts, Ks = _camera_arrays(cameras)
        boxes = np.empty((len(cameras), 4), np.int64)
        self._dirty = True
        _splat(np.ascontiguousarray(xyz, np.float32), np.ascontiguousarray(colour, np.uint32),
               np.ascontiguousarray(size, np.float32), np.ascontiguousarray(ranges[:, 0]),
               np.ascontiguousarray(ranges[:, 1]), np.ascontiguousarray(min_size, np.float32), task_bounds,
               Rts, Ks, buffers, self.width, boxes)  # fmt: skip
        # Each frame's box: the union of its buffers' boxes.
        g = boxes.reshape(frames, -1, 4)
        frame_boxes = np.stack(
            [g[:, :, 0].min(1), g[:, :, 1].max(1), g[:, :, 2].min(1), g[:, :, 3].max(1)], axis=1
        )
        rgb = np.empty((frames, self.height, self.width, 3), np.uint8)
        depth = np.empty((frames, self.height, self.width), np.float32)
        packed = self.width % 4 == 0 and sys.byteorder == "little"
        words = rgb.reshape(-1).view(np.uint32) if packed else np.empty(1, np.uint32)
        _resolve(buffers, np.ascontiguousarray(frame_boxes), np.asarray(background, np.uint8), rgb, words, packed,
                 depth.view(np.uint32))  # fmt: skip
        self._dirty = False
        return rgb, depth

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
        rgbs, depths = self._draw([camera] * self.threads, xyz, colour, size, ranges, min_size, task_bounds, 1,
                                  background)  # fmt: skip
        rgb, depth = rgbs[0], depths[0]
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
        rgbs, depths = self._draw(list(cameras), xyz, colour, size, all_ranges, all_min, task_bounds,
                                  len(cameras), background)  # fmt: skip
        frames = []
        for k in range(len(cameras)):
            rgb, depth = rgbs[k], depths[k]
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
