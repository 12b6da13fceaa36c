"""Range images (depth on the camera grid) coded by a quadtree of surface models, local
prediction (LOCO-I/CALIC-style, a least-squares predictor fitted per band, JPEG-XL's weighted
predictor) or, error-bounded, hierarchical interpolation (SZ3's order), and rANS: codec
``quadtree-lp-10`` (``quadtree-lp-9``'s streams with two more predictors a leaf may choose,
its N and its W neighbour; each band with the check of the samples it decodes to,
:mod:`shared.compress._check`, bound to the band's place and to the header: ``quadtree-lp-8``'s
check was not, so a file whose chunks were swapped or repeated, each with its CRC, decoded to
another image, and one whose header was rewritten with its CRC to another camera or units
decoded with them).

A range image is ``z`` (H, W) float32, depth in the rig's units with NaN holes (the
``range.npz`` a scan writes). Two modes:

- **lossless at a quantum** ``q``: every valid sample decodes to ``float32(round(z / q) * q)``,
  the nearest multiple of ``q`` (e.g. 0.02 mm, a tenth of the scanner's noise);
- **error-bounded** ``max_error`` E: every valid sample decodes within E of the input
  (``|z' - z| <= E``, float32 rounding included).

The validity mask (the non-NaN samples) is always coded exactly. A damaged chunk is refused by
its CRC-32; one rewritten with a fresh CRC by the rANS stream's end state and the 32-bit check
of its decoded samples (the end state alone let 4 % of single-bit flips through on a real
capture). The image is cut into
bands of :data:`BAND_ROWS` rows, each an independent chunk of the container
(:mod:`shared.formats.container`, kind ``range``), coded and decoded on a thread pool by
``nogil`` kernels (:mod:`shared.compress._band` over :mod:`shared.compress._quadtree`, :mod:`shared.compress._lpred`,
:mod:`shared.compress._ls`, :mod:`shared.compress._wp`, :mod:`shared.compress._interp`), so memory stays proportional to a few bands and both cores work.
Files of the earlier codecs (:data:`OLD_CODECS`) are refused by name (re-encode them from the
``range.npz``).

Measured with ``quadtree-lp-10`` (``make bench``; the lossless sizes of ``quadtree-lp-9`` in
brackets): the bunny at 1:1 4.044 (4.180; JPEG-XL effort 7 4.017), the Cyberware dragon scans
4.576 / 4.359 (4.771 / 4.471; JPEG-XL 4.552 / 4.481), the relief at 2:1 1.948 (1.971), the real
captures 8.45-8.99 (8.47-9.10), the synthetic image 5.493 (5.495). Measured with
``quadtree-lp-7`` (the check adds 4 bytes a band of 256 rows)
(``tests/bench/bench_compress.py``, bits per valid sample, lossless at 0.02 mm / within
0.1 mm, effort 1): a simulated carved relief scanned by a 2048x1536 camera over a 1024x768
projector 1.971 / 0.379 (``quadtree-lp-6`` 1.977 / 0.379; JPEG-XL effort 7 2.16, JPEG-LS 2.44,
JPEG-LS NEAR 1.29, SZ3 0.51); the bunny at 2:1 2.722 / 0.742 (``-lp-6`` 2.746; JPEG-XL 2.93,
SZ3 0.86); a real kamino410 capture 8.78 / 5.67 (``-lp-6`` 8.94 / 5.68; JPEG-XL 9.29, JPEG-LS
NEAR 7.20); the Cyberware dragon scan 4.77 / 1.90 (``-lp-6`` 4.86 / 1.94; JPEG-XL 4.55, JPEG-LS
NEAR 3.00); a synthetic image with 0.2 mm white noise 5.49 / 2.25 (JPEG-XL 5.73, SZ3 2.72).
"""

from __future__ import annotations

import io
import logging
import math
import os
import struct
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.compress import _lpred as lp
from shared.compress import _quadtree as qt
from shared.compress._band import decode_band, encode_band
from shared.compress._check import output_check
from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.core.threads import cpu_budget
from shared.formats.container import header_crc, header_int, open_container, write_container, write_stream
from shared.formats.rig import DIST_LENGTHS, MAX_DISTORTION

log = logging.getLogger(__name__)

