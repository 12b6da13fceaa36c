"""Gray-code decoding: camera images of stripe patterns -> sub-pixel projector coordinates.

In: a :class:`~shared.capture.Capture` (white and black frames, column patterns, optional
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

Images are streamed in small batches of pattern/inverse pairs (about 160 MB of images at a
time), read ahead by a small thread pool (PNG decoding releases the GIL); the per-pixel work
runs in numba kernels. Working memory is about 60 bytes per camera pixel plus one batch of
images: a 15 MP capture peaks near 1.5 GB.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np

from shared.capture import Capture, CodeImage
from shared.errors import InputError
from shared.files import atomic_file
from shared.images import read_grey, read_grey_and_colour

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DecodeParams:
    """Thresholds of the decoder, in grey levels of an 8-bit image (scaled for 16-bit images).

    ``lit_threshold``: least white-black contrast of a projector-lit pixel.
    ``noise``: a bit whose pattern-inverse difference is below this is weak.
    ``weak_ratio``: ... or below this share of the pixel's white-black contrast.
    ``max_drop``: at most this many finest bits are dropped for a coarser code.
    """

    lit_threshold: float = 2.5
    noise: float = 1.5
    weak_ratio: float = 0.12
    max_drop: int = 3


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


# --------------------------------------------------------------------------- numba kernels


@numba.njit(parallel=True, cache=True)
def _bit_planes(pats, refs, bits, thr, kq, signs, weak, q, store_q, m1, m2):  # pragma: no cover
    """Classify a batch (tuple) of k flat bit planes: sign of ``pats[j] - refs[j]`` into ``signs``, and
    ``|pats[j] - refs[j]| < thr`` into ``weak``, at bit ``bits[j]``.

    ``refs`` holds inverse images or the white/black midpoint; with ``store_q`` the differences
    scaled by ``kq`` (127 / full swing) go to ``q[j]`` (int8), and ``m1``/``m2`` keep the smallest
    and second-smallest ``|q|`` seen so far (the confidence). One launch per batch, the bits of a
    batch: launches, not arithmetic, dominate on a busy machine.
    """
    k = len(pats)
    n = pats[0].size
    chunk = 1 << 15
    zero = np.uint16(0)
    for c in numba.prange((n + chunk - 1) // chunk):
        lo = c * chunk
        hi = min(n, lo + chunk)
        sg = signs[lo:hi]
        wk = weak[lo:hi]
        t = thr[lo:hi]
        kk = kq[lo:hi]
        a1 = m1[lo:hi]
        a2 = m2[lo:hi]
        # Bit plane outer, pixel inner over slices indexed from 0: these loops vectorise.
        for j in range(k):
            one = np.uint16(1) << bits[j]
            p = pats[j][lo:hi]
            r = refs[j][lo:hi]
            for i in range(hi - lo):
                d = np.float32(p[i]) - np.float32(r[i])
                sg[i] |= one if d > 0 else zero
                wk[i] |= one if abs(d) < t[i] else zero
            if store_q:
                qq = q[j, lo:hi]
                for i in range(hi - lo):
                    d = np.float32(p[i]) - np.float32(r[i])
                    v = min(max(d * kk[i], np.float32(-127.0)), np.float32(127.0))
                    v += np.float32(0.5) if v >= 0 else np.float32(-0.5)
                    qi = np.int8(v)
                    qq[i] = qi
                    aq = np.uint8(abs(np.int16(qi)))
                    b1 = a1[i]
                    a2[i] = min(a2[i], max(b1, aq))
                    a1[i] = min(b1, aq)


@numba.njit(inline="always")
def _gray_to_binary(g):  # pragma: no cover
    # Prefix XOR from the top bit down (codes have at most 16 bits).
    g ^= g >> 1
    g ^= g >> 2
    g ^= g >> 4
    g ^= g >> 8
    return g


@numba.njit(parallel=True, cache=True)
def _resolve(signs, weak, lit, nbits, lowest, max_level, n_proj, m2, has_q, block, level, conf, centre):  # pragma: no cover
    n = signs.size
    full = (1 << nbits) - 1
    chunk = 1 << 14
    for ch in numba.prange((n + chunk - 1) // chunk):
        lo = ch * chunk
        hi_i = min(n, lo + chunk)
        for ii in range(hi_i - lo):
            _resolve_one(lo + ii, signs, weak, lit, full, lowest, max_level, n_proj, m2, has_q,
                         block, level, conf, centre)


@numba.njit(inline="always")
def _resolve_one(i, signs, weak, lit, full, lowest, max_level, n_proj, m2, has_q, block, level, conf, centre):  # pragma: no cover
    block[i] = -1
    level[i] = -1
    conf[i] = 0.0
    centre[i] = np.nan
    if lit[i]:
        g = np.int64(signs[i])
        w = np.int64(weak[i])
        if (w & full) == 0:
            # Fast path, most pixels: no weak bit.
            b = _gray_to_binary(g >> lowest)
            if (b << lowest) < n_proj:
                block[i] = b
                level[i] = lowest
                c = np.float32(b << lowest) + np.float32(((1 << lowest) - 1) * 0.5)
                centre[i] = min(c, np.float32(n_proj - 1))
                conf[i] = min(np.float32(m2[i]) / np.float32(127.0), np.float32(1.0)) if has_q else np.float32(1.0)
            return
        for L in range(lowest, max_level + 1):
            hi = full & ~((1 << L) - 1)
            wm = w & hi
            ok = False
            if wm == 0:
                ok = True
            elif (wm & (wm - 1)) == 0:
                k = 0
                while (wm >> k) != 1:
                    k += 1
                if k > L:
                    # On the edge of bit k the finer bits read: bit k-1 on, the rest off.
                    fine = ((1 << k) - 1) & hi
                    if (g & fine) == (1 << (k - 1)):
                        ok = True
                elif L == lowest:
                    # The finest captured bit is weak on every one of its own edges (half of
                    # all stripe edges) and nowhere can it err by more than one column: keep
                    # it, so that the sub-pixel step sees these edges.
                    ok = True
            if not ok:
                continue
            b = _gray_to_binary((g & hi) >> L)
            if (b << L) >= n_proj:
                break
            block[i] = b
            level[i] = L
            # Centre of the code's span b*2^L .. (b+1)*2^L - 1, inside the projector.
            c = np.float32(b << L) + np.float32(((1 << L) - 1) * 0.5)
            centre[i] = min(c, np.float32(n_proj - 1))
            if has_q:
                conf[i] = min(np.float32(m2[i]) / np.float32(127.0), np.float32(1.0))
            else:
                conf[i] = 1.0
            break


@numba.njit(parallel=True, cache=True)
def _subpixel_rows(block, level, lowest, nbits, q, out, flags):  # pragma: no cover
    """Interpolate projector columns between stripe edges along each camera row.

    block, level: (H, W) code block and level; out: (H, W) float32 pre-filled with the
    integer decode; flags: (H, W) uint8 set to 1 where a pixel was interpolated.
    """
    H, W = block.shape
    step = 1 << lowest
    for y in numba.prange(H):
        pos = np.empty(W, np.float64)
        val = np.empty(W, np.float64)
        ne = 0
        for x in range(W - 1):
            a = block[y, x]
            b = block[y, x + 1]
            if a < 0 or b < 0 or level[y, x] != lowest or level[y, x + 1] != lowest:
                continue
            if abs(a - b) != 1:
                continue
            diff = (a ^ (a >> 1)) ^ (b ^ (b >> 1))
            k = 0
            while (diff >> k) != 1:
                k += 1
            e = nbits - 1 - (k + lowest)
            qa = np.float64(q[e, y, x])
            qb = np.float64(q[e, y, x + 1])
            den = qa - qb
            t = 0.5
            if den != 0.0:
                t = qa / den
                if t < 0.0:
                    t = 0.0
                elif t > 1.0:
                    t = 1.0
            pos[ne] = x + t
            val[ne] = (min(a, b) + 1) * step - 0.5
            ne += 1
        j = 0
        for x in range(W):
            B = block[y, x]
            if B < 0 or level[y, x] != lowest:
                continue
            while j < ne and pos[j] <= x:
                j += 1
            lo = B * step - 0.5
            hi = (B + 1) * step - 0.5
            v = np.nan
            left_ok = j > 0 and (val[j - 1] == lo or val[j - 1] == hi)
            right_ok = j < ne and (val[j] == lo or val[j] == hi)
            if left_ok and right_ok and val[j - 1] != val[j]:
                v = val[j - 1] + (x - pos[j - 1]) * (val[j] - val[j - 1]) / (pos[j] - pos[j - 1])
            elif left_ok and j > 1 and abs(val[j - 1] - val[j - 2]) == step:
                # Only the left edge bounds this stripe: carry on the slope of the stripe before.
                s = (val[j - 1] - val[j - 2]) / (pos[j - 1] - pos[j - 2])
                v = val[j - 1] + (x - pos[j - 1]) * s
            elif right_ok and j + 1 < ne and abs(val[j + 1] - val[j]) == step:
                s = (val[j + 1] - val[j]) / (pos[j + 1] - pos[j])
                v = val[j] + (x - pos[j]) * s
            if v == v:
                if v < lo:
                    v = lo
                elif v > hi:
                    v = hi
                out[y, x] = v
                flags[y, x] = 1


# --------------------------------------------------------------------------- threads


def kernel_threads() -> int:
    """Threads for the numba kernels: all of numba's, unless the machine is already busy.

    A parallel kernel waits for its slowest worker; on an oversubscribed machine (1-minute load
    average at or above the core count) a descheduled worker stalls every launch, and one
    thread measured faster than two (here: 115 ms against 184 ms for a 1.3 MP decode).
    """
    try:
        busy = os.getloadavg()[0] >= (os.cpu_count() or 1)
    except OSError:
        busy = False
    return 1 if busy else numba.config.NUMBA_NUM_THREADS


@contextmanager
def kernel_thread_scope() -> Iterator[None]:
    """Run the enclosed numba kernels with :func:`kernel_threads` threads, then restore."""
    before = numba.get_num_threads()
    numba.set_num_threads(kernel_threads())
    try:
        yield
    finally:
        numba.set_num_threads(before)


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
        return image
    return read_grey(image, size)


def _pairs(planes: Sequence[_Plane], size: tuple[int, int], pool: ThreadPoolExecutor | None) -> Iterator[
    tuple[_Plane, np.ndarray, np.ndarray | None]
]:
    """Yield (plane, pattern, inverse) while the pool already reads the next pairs."""
    if pool is None or all(not isinstance(x, Path) for e in planes for x in (e.pattern, e.inverse)):
        # In memory: nothing to overlap.
        for e in planes:
            yield e, _load(e.pattern, size, e.pattern_name), (
                _load(e.inverse, size, e.inverse_name) if e.inverse is not None else None
            )
        return

    def submit(e: _Plane):
        fp = pool.submit(_load, e.pattern, size, e.pattern_name)
        fi = pool.submit(_load, e.inverse, size, e.inverse_name) if e.inverse is not None else None
        return fp, fi

    ahead = _batch_size(size, 1) + 2
    pending = [submit(e) for e in planes[:ahead]]
    for k, e in enumerate(planes):
        fp, fi = pending.pop(0)
        if k + ahead < len(planes):
            pending.append(submit(planes[k + ahead]))
        yield e, fp.result(), (fi.result() if fi is not None else None)


@dataclass
class _Axis:
    signs: np.ndarray
    weak: np.ndarray
    q: np.ndarray | None
    m2: np.ndarray | None


class _References:
    """Per-pixel references shared by every bit plane: midpoint, weak-bit thresholds, q scales."""

    def __init__(self, contrast: np.ndarray, mid: np.ndarray, params: DecodeParams, scale: float) -> None:
        self.contrast = contrast
        self.mid = mid
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


#: Bytes of pattern images classified per kernel launch (a batch is held in memory together):
#: few launches matter on a busy machine, memory matters at 15 MP.
_BATCH_BYTES = 160_000_000
_MAX_BATCH = 12


def _batch_size(size: tuple[int, int], itemsize: int) -> int:
    return int(max(1, min(_MAX_BATCH, _BATCH_BYTES // (2 * size[0] * size[1] * itemsize))))


def _decode_axis(
    entries: Sequence[_Plane],
    size: tuple[int, int],
    refs: _References,
    scale: float,
    store_q: bool,
    pool: ThreadPoolExecutor | None,
    tick: Callable[[int], None],
) -> _Axis:
    n = refs.contrast.size
    signs = np.zeros(n, np.uint16)
    weak = np.zeros(n, np.uint16)
    q = np.zeros((len(entries), n), np.int8) if store_q else np.zeros((1, 1), np.int8)
    m1 = np.full(n, 255, np.uint8)
    m2 = np.full(n, 255, np.uint8)
    batch: list[tuple[_Plane, np.ndarray, np.ndarray | None]] = []
    first = 0  # index of the batch's first entry
    batch_size = _batch_size(size, 2 if scale > 1 else 1)

    def flush() -> None:
        nonlocal first
        if not batch:
            return
        with_inverse = batch[0][2] is not None
        thr, kq = refs.thresholds(with_inverse)
        # Tuples of flat views: no copies (numba specialises on the batch length).
        pats = tuple(p.ravel() for _, p, _ in batch)
        if with_inverse:
            ref = tuple(i.ravel() for _, _, i in batch)
        else:
            ref = (refs.mid,) * len(batch)
        bits = np.array([e.bit for e, _, _ in batch], np.uint16)
        qs = q[first : first + len(batch)] if store_q else q
        _bit_planes(pats, ref, bits, thr, kq, signs, weak, qs, store_q, m1, m2)
        first += len(batch)
        tick(sum(1 + (i is not None) for _, _, i in batch))
        batch.clear()

    for entry, pat, inv in _pairs(entries, size, pool):
        if pat.dtype.itemsize * 8 != (16 if scale > 1 else 8):
            raise InputError(entry.pattern_name, f"image is {pat.dtype.itemsize * 8}-bit but the white frame is not")
        if inv is not None and inv.dtype != pat.dtype:
            raise InputError(entry.inverse_name, "inverse image has a different bit depth from its pattern")
        if batch and (batch[0][2] is None) != (inv is None):
            flush()
        batch.append((entry, pat, inv))
        if len(batch) == batch_size:
            flush()
    flush()
    return _Axis(signs, weak, q if store_q else None, m2 if store_q else None)


def decode_capture(
    capture: Capture,
    *,
    progress: Callable[[float], None] | None = None,
    subpixel: bool = True,
    params: DecodeParams | None = None,
    threads: int = 2,
) -> Decoded:
    """Decode a capture into per-pixel projector coordinates.

    Parameters
    ----------
    capture : the validated capture (images are read here; size mismatches raise InputError).
    progress : called with the fraction done in [0, 1] as images are consumed.
    subpixel : interpolate columns between stripe edges (True) or keep integer codes (False).
    params : decoder thresholds (:class:`DecodeParams`).
    threads : image-reading threads (PNG decoding releases the GIL).

    Returns
    -------
    Decoded with (H, W) arrays; see :class:`Decoded`.
    """

    def planes(entries: Sequence[CodeImage]) -> list[_Plane]:
        return [_Plane(e.bit, e.pattern, e.inverse) for e in entries]

    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        fb = pool.submit(read_grey, capture.black)
        white, colour = read_grey_and_colour(capture.white)
        black = fb.result()
        if black.shape != white.shape:
            raise InputError(
                capture.black,
                f"image is {black.shape[1]}x{black.shape[0]}, but the white frame is {white.shape[1]}x{white.shape[0]}",
            )
        return _decode(
            white, black, colour, planes(capture.columns), planes(capture.rows),
            (capture.projector_width, capture.projector_height), str(capture.white), str(capture.black),
            progress, subpixel, params or DecodeParams(), pool,
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
    if colour is None:
        w8 = white if white.dtype == np.uint8 else (white >> 8).astype(np.uint8)
        colour = np.repeat(w8[..., None], 3, axis=2)
    # In memory there is no reading to overlap: no thread pool.
    return _decode(
        white, black, colour, [_Plane(*c) for c in columns], [_Plane(*r) for r in rows],
        tuple(projector_size), "white frame", "black frame", None, subpixel, params or DecodeParams(), None,
    )


def _decode(*args: Any) -> Decoded:
    with kernel_thread_scope():
        return _decode_inner(*args)


def _decode_inner(
    white: np.ndarray,
    black: np.ndarray,
    colour: np.ndarray,
    col_planes: list[_Plane],
    row_planes: list[_Plane],
    projector_size: tuple[int, int],
    white_name: str,
    black_name: str,
    progress: Callable[[float], None] | None,
    subpixel: bool,
    params: DecodeParams,
    pool: ThreadPoolExecutor | None,
) -> Decoded:
    from shared.capture import code_bits

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
    size = (w, h)
    if black.dtype != white.dtype:
        raise InputError(black_name, "black frame has a different bit depth from the white frame")
    tick(2)
    scale = _scale_for(white.dtype)
    contrast = white.astype(np.float32).ravel() - black.astype(np.float32).ravel()
    lit = contrast > params.lit_threshold * scale
    n_lit = int(np.count_nonzero(lit))
    if n_lit == 0:
        peak = float(contrast.max()) if contrast.size else 0.0
        raise InputError(
            white_name,
            f"nothing is lit by the projector: white and black frames differ by at most {peak:.0f} grey "
            f"levels (all-dark capture?)",
        )
    mid = (white.astype(np.float32).ravel() + black.astype(np.float32).ravel()) * np.float32(0.5)
    t_ref = time.perf_counter()
    refs = _References(contrast, mid, params, scale)
    cols = _decode_axis(col_planes, size, refs, scale, True, pool, tick)
    rows = None
    if row_planes:
        rows = _decode_axis(row_planes, size, refs, scale, False, pool, tick)
    del mid, refs
    t_read = time.perf_counter()

    n = h * w
    col_block = np.empty(n, np.int32)
    col_level = np.empty(n, np.int8)
    conf = np.empty(n, np.float32)
    column = np.empty(n, np.float32)
    lowest = min(p.bit for p in col_planes)
    max_level = min(col_bits - 1, lowest + params.max_drop)
    assert cols.q is not None
    _resolve(cols.signs, cols.weak, lit, col_bits, lowest, max_level, pw, cols.m2, True, col_block, col_level, conf,
             column)
    del cols.signs, cols.weak
    n_sub = 0
    t_col = time.perf_counter()
    if subpixel:
        flags = np.zeros((h, w), np.uint8)
        column2d = column.reshape(h, w)
        _subpixel_rows(col_block.reshape(h, w), col_level.reshape(h, w), lowest, col_bits,
                       cols.q.reshape(len(col_planes), h, w), column2d, flags)
        n_sub = int(np.count_nonzero(flags))
        del flags
    del cols
    t_sub = time.perf_counter()

    row = np.full(n, np.nan, np.float32)
    row_level = None
    n_row = 0
    if rows is not None:
        row_block = np.empty(n, np.int32)
        row_level = np.empty(n, np.int8)
        row_conf = np.empty(n, np.float32)
        r_lowest = min(p.bit for p in row_planes)
        r_max = min(row_bits - 1, r_lowest + params.max_drop)
        _resolve(rows.signs, rows.weak, lit, row_bits, r_lowest, r_max, ph,
                 np.zeros(1, np.uint8), False, row_block, row_level, row_conf, row)
        n_row = int(np.count_nonzero(row_block >= 0))
        del row_block, row_conf
    t_end = time.perf_counter()

    n_col = int(np.count_nonzero(col_block >= 0))
    levels = np.bincount(col_level[col_level >= 0].astype(np.int64) - lowest, minlength=params.max_drop + 1)
    stats: dict[str, Any] = {
        "camera_width": w,
        "camera_height": h,
        "projector_width": pw,
        "projector_height": ph,
        "column_bits_captured": len(col_planes),
        "row_bits_captured": len(row_planes),
        "inverse_patterns": all(p.inverse is not None for p in (*col_planes, *row_planes)),
        "lit_pixels": n_lit,
        "column_decoded": n_col,
        "column_decoded_share_of_lit": n_col / n_lit,
        "row_decoded": n_row,
        "subpixel": subpixel,
        "subpixel_interpolated": n_sub,
        "column_bits_dropped_histogram": [int(v) for v in levels],
        "seconds_references": round(t_ref - t0, 4),
        "seconds_read_and_classify": round(t_read - t_ref, 4),
        "seconds_resolve_columns": round(t_col - t_read, 4),
        "seconds_subpixel": round(t_sub - t_col, 4),
        "seconds_resolve_rows": round(t_end - t_sub, 4),
        "seconds_total": round(t_end - t0, 4),
    }
    log.info("decoded %d of %d lit pixels (%.1f %%) in %.2f s", n_col, n_lit, 100 * n_col / n_lit, t_end - t0)
    return Decoded(
        column=column.reshape(h, w),
        row=row.reshape(h, w),
        confidence=conf.reshape(h, w),
        colour=colour,
        lit=lit.reshape(h, w),
        stats=stats,
        projector_size=(pw, ph),
        column_level=col_level.reshape(h, w),
        row_level=row_level.reshape(h, w) if row_level is not None else None,
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
