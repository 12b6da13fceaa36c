"""Gray-code decoding: camera images of stripe patterns -> sub-pixel projector coordinates.

In: a :class:`~shared.formats.capture.Capture` (white and black frames, column patterns, optional
row patterns, each with an optional inverse; 8- or 16-bit, grey or colour).
Out: a :class:`Decoded` record of per-camera-pixel arrays: projector ``column`` (sub-pixel,
in projector pixels with OpenCV's convention that pixel centres are integers), projector
``row``, a ``confidence`` in [0, 1], the ``colour`` of the white frame and the ``lit`` mask.

How (see FIELD-NOTES, "Decoding Gray codes"):

* ``contrast = white - black``; a pixel is *lit* when it exceeds ``lit_threshold``.
* Each bit is decided by the sign of ``pattern - inverse`` (or ``pattern - (white+black)/2``
  without an inverse) and is *weak* when that difference is small against the pixel's own
  contrast or against the sensor noise. Low albedo and ambient light scale both sides, so
  the decision is local to each pixel.
* A Gray code changes one bit between neighbouring columns, so one weak bit whose finer bits
  read the pattern of that bit's stripe edge means the pixel lies on that edge: either value
  gives an adjacent column. Any other weak bit makes the code unreliable; the finest bits
  are then dropped one at a time (a coarser code, up to ``max_drop`` bits) rather than
  returning a wrong column.
* Sub-pixel: along each camera row, the edge between two neighbouring pixels of adjacent
  codes is placed at the zero crossing of the bit that changes there (``pattern - inverse``
  interpolated linearly), and pixels between two edges get a column interpolated between the
  edges' projector columns. Pixels without two consistent edges keep the centre of their code.

Each axis whose images fit in memory (up to 480 MB: any 8-bit capture up to 15 MP) is decoded
in one pass by a numba kernel working through bands of camera rows: every bit plane of a row is
classified into row buffers that stay in cache, then the same row's codes are resolved and its
sub-pixel edges placed, so each image is read once and only the outputs go back to memory.
The loops are written for LLVM's vectoriser: bit planes are classified in narrow integers
(int16 differences for 8-bit images, scaled only where a confidence or an edge needs them),
codes are resolved level by level over a whole row without branches, and values are loaded
before any conditional expression (numba turns a load inside one into a branch, which keeps
a loop scalar).
Larger axes stream in batches of pattern/inverse pairs (about 160 MB of images at a time) into
whole-frame code planes. A small thread pool reads images ahead (PNG decoding releases the
GIL): the row patterns load while the columns are decoded. Working memory is about 25 bytes
per camera pixel plus one axis's images: a 15 MP 8-bit capture peaks near 1.1 GB.
The kernels run on :func:`kernel_threads` threads, counted in :mod:`shared.scan._kernel_threads`.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.core.threads import cpu_budget
from shared.formats.capture import Capture, CodeImage, code_bits
from shared.formats.images import prepare_png_reading, probe_image, read_grey, read_grey_and_colour
from shared.formats.rig import load_rig
from shared.scan._bands import run_bands
from shared.scan._decode_kernels import _bit_planes, _decode_rows, _finish_rows, _grey_rgb
from shared.scan._kernel_threads import kernel_thread_scope, kernel_threads
from shared.scan.albedo import CameraResponse, response_for_rig

__all__ = [
    "DecodeParams",
    "Decoded",
    "decode_capture",
    "decode_stack",
    "kernel_thread_scope",
    "kernel_threads",
    "load_decoded",
    "save_decoded",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DecodeParams:
    """Thresholds of the decoder, in grey levels of an 8-bit image (scaled for 16-bit images).

    ``lit_threshold``: least white-black contrast of a projector-lit pixel.
    ``noise``: a bit whose pattern-inverse difference is below this is weak.
    ``weak_ratio``: ... or below this share of the pixel's white-black contrast.
    ``max_drop``: at most this many finest bits are dropped for a coarser code.
    ``response``: the camera's response (stored value -> linear light). None: the one the
    capture's rig states (``radiometry.camera_response``), sRGB when it states none or there is
    no rig, as :mod:`shared.scan.albedo` assumes. Without inverse patterns a bit is read against
    the white/black midpoint, and the projector's half-way light lies at the midpoint of linear
    light, not of stored values: under
    an sRGB camera the stored midpoint moves every stripe edge (median column error 0.19 against
    0.016 projector pixels on the simulated bunny). With inverses the response does not matter:
    pattern and inverse cross where their light is equal, whatever the curve.
    """

    lit_threshold: float = 2.5
    noise: float = 1.5
    weak_ratio: float = 0.12
    max_drop: int = 3
    response: CameraResponse | None = None


@dataclass
class Decoded:
    """Per-camera-pixel decode of one capture. All arrays are (H, W) unless noted.

    column : float32, sub-pixel projector column, NaN where invalid.
    row : float32, projector row, NaN where invalid or when no rows were captured.
    confidence : float32 in [0, 1]: the second-weakest kept column bit's
        ``|pattern - inverse| / (white - black)`` (the weakest may be an edge); 0 where invalid.
    colour : (H, W, 3) uint8 RGB of the white frame.
    lit : bool, projector-lit (white-black contrast above the lit threshold).
    stats : counts and timings (JSON-ready).
    projector_size : (width, height) of the projector.
    """

    column: np.ndarray
    row: np.ndarray
    confidence: np.ndarray
    colour: np.ndarray
    lit: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict)
    projector_size: tuple[int, int] = (0, 0)
    column_level: np.ndarray | None = None  # (H, W) int8 code level (dropped bits), -1 invalid
    row_level: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.column.shape[0]), int(self.column.shape[1]))


# --------------------------------------------------------------------------- streaming


def _scale_for(dtype: np.dtype) -> float:
    return 257.0 if dtype == np.uint16 else 1.0


@dataclass(frozen=True)
class _Plane:
    """One bit plane to decode: pattern and optional inverse, as files or in-memory images."""

    bit: int
    pattern: Path | np.ndarray
    inverse: Path | np.ndarray | None = None

    @property
    def pattern_name(self) -> str:
        return str(self.pattern) if isinstance(self.pattern, Path) else f"bit {self.bit} pattern"

    @property
    def inverse_name(self) -> str:
        return str(self.inverse) if isinstance(self.inverse, Path) else f"bit {self.bit} inverse"


def _load(image: Path | np.ndarray, size: tuple[int, int], name: str) -> np.ndarray:
    if isinstance(image, np.ndarray):
        if image.ndim != 2 or (image.shape[1], image.shape[0]) != size or image.dtype not in (np.uint8, np.uint16):
            raise InputError(name, f"in-memory image must be a {size[0]}x{size[1]} uint8 or uint16 grey array")
        # C order, like decoded files: the kernels are compiled for that layout (no copy if it is).
        return np.ascontiguousarray(image)
    return read_grey(image, size)


class _Reader:
    """Reads one axis's (plane, pattern, inverse) through the thread pool, ``ahead`` planes in
    advance. Reading starts at construction: the next axis's images load while this one is
    decoded. In-memory planes (or no pool) are handed over as they are."""

    def __init__(self, planes: Sequence[_Plane], size: tuple[int, int], pool: ThreadPoolExecutor | None,
                 ahead: int) -> None:
        self.planes = list(planes)
        self.size = size
        files = any(isinstance(x, Path) for e in self.planes for x in (e.pattern, e.inverse))
        self.pool = pool if files else None
        self.ahead = max(1, ahead)
        self.pending = [self._submit(e) for e in self.planes[: self.ahead]] if self.pool is not None else []

    def _submit(self, e: _Plane) -> tuple[Future[np.ndarray], Future[np.ndarray] | None]:
        assert self.pool is not None
        fp = self.pool.submit(_load, e.pattern, self.size, e.pattern_name)
        fi = self.pool.submit(_load, e.inverse, self.size, e.inverse_name) if e.inverse is not None else None
        return fp, fi

    def __iter__(self) -> Iterator[tuple[_Plane, np.ndarray, np.ndarray | None]]:
        if self.pool is None:
            for e in self.planes:
                yield e, _load(e.pattern, self.size, e.pattern_name), (
                    _load(e.inverse, self.size, e.inverse_name) if e.inverse is not None else None
                )
            return
        for k, e in enumerate(self.planes):
            fp, fi = self.pending.pop(0)
            if k + self.ahead < len(self.planes):
                self.pending.append(self._submit(self.planes[k + self.ahead]))
            yield e, fp.result(), (fi.result() if fi is not None else None)

    def cancel(self) -> None:
        """Drop reads not started yet (after a failure elsewhere)."""
        for fp, fi in self.pending:
            fp.cancel()
            if fi is not None:
                fi.cancel()
        self.pending.clear()


class _References:
    """Per-pixel references of the streaming path, shared by every batch: midpoint, weak-bit
    thresholds, q scales (the one-pass kernel computes the same values row by row)."""

    def __init__(self, white: np.ndarray, black: np.ndarray, params: DecodeParams, scale: float,
                 mid2: np.ndarray) -> None:
        self.contrast = white.astype(np.float32).ravel() - black.astype(np.float32).ravel()
        if mid2.size:
            self.mid = mid2.astype(np.float32).ravel() * np.float32(0.5)
        else:
            self.mid = (white.astype(np.float32).ravel() + black.astype(np.float32).ravel()) * np.float32(0.5)
        self.noise = np.float32(params.noise * scale)
        self.ratio = np.float32(params.weak_ratio)
        self._cache: dict[bool, tuple[np.ndarray, np.ndarray]] = {}

    def thresholds(self, with_inverse: bool) -> tuple[np.ndarray, np.ndarray]:
        """(weak threshold, 127 / full swing) per pixel; the swing is the contrast with an
        inverse and half of it against the midpoint."""
        if with_inverse not in self._cache:
            swing = self.contrast if with_inverse else self.contrast * np.float32(0.5)
            thr = np.maximum(self.noise, self.ratio * swing).astype(np.float32)
            with np.errstate(divide="ignore"):
                kq = np.where(swing > 0, np.float32(127.0) / swing, np.float32(0.0)).astype(np.float32)
            self._cache[with_inverse] = (thr, kq)
        return self._cache[with_inverse]

    def release(self) -> None:
        """Drop the per-pixel arrays (they are not needed once every batch is classified)."""
        self.contrast = self.mid = np.empty(0, np.float32)
        self._cache.clear()


#: Bytes of pattern images classified per kernel launch (a batch is held in memory together):
#: few launches matter on a busy machine, memory matters at 15 MP. An axis whose images all
#: fit in one batch is decoded by the one-pass kernel.
_BATCH_BYTES = 160_000_000
_MAX_BATCH = 12


#: An axis whose images total at most this is decoded in one pass from memory (a 15 MP 8-bit
#: capture's 20 images of an axis take 300 MB); larger ones stream in batches.
_ONE_PASS_BYTES = 480_000_000


#: Bit planes an axis can have (a 16384-pixel projector side needs 14): the one-pass kernel's
#: tuples are padded to this length, so that every capture runs one compiled signature.
_MAX_PLANES = 16


def _padded(images: Sequence[np.ndarray], n: int) -> tuple[np.ndarray, ...]:
    """``images`` as a tuple of length ``n``, padded with its first image (never read: the
    kernels take the count from their ``bits`` array). numba compiles a kernel for each tuple
    length it sees; a fixed length lets ``make setup`` compile the one the pipeline uses."""
    if not 0 < len(images) <= n:
        raise ValueError(f"{len(images)} images, need 1..{n}")
    return (*images, *(images[0],) * (n - len(images)))


def _batch_size(size: tuple[int, int], itemsize: int) -> int:
    return int(max(1, min(_MAX_BATCH, _BATCH_BYTES // (2 * size[0] * size[1] * itemsize))))


def _one_pass(entries: Sequence[_Plane], size: tuple[int, int], itemsize: int) -> bool:
    """Whether an axis is decoded by the one-pass kernel: its images fit the one-pass budget and
    either every plane has an inverse or none has."""
    n_images = sum(1 + (p.inverse is not None) for p in entries)
    return (
        n_images * size[0] * size[1] * itemsize <= _ONE_PASS_BYTES
        and len({p.inverse is None for p in entries}) == 1
    )


def _reader(entries: Sequence[_Plane], size: tuple[int, int], itemsize: int,
            pool: ThreadPoolExecutor | None) -> _Reader:
    ahead = len(entries) if _one_pass(entries, size, itemsize) else _batch_size(size, itemsize) + 2
    return _Reader(entries, size, pool, ahead)


def _midpoint2(white: np.ndarray, black: np.ndarray, response: CameraResponse) -> np.ndarray:
    """Twice the stored value of the white/black midpoint in linear light, (H, W) int32, rounded
    to a half level; a (0, 0) array for a linear camera (the kernels then take ``white + black``,
    exactly). 8-bit frames go through a 256 x 256 table of every (white, black) pair."""
    if response.kind == "linear":
        return np.zeros((0, 0), np.int32)
    lut8 = response.lut().astype(np.float64)
    if white.dtype == np.uint8:
        codes = np.arange(256, dtype=np.float64)
        mid = np.interp(0.5 * (lut8[:, None] + lut8[None, :]), lut8, codes)
        table = np.rint(2.0 * mid).astype(np.int32)
        return table[white, black]
    # 16-bit: the curve of the 8-bit codes, read between them (a response is stated per 8-bit code).
    codes = np.arange(256, dtype=np.float64) * 257.0
    lin = np.interp(white, codes, lut8) + np.interp(black, codes, lut8)
    return np.rint(2.0 * np.interp(0.5 * lin, lut8, codes)).astype(np.int32)


@dataclass
class _AxisOut:
    """Outputs of one axis, (H, W): value (float32), level (int8), conf (float32 or a (1, W)
    dummy when the axis keeps no confidence), lit (bool, filled by the first axis)."""

    value: np.ndarray
    level: np.ndarray
    conf: np.ndarray
    lit: np.ndarray


def _decode_axis(
    entries: Sequence[_Plane],
    white: np.ndarray,
    black: np.ndarray,
    mid2: np.ndarray,
    params: DecodeParams,
    scale: float,
    nbits: int,
    n_proj: int,
    store_q: bool,
    subpixel: bool,
    lit_known: bool,
    out: _AxisOut,
    reader: _Reader,
    tick: Callable[[int], None],
) -> np.ndarray:
    """Decode one axis into ``out`` (``mid2``: see :func:`_midpoint2`); returns per-row counts
    (H, 2 + levels) int64: lit pixels
    (0 when ``lit_known``: ``out.lit`` is then read, not written), interpolated pixels,
    decoded pixels per level."""
    h, w = white.shape
    size = (w, h)
    lowest = min(p.bit for p in entries)
    max_level = min(nbits - 1, lowest + params.max_drop)
    counts = np.zeros((h, 2 + max_level - lowest + 1), np.int64)
    itemsize = 2 if scale > 1 else 1
    batch_size = _batch_size(size, itemsize)
    one_pass = _one_pass(entries, size, itemsize)

    def checked(entry: _Plane, pat: np.ndarray, inv: np.ndarray | None) -> None:
        if pat.dtype.itemsize * 8 != (16 if scale > 1 else 8):
            raise InputError(entry.pattern_name, f"image is {pat.dtype.itemsize * 8}-bit but the white frame is not")
        if inv is not None and inv.dtype != pat.dtype:
            raise InputError(entry.inverse_name, "inverse image has a different bit depth from its pattern")

    if one_pass:
        pats: list[np.ndarray] = []
        invs: list[np.ndarray] = []
        for entry, pat, inv in reader:
            checked(entry, pat, inv)
            pats.append(pat)
            if inv is not None:
                invs.append(inv)
            tick(1 + (inv is not None))
        with_inverse = bool(invs)
        bits = np.array([e.bit for e in entries], np.uint16)
        run_bands(
            _decode_rows,
            _padded(pats, _MAX_PLANES), _padded(invs if with_inverse else pats, _MAX_PLANES), with_inverse, bits,
            white, black, mid2, np.float32(params.lit_threshold * scale), np.float32(params.noise * scale),
            np.float32(params.weak_ratio), int(nbits), int(lowest), int(max_level), int(n_proj), bool(store_q),
            bool(subpixel), np.zeros(0, np.int16 if itemsize == 1 else np.int32),
            out.lit, out.value, out.level, out.conf, counts,
        )
        if lit_known:
            counts[:, 0] = 0
        return counts

    # Streaming: more images than one batch holds; classify batch by batch into whole-frame
    # code planes, then resolve.
    refs = _References(white, black, params, scale, mid2)
    lit = out.lit.ravel()
    if not lit_known:
        lit[:] = refs.contrast > np.float32(params.lit_threshold * scale)
        counts[:, 0] = np.count_nonzero(out.lit, axis=1)
    n = h * w
    signs = np.zeros(n, np.uint16)
    weak = np.zeros(n, np.uint16)
    q = np.zeros((len(entries), n), np.int8) if store_q else np.zeros((1, 1), np.int8)
    m1 = np.full(n, 255, np.uint8)
    m2 = np.full(n, 255, np.uint8)
    batch: list[tuple[_Plane, np.ndarray, np.ndarray | None]] = []
    first = 0  # index of the batch's first entry

    def flush() -> None:
        nonlocal first
        if not batch:
            return
        with_inverse = batch[0][2] is not None
        thr, kq = refs.thresholds(with_inverse)
        # Tuples of flat views (no copies), padded to one length: numba specialises on it.
        pats = _padded([p.ravel() for _, p, _ in batch], _MAX_BATCH)
        if with_inverse:
            ref = _padded([i.ravel() for _, _, i in batch], _MAX_BATCH)
        else:
            ref = (refs.mid,) * _MAX_BATCH
        bits = np.array([e.bit for e, _, _ in batch], np.uint16)
        qs = q[first : first + len(batch)] if store_q else q
        run_bands(_bit_planes, pats, ref, bits, thr, kq, signs, weak, qs, bool(store_q), m1, m2)
        first += len(batch)
        tick(sum(1 + (i is not None) for _, _, i in batch))
        batch.clear()

    for entry, pat, inv in reader:
        checked(entry, pat, inv)
        if batch and (batch[0][2] is None) != (inv is None):
            flush()
        batch.append((entry, pat, inv))
        if len(batch) == batch_size:
            flush()
    flush()
    refs.release()
    q3 = q.reshape(len(entries), h, w) if store_q else np.zeros((1, 1, 1), np.int8)
    run_bands(
        _finish_rows,
        signs.reshape(h, w), weak.reshape(h, w), out.lit, m2.reshape(h, w) if store_q else np.zeros((1, w), np.uint8),
        bool(store_q), q3, int(nbits), int(lowest), int(max_level), int(n_proj), bool(subpixel), out.value,
        out.level, out.conf, counts,
    )
    return counts


def decode_capture(
    capture: Capture,
    *,
    progress: Callable[[float], None] | None = None,
    subpixel: bool = True,
    params: DecodeParams | None = None,
    threads: int | None = None,
) -> Decoded:
    """Decode a capture into per-pixel projector coordinates.

    Parameters
    ----------
    capture : the validated capture (images are read here; size mismatches raise InputError).
    progress : called with the fraction done in [0, 1] as images are consumed.
    subpixel : interpolate columns between stripe edges (True) or keep integer codes (False).
    params : decoder thresholds (:class:`DecodeParams`).
    threads : image-reading threads (PNG decoding releases the GIL; default
        :func:`~shared.core.threads.cpu_budget`).

    Returns
    -------
    Decoded with (H, W) arrays; see :class:`Decoded`.
    """

    def planes(entries: Sequence[CodeImage]) -> list[_Plane]:
        return [_Plane(e.bit, e.pattern, e.inverse) for e in entries]

    col_planes, row_planes = planes(capture.columns), planes(capture.rows)
    params = params or DecodeParams()
    if params.response is None and any(p.inverse is None for p in (*col_planes, *row_planes)):
        # Only a plane without its inverse is read against the midpoint, which needs the response.
        params = replace(params, response=response_for_rig(load_rig(capture.rig) if capture.rig is not None else None))
    # The size and depth from the white frame's header, so that every image can be queued for
    # reading at once: the pool reads while this thread makes the fast PNG path ready (numba's
    # first dispatch in a process, up to about a second) and then waits for white and black.
    info = probe_image(capture.white)
    itemsize = 2 if info.bit_depth > 8 else 1
    with ThreadPoolExecutor(max_workers=max(1, threads or cpu_budget())) as pool:
        fw = pool.submit(read_grey_and_colour, capture.white)
        fb = pool.submit(read_grey, capture.black)
        readers = (_reader(col_planes, info.size, itemsize, pool), _reader(row_planes, info.size, itemsize, pool))
        try:
            if info.format == "png":  # other formats never take the fast path: no kernel to load
                prepare_png_reading()
            white, colour = fw.result()
            black = fb.result()
            if white.shape[::-1] != info.size:  # a header that disagrees with its pixels
                raise InputError(capture.white, f"header says {info.width}x{info.height}, pixels are "
                                 f"{white.shape[1]}x{white.shape[0]}")  # fmt: skip
            if black.shape != white.shape:
                raise InputError(
                    capture.black,
                    f"image is {black.shape[1]}x{black.shape[0]}, but the white frame is "
                    f"{white.shape[1]}x{white.shape[0]}",
                )
        except BaseException:
            for r in readers:
                r.cancel()
            raise
        return _decode(
            white, black, colour, col_planes, row_planes,
            (capture.projector_width, capture.projector_height), str(capture.white), str(capture.black),
            progress, subpixel, params, pool, readers,
        )


def decode_stack(
    white: np.ndarray,
    black: np.ndarray,
    columns: Sequence[tuple[int, np.ndarray, np.ndarray | None]],
    rows: Sequence[tuple[int, np.ndarray, np.ndarray | None]] = (),
    projector_size: tuple[int, int] = (1024, 768),
    *,
    colour: np.ndarray | None = None,
    subpixel: bool = True,
    params: DecodeParams | None = None,
) -> Decoded:
    """Decode an in-memory image stack (what :func:`decode_capture` does with files).

    Parameters
    ----------
    white, black : (H, W) uint8 or uint16 grey reference frames.
    columns, rows : ``(bit, pattern, inverse or None)`` per captured bit, most significant first;
        images (H, W) of the white frame's dtype.
    projector_size : (width, height) of the projector.
    colour : (H, W, 3) uint8 RGB for the points; grey white frame when None.
    """
    # C order, like decoded files (the kernels are compiled for it; no copy when it already is).
    white, black = np.ascontiguousarray(white), np.ascontiguousarray(black)
    # In memory there is no reading to overlap: no thread pool.
    return _decode(
        white, black, colour, [_Plane(*c) for c in columns], [_Plane(*r) for r in rows],
        tuple(projector_size), "white frame", "black frame", None, subpixel, params or DecodeParams(), None,
    )


class _Slab:
    """One uint8 block holding several arrays of ``n`` elements each (``itemsizes`` bytes per
    element, in the order they are taken), each starting on a 64-byte boundary."""

    def __init__(self, n: int, itemsizes: Sequence[int]) -> None:
        self.sizes = [(n * k + 63) // 64 * 64 for k in itemsizes]
        self.buf = np.empty(sum(self.sizes) + 64, np.uint8)
        self.offset = (-self.buf.ctypes.data) % 64
        self.k = 0

    def take(self, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        """The next array of ``shape`` and ``dtype`` (C order, uninitialised)."""
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        if self.k >= len(self.sizes) or nbytes > self.sizes[self.k]:
            raise ValueError("slab exhausted")
        view = self.buf[self.offset : self.offset + nbytes].view(dtype).reshape(shape)
        self.offset += self.sizes[self.k]
        self.k += 1
        return view


def _decode(*args: Any) -> Decoded:
    with kernel_thread_scope():
        return _decode_inner(*args)


def _decode_inner(
    white: np.ndarray,
    black: np.ndarray,
    colour: np.ndarray | None,
    col_planes: list[_Plane],
    row_planes: list[_Plane],
    projector_size: tuple[int, int],
    white_name: str,
    black_name: str,
    progress: Callable[[float], None] | None,
    subpixel: bool,
    params: DecodeParams,
    pool: ThreadPoolExecutor | None,
    readers: tuple[_Reader, _Reader] | None = None,
) -> Decoded:

    t0 = time.perf_counter()
    pw, ph = projector_size
    col_bits = code_bits(pw)
    row_bits = code_bits(ph)
    n_images = 2 + sum(1 + (p.inverse is not None) for p in (*col_planes, *row_planes))
    done = [0]

    def tick(k: int) -> None:
        done[0] += k
        if progress is not None:
            progress(min(1.0, done[0] / n_images))

    h, w = white.shape
    if black.dtype != white.dtype:
        raise InputError(black_name, "black frame has a different bit depth from the white frame")
    tick(2)
    scale = _scale_for(white.dtype)
    # Only a plane without its inverse is read against the midpoint.
    against_mid = any(p.inverse is None for p in (*col_planes, *row_planes))
    response = params.response or CameraResponse()
    mid2 = _midpoint2(white, black, response) if against_mid else np.zeros((0, 0), np.int32)
    # Every (H, W) output carved from one allocation (the grey colour too, when made here): a
    # block that size gets transparent huge pages (numpy asks for them above 4 MB), so the
    # first writes fault a page per 2 MB, not per 4 KB (3173 faults, a sixth of the bench's
    # in-memory decode, were gone).
    slab = _Slab(h * w, ([3] if colour is None else []) + [1, 4, 1, 4] + ([4, 1] if row_planes else []))
    if colour is None:  # an in-memory stack without colour: the grey white frame
        colour = slab.take((h, w, 3), np.uint8)
        run_bands(_grey_rgb, white, 8 if white.dtype == np.uint16 else 0, colour)
    lit = slab.take((h, w), np.bool_)
    itemsize = 2 if scale > 1 else 1
    if readers is not None:  # queued by decode_capture as soon as the size was known
        col_reader, row_reader = readers
    else:
        col_reader = _reader(col_planes, (w, h), itemsize, pool)
        # The rows' images start loading now, while the columns are decoded.
        row_reader = _reader(row_planes, (w, h), itemsize, pool)
    try:
        cols = _AxisOut(slab.take((h, w), np.float32), slab.take((h, w), np.int8), slab.take((h, w), np.float32), lit)
        col_counts = _decode_axis(col_planes, white, black, mid2, params, scale, col_bits, pw, True, subpixel, False, cols,
                                  col_reader, tick)
    except BaseException:
        col_reader.cancel()
        row_reader.cancel()
        raise
    n_lit = int(col_counts[:, 0].sum())
    if n_lit == 0:
        row_reader.cancel()
        contrast = white.astype(np.float32) - black.astype(np.float32)
        peak = float(contrast.max()) if contrast.size else 0.0
        raise InputError(
            white_name,
            f"nothing is lit by the projector: white and black frames differ by at most {peak:.0f} grey "
            f"levels (all-dark capture?)",
        )
    t_col = time.perf_counter()
    n_row = 0
    if row_planes:
        rows = _AxisOut(slab.take((h, w), np.float32), slab.take((h, w), np.int8), np.empty((1, w), np.float32), lit)
        try:
            row_counts = _decode_axis(row_planes, white, black, mid2, params, scale, row_bits, ph, False, False, True, rows,
                                      row_reader, tick)
        except BaseException:
            row_reader.cancel()
            raise
        n_row = int(row_counts[:, 2:].sum())
        row, row_level = rows.value, rows.level
    else:
        row, row_level = np.full((h, w), np.nan, np.float32), None
    t_end = time.perf_counter()

    levels = col_counts[:, 2:].sum(axis=0)
    n_col = int(levels.sum())
    stats: dict[str, Any] = {
        "camera_width": w,
        "camera_height": h,
        "projector_width": pw,
        "projector_height": ph,
        "column_bits_captured": len(col_planes),
        "row_bits_captured": len(row_planes),
        "inverse_patterns": not against_mid,
        "midpoint": ("linear light, " + response.kind + " response") if mid2.size else (
            "stored values" if against_mid else "none (inverse patterns)"),
        "lit_pixels": n_lit,
        "column_decoded": n_col,
        "column_decoded_share_of_lit": n_col / n_lit,
        "row_decoded": n_row,
        "subpixel": subpixel,
        "subpixel_interpolated": int(col_counts[:, 1].sum()),
        "column_bits_dropped_histogram": [int(v) for v in levels],
        "seconds_columns": round(t_col - t0, 4),
        "seconds_rows": round(t_end - t_col, 4),
        "seconds_total": round(t_end - t0, 4),
    }
    log.info("decoded %d of %d lit pixels (%.1f %%) in %.2f s", n_col, n_lit, 100 * n_col / n_lit, t_end - t0)
    return Decoded(
        column=cols.value,
        row=row,
        confidence=cols.conf,
        colour=colour,
        lit=lit,
        stats=stats,
        projector_size=(pw, ph),
        column_level=cols.level,
        row_level=row_level,
    )


# --------------------------------------------------------------------------- persistence

_ARRAYS = ("column", "row", "confidence", "colour", "lit")


def save_decoded(decoded: Decoded, path: str | os.PathLike[str]) -> Path:
    """Write a :class:`Decoded` to ``path`` (npz) through a temporary name, then rename."""
    path = Path(path)
    arrays = {k: getattr(decoded, k) for k in _ARRAYS}
    if decoded.column_level is not None:
        arrays["column_level"] = decoded.column_level
    if decoded.row_level is not None:
        arrays["row_level"] = decoded.row_level
    with atomic_file(path, suffix=".tmp.npz") as tmp:
        np.savez(
            tmp,
            **arrays,
            projector_size=np.asarray(decoded.projector_size, np.int64),
            stats=np.frombuffer(json.dumps(decoded.stats).encode("utf-8"), np.uint8),
        )
    return path


def load_decoded(path: str | os.PathLike[str]) -> Decoded:
    """Read a :class:`Decoded` written by :func:`save_decoded`; InputError if it is not one."""
    import zipfile

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "decoded file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in (*_ARRAYS, "projector_size", "stats") if k not in z.files]
            if missing:
                raise InputError(path, f"not a decoded capture (lacks {', '.join(missing)})")
            arrays = {k: z[k] for k in _ARRAYS}
            stats = json.loads(z["stats"].tobytes().decode("utf-8"))
            ps = z["projector_size"]
            col_level = z["column_level"] if "column_level" in z.files else None
            row_level = z["row_level"] if "row_level" in z.files else None
    except (OSError, ValueError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise InputError(path, f"unreadable decoded file ({exc})") from None
    shape = arrays["column"].shape
    if len(shape) != 2 or any(arrays[k].shape[:2] != shape for k in _ARRAYS):
        raise InputError(path, "decoded arrays disagree in shape")
    return Decoded(
        **arrays, stats=stats, projector_size=(int(ps[0]), int(ps[1])), column_level=col_level, row_level=row_level
    )