#: Rows per chunk (a multiple of the quadtree's top block).
BAND_ROWS = 256
CODEC = "quadtree-lp-10"
#: Range codecs of earlier releases, refused by name (their streams are not read any more).
OLD_CODECS = ("quadtree-rans-1", "quadtree-lp-2", "quadtree-lp-3", "quadtree-lp-4", "quadtree-lp-5", "quadtree-lp-6",
              "quadtree-lp-7", "quadtree-lp-8", "quadtree-lp-9")
#: The encoder's options per effort. 1 (the default): every tool but JPEG-XL's weighted
#: predictor (the least-squares predictor included: its bands encode about half as fast,
#: 5 MP per CPU second against 9-10 on the relief and the bunny); 2: the weighted predictor
#: tried too, per lossless band, kept where it saves 0.5 %.
#: Measured A/B in one run with ``quadtree-lp-3`` (MP per CPU second; bits per valid sample at 0.02 mm, effort 1 / 2):
#: the relief at 2:1 2.165 / 2.141, the bunny at 1:1 4.204 / 4.196, the Cyberware dragon scan 0
#: 4.953 / 4.851, the synthetic image 5.512 either way; lossless encoding 15-18 / 6-10, decoding
#: of the bands that take the predictor 61-68 / 28-43 (the targets, 30 MP/s encoding and
#: 100 MP/s decoding on two cores, hold at effort 1 only). Fewer options than these are for the
#: bench's ablation alone (such streams do not decode).
EFFORTS: dict[int, int] = {1: lp.OPT_ALL & ~lp.OPT_WP, 2: lp.OPT_ALL}
#: A band's chunk starts with its packed tables' length and its check.
_BAND_HEAD = struct.Struct("<II")
#: Largest |z / quantum|: fine units (32 per quantum) must stay well inside int64.
_MAX_QUANTA = 2.0**55
#: Most samples a range image may hold (1 GiB as float32; a 150 MP camera's is 151 M): a header
#: claiming more is refused before anything is allocated. A constant band codes in a few
#: bytes, so without it a kilobyte file could claim, and make a worker fill, tens of gigabytes
#: (a decompression bomb); the encoder refuses such images too, so that nothing it writes is
#: refused on reading.
MAX_SAMPLES = 1 << 28


@dataclass
class RangeImage:
    """A range image: ``z`` (H, W) float32 depth in ``units`` with NaN holes; the camera's
    ``K`` (3, 3) and ``dist`` (5,) when known."""

    z: np.ndarray
    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    units: str = "mm"

    @property
    def mask(self) -> np.ndarray:
        return ~np.isnan(self.z)


def _threads() -> int:
    # Bands are coded and decoded on their own, so the stream does not depend on the count.
    return cpu_budget()


@dataclass(frozen=True)
class _Plan:
    lossless: bool
    scale: float  # the quantum (lossless) or the fine unit (bounded), in units
    step: float  # the residual quantum in units
    opts: int  # the encoder's options (:data:`EFFORTS`)


def _effort_opts(effort: int) -> int:
    if isinstance(effort, bool) or effort not in EFFORTS:
        raise InputError("--effort", f"must be one of {sorted(EFFORTS)}, got {effort!r}")
    return EFFORTS[effort]


def _plan(z: np.ndarray, quantum: float | None, max_error: float | None, effort: int = 1) -> _Plan:
    opts = _effort_opts(effort)
    if (quantum is None) == (max_error is None):
        raise InputError("--quantum/--max-error", "give exactly one of a quantum and an error bound")
    zmax, nvalid = qt.finite_abs_max(z)
    zmax = zmax if nvalid else 1.0
    ulp = float(np.spacing(np.float32(max(zmax, 1e-30))))
    if quantum is not None:
        q = float(quantum)
        if not math.isfinite(q) or q <= 0:
            raise InputError("--quantum", f"must be a positive number, got {quantum!r}")
        if q < ulp:
            raise InputError("--quantum", f"{q:g} is finer than float32 can hold at depth {zmax:g} (spacing {ulp:.3g})")
        if zmax / q > _MAX_QUANTA:
            raise InputError("--quantum", f"{q:g} is too fine for depths up to {zmax:g}")
        return _Plan(True, q, q, opts)
    e = float(max_error)  # type: ignore[arg-type]
    if not math.isfinite(e) or e <= 0:
        raise InputError("--max-error", f"must be a positive number, got {max_error!r}")
    # Reconstruction errs by half a step plus half a fine unit, plus float32 rounding (<= ulp/2).
    step = 2.0 * (e - ulp) / (1.0 + 1.0 / qt.FINE)
    if step < 2 * ulp:
        raise InputError("--max-error", f"{e:g} is finer than float32 can hold at depth {zmax:g} (spacing {ulp:.3g})")
    if zmax / step > _MAX_QUANTA:
        raise InputError("--max-error", f"{e:g} is too fine for depths up to {zmax:g}")
    return _Plan(False, step / qt.FINE, step, opts)


def check_range(z: np.ndarray, where: str = "z") -> np.ndarray:
    """``z`` as a C-contiguous (H, W) float32 array; :class:`InputError` for another shape or an
    infinite depth (holes must be NaN)."""
    z = np.asarray(z)
    if z.ndim != 2 or z.shape[0] < 1 or z.shape[1] < 1:
        raise InputError(where, f"a range image must be a 2-D array, got shape {z.shape}")
    if z.size > MAX_SAMPLES:
        raise InputError(where, f"a {z.shape[1]} x {z.shape[0]} range image holds {z.size / 1e6:.0f} M samples, more "
                                f"than the codec's {MAX_SAMPLES / 1e6:.0f} M")
    if not np.issubdtype(z.dtype, np.floating):
        raise InputError(where, f"a range image must be floating point, got {z.dtype}")
    z = np.ascontiguousarray(z, np.float32)
    bad = np.isinf(z)
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise InputError(where, f"infinite depth among the valid samples ({int(bad.sum())} samples, first at row {y}, column {x}); holes must be NaN")
    return z


def check_camera(K: Any, dist: Any, units: Any, where: str) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """A range image's camera as its reader and writer accept it: ``K`` None or (3, 3) float64,
    finite or all NaN (unknown, as a scan without a rig writes it); ``dist`` None or OpenCV's 4,
    5, 8, 12 or 14 finite coefficients (flattened); ``units`` a short printable name (``mm``).
    InputError naming the field otherwise: a header or an npz from elsewhere must not pass a
    camera the triangulation or an export would misread."""
    def numbers(value: Any, name: str) -> np.ndarray:
        try:
            return np.asarray(value, np.float64)
        except (TypeError, ValueError, OverflowError):  # OverflowError: an integer past float's range
            raise InputError(where, f"{name} must be numbers, got {_short(value)}") from None

    if K is not None:
        K = numbers(K, "K")
        if K.shape != (3, 3) or not (np.isfinite(K).all() or np.isnan(K).all()):
            raise InputError(where, f"K must be a 3 x 3 matrix of finite numbers (or all NaN: unknown), got {_short(K.tolist())}")
    if dist is not None:
        dist = numbers(dist, "dist").ravel()
        if dist.size not in DIST_LENGTHS or not np.isfinite(dist).all() or np.abs(dist).max() > MAX_DISTORTION:
            raise InputError(where, f"dist must be OpenCV's {', '.join(map(str, DIST_LENGTHS))} finite distortion coefficients "
                                    f"(at most {MAX_DISTORTION:g} in magnitude), got {_short(dist.tolist())}")
    # the rig's rule (a scan writes its rig's units), printable: units go into PLY headers' comments
    if not (isinstance(units, str) and 0 < len(units) <= 16 and units.isprintable()):
        raise InputError(where, f"units must be a short printable name such as mm, got {_short(units)}")
    return K, dist, units


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _band_key(i: int, header: int) -> int:
    """What band ``i``'s check is XORed with, ``header`` the CRC-32 of the container's header
    (:func:`shared.formats.container.header_crc`): a different 32-bit value for every band (an
    odd multiplier is a bijection modulo 2**32) and every header, so that a band's chunk in
    another band's place (a writer's mix-up, each chunk with its CRC) and a header rewritten
    with its CRC fail the check of the decoded samples: another scale changes the samples
    themselves, but another camera (``K``, ``dist``) or ``units`` would have decoded silently."""
    return ((i * 0x9E3779B1) ^ header) & 0xFFFFFFFF


def _encode_band(zb: np.ndarray, plan: _Plan, i: int, header: int) -> bytes:
    t, valid = qt.quantise(zb, plan.scale, plan.lossless)
    tables, words, check = encode_band(t, valid, plan.lossless, plan.opts, plan.scale)
    # the check of the samples band i decodes to (:mod:`._check`) after the tables' length
    return _BAND_HEAD.pack(len(tables), check ^ _band_key(i, header)) + tables.tobytes() + words.astype("<u2").tobytes()


def _bands(h: int) -> list[tuple[int, int]]:
    return [(y, min(y + BAND_ROWS, h)) for y in range(0, h, BAND_ROWS)]


def _encoded_chunks(z: np.ndarray, plan: _Plan, header: int) -> Iterator[bytes]:
    bands = _bands(z.shape[0])
    with ThreadPoolExecutor(_threads()) as pool:
        # At most two bands per thread in flight: memory stays a few bands' worth.
        window = 2 * _threads()
        futures = [pool.submit(_encode_band, z[a:b], plan, i, header) for i, (a, b) in enumerate(bands[:window])]
        for i in range(len(bands)):
            nxt = i + window
            if nxt < len(bands):
                a, b = bands[nxt]
                futures.append(pool.submit(_encode_band, z[a:b], plan, nxt, header))
            yield futures[i].result()
            futures[i] = None  # type: ignore[call-overload]


def _meta(img: RangeImage, z: np.ndarray, plan: _Plan, quantum: float | None, max_error: float | None) -> dict[str, Any]:
    h, w = z.shape
    return {
        "codec": CODEC,
        "width": w,
        "height": h,
        "band_rows": BAND_ROWS,
        "chunks": len(_bands(h)),
        "units": img.units,
        "mode": "lossless" if plan.lossless else "bounded",
        "quantum": quantum,
        "max_error": max_error,
        "scale": plan.scale,
        "fine_shift": qt.F_SHIFT,
        "valid": int(np.count_nonzero(~np.isnan(z))),
        "K": None if img.K is None else np.asarray(img.K, np.float64).tolist(),
        "dist": None if img.dist is None else np.asarray(img.dist, np.float64).ravel().tolist(),
    }


def write_range(path: str | os.PathLike[str], img: RangeImage, *, quantum: float | None = None,
                max_error: float | None = None, effort: int = 1) -> int:
    """Code ``img`` into the container file ``path`` (atomically); returns its size in bytes.

    Exactly one of ``quantum`` (lossless at that quantum, in ``img.units``) and ``max_error``
    (every valid sample within it, in ``img.units``) is given. ``effort`` 1 or 2 (:data:`EFFORTS`:
    2 is up to 2 % smaller lossless, and slower to code and to decode).
    """
    z = check_range(img.z)
    check_camera(img.K, img.dist, img.units, "range image")
    plan = _plan(z, quantum, max_error, effort)
    meta = _meta(img, z, plan, quantum, max_error)
    return write_container(path, "range", meta, _encoded_chunks(z, plan, header_crc(meta)))


def encode_range(img: RangeImage, *, quantum: float | None = None, max_error: float | None = None,
                 effort: int = 1) -> bytes:
    """:func:`write_range` into memory: the container's bytes."""
    z = check_range(img.z)
    check_camera(img.K, img.dist, img.units, "range image")
    plan = _plan(z, quantum, max_error, effort)
    buf = io.BytesIO()
    meta = _meta(img, z, plan, quantum, max_error)
    write_stream(buf, "range", meta, _encoded_chunks(z, plan, header_crc(meta)))
    return buf.getvalue()


def _check_meta(meta: dict[str, Any], where: str) -> tuple[int, int, int, bool, float]:
    codec = meta.get("codec")
    if codec in OLD_CODECS:
        raise InputError(where, f"range codec {codec!r} is not supported (this build reads {CODEC!r}; re-encode the range image)")
    try:
        w, h, band = header_int(meta, "width"), header_int(meta, "height"), header_int(meta, "band_rows")
        lossless = meta["mode"] == "lossless"
        scale = float(meta["scale"])
        ok = (meta.get("codec") == CODEC and header_int(meta, "fine_shift") == qt.F_SHIFT and w > 0 and h > 0
              and band > 0 and band % qt.TOP == 0 and meta["chunks"] == -(-h // band) and math.isfinite(scale)
              and scale > 0 and meta["mode"] in ("lossless", "bounded"))
    except (KeyError, TypeError, ValueError, OverflowError):  # OverflowError: float() of a 400-digit integer
        ok = False
    if not ok:
        raise InputError(where, "corrupt or unsupported range header")
    if w * h > MAX_SAMPLES:
        claim = f"a {w} x {h} image ({w * h / 1e6:.0f} M samples)" if w * h < 10**15 else "an image of over 10^15 samples"
        raise InputError(where, f"corrupt or hostile range header: it claims {claim}, more than the codec's "
                                f"{MAX_SAMPLES / 1e6:.0f} M")
    return w, h, band, lossless, scale


def read_range(source: str | os.PathLike[str] | bytes) -> RangeImage:
    """Decode a range container (a file or its bytes) into a :class:`RangeImage`."""
    where = "<bytes>" if isinstance(source, bytes | bytearray | memoryview) else str(source)
    header, chunks = open_container(source, kind="range")
    w, h, band, lossless, scale = _check_meta(header.meta, where)
    K, dist, units = check_camera(header.meta.get("K"), header.meta.get("dist"), header.meta.get("units", "mm"),
                                  f"{where}: corrupt range header")
    z = np.empty((h, w), np.float32)

    def decode(i: int, payload: bytes) -> None:
        a, b = i * band, min((i + 1) * band, h)
        start = _BAND_HEAD.size  # the tables' length and the band's check come first
        if len(payload) < start:
            raise InputError(where, f"corrupt chunk {i} (too short)")
        nt, check = _BAND_HEAD.unpack_from(payload)
        if start + nt > len(payload) or (len(payload) - start - nt) % 2:
            raise InputError(where, f"corrupt chunk {i} (bad table length)")
        tables = np.frombuffer(payload, np.uint8, nt, start)
        words = np.frombuffer(payload, "<u2", (len(payload) - start - nt) // 2, start + nt).astype(np.uint16)
        if decode_band(tables, words, b - a, w, lossless, scale, z[a:b]) != 0:
            raise InputError(where, f"corrupt chunk {i} (the coded stream does not decode)")
        if output_check(z[a:b].view(np.uint32)) ^ _band_key(i, header.crc) != check:
            raise InputError(where, f"corrupt chunk {i} (its decoded samples fail their check)")

    with ThreadPoolExecutor(_threads()) as pool:
        futures = []
        for i, payload in enumerate(chunks):
            futures.append(pool.submit(decode, i, payload))
            if len(futures) > 2 * _threads():
                futures.pop(0).result()
        for f in futures:
            f.result()
    return RangeImage(z, K, dist, units)


def expected_lossless(z: np.ndarray, quantum: float) -> np.ndarray:
    """What lossless mode reproduces: ``float32(round(z / q) * q)`` with NaN kept (the reference of tests)."""
    z = np.asarray(z, np.float32)
    return (np.rint(z.astype(np.float64) / quantum) * quantum).astype(np.float32)


def load_range_npz(path: str | os.PathLike[str]) -> RangeImage:
    """A scan's ``range.npz`` (``z``, ``K``, ``dist``, ``units``) as a :class:`RangeImage`."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "a folder, not a range.npz file" if p.is_dir() else "no such file")
    try:
        with np.load(p, allow_pickle=False) as d:
            if "z" not in d:
                raise InputError(p, 'no "z" array: not a range.npz of a scan')
            z = np.asarray(d["z"])
            K = np.asarray(d["K"], np.float64) if "K" in d else None
            dist = np.asarray(d["dist"], np.float64) if "dist" in d else None
            units = str(d["units"]) if "units" in d else "mm"
    except InputError:
        raise
    except Exception as exc:  # zipfile/np.load raise many types for a damaged file
        raise InputError(p, f"unreadable range.npz ({type(exc).__name__}: {exc})") from None
    K, dist, units = check_camera(K, dist, units, str(p))
    return RangeImage(check_range(z, f"{p}: z"), K, dist, units)


def save_range_npz(path: str | os.PathLike[str], img: RangeImage) -> Path:
    """Write ``range.npz`` as a scan does (``z`` float32 NaN holes, ``K``, ``dist``, ``units``), atomically."""
    p = Path(path)
    with atomic_file(p, suffix=".tmp.npz") as tmp:
        np.savez(
            tmp,
            z=np.asarray(img.z, np.float32),
            K=np.asarray(img.K if img.K is not None else np.full((3, 3), np.nan), np.float64),
            dist=np.asarray(img.dist if img.dist is not None else np.zeros(5), np.float64),
            units=np.array(img.units),
        )
    return p
