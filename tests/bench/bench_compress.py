"""Bench of range compression: our quadtree range codec and octree cloud codec against the
codecs people would otherwise use, side by side in one run on the same data.

First one table (:func:`section_table`, issue 26): every codec and peer on every range image --
the virtual rig's detailed scenes (a carved relief, bunny, fandisk, spot) scanned by a 2048x1536
camera over projectors of 1:1, 2:1 and 4:1 sampling (:mod:`tests.support.range_scenes`, rendered
and scanned once, then cached in a temp folder), the five real captures, two real Cyberware
scans of the Stanford dragon, and the synthetic image -- with our rank per image and the
targets (lossless <= 0.95x the better of JPEG-XL e7 and JPEG-LS; within 0.1 mm <= 0.9x the
better of JPEG-LS NEAR and SZ3); the ones not reached are listed with their figures.

Range images in detail: a synthetic 2048x1536 scan with 0.2 mm depth noise (:func:`tests.support.range_images.synthetic_range`)
and a synthetic 15 MP image. Per codec: bits per valid sample, the largest error over every valid sample, encode
and decode megapixels per second (of the whole image), and the distance from the noise floor
log2(sigma / step) + 2.05, with sigma from plane-fit residuals. Peers (imagecodecs): JPEG-XL
lossless at efforts 1/3/7, JPEG-LS lossless and NEAR, PNG-16, LERC, zstd of the quantised
depth; SZ3 (pysz). 16-bit codecs see the quantised depth as uint16 with 0 for holes, so they
cover 65535 quanta; where the depth range needs more they are "n/a".

Clouds: the synthetic scan as 2.6 M points, geometry only, at 0.1 and 0.5 mm grids: ours
against Draco (DracoPy, quantisation bits giving a grid at least as fine) and LAZ
(laspy + lazrs at the grid's scale, in scan order), bits per point and decode M points/s.

Then which surface model the depth wants (depth, log-depth or inverse depth), measured on
blocks of the synthetic and real images. Targets (issue 11) are printed beside our figures.
"""

from __future__ import annotations

import io
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from shared.compress.cloud import decode_cloud, encode_cloud
from shared.compress.range import RangeImage, encode_range, expected_lossless, load_range_npz, read_range
from shared.formats.ply import iter_ply_records
from tests.support import real_ranges
from tests.support.range_images import synthetic_range
from tests.support.range_scenes import BENCH_IMAGES, bench_range, dragon_range

Q = 0.02
BOUNDS = (0.1, 0.5, 1.0)
TARGETS_BOUNDED = {0.1: 2.4, 0.5: 0.6, 1.0: 0.25}


class Clock(tuple):
    """(wall seconds, CPU seconds of every thread of this process) of the fastest run."""

    @property
    def wall(self) -> float:
        return self[0]

    @property
    def cpu(self) -> float:
        return self[1]


#: Repetitions of a timed call beyond its ``reps`` while its runs took less than this many seconds
#: in all, up to :data:`TIMED_MAX` runs. On this shared host other load can slow every run of a
#: short window (the synthetic image's lossless decode, best of 3 after a warm-up: 39 ms in a
#: bench run, 28.5-30.3 ms in four quiet runs minutes later), so a call of tens of milliseconds
#: gets enough runs to meet a quiet moment; a slow one (JPEG-XL effort 7, seconds a run) keeps
#: its count.
TIMED_BUDGET = 1.0
TIMED_MAX = 20


def _best(fn: Callable[[], object], reps: int) -> tuple[Clock, object]:
    """Fastest of at least ``reps`` runs after a warm-up (more, as :data:`TIMED_BUDGET` says;
    none with ``reps`` 0, where only the result is wanted):
    the machine is shared, so the CPU seconds (threads of this process only) are printed too --
    other engineers' load inflates the wall. Ours and every peer are timed alike."""
    out = fn()
    best = (math.inf, math.inf)
    spent = 0.0
    runs = 0
    while runs < reps or (0 < reps and spent < TIMED_BUDGET and runs < TIMED_MAX):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        t = (time.perf_counter() - t0, time.process_time() - c0)
        best = min(best, t)
        spent += t[0]
        runs += 1
    return Clock(best), out


def noise_sigma(z: np.ndarray, b: int = 16) -> float:
    """Depth noise from plane fits: the median RMS residual of fully valid b x b blocks (dof-corrected)."""
    h, w = (z.shape[0] // b) * b, (z.shape[1] // b) * b
    blocks = z[:h, :w].reshape(h // b, b, w // b, b).transpose(0, 2, 1, 3).reshape(-1, b * b).astype(np.float64)
    blocks = blocks[~np.isnan(blocks).any(axis=1)]
    yy, xx = np.mgrid[0:b, 0:b]
    A = np.stack([np.ones(b * b), xx.ravel(), yy.ravel()], 1)
    coef, *_ = np.linalg.lstsq(A, blocks.T, rcond=None)
    res = blocks.T - A @ coef
    rms = np.sqrt((res**2).sum(0) / (b * b - 3))
    return float(np.median(rms))


def floor_bits(sigma: float, step: float) -> float | None:
    """The entropy of Gaussian noise sigma at quantum step; the formula holds for sigma >~ step / 2."""
    return math.log2(sigma / step) + 2.05 if sigma >= step / 2 else None


# ------------------------------------------------------------------------------- range codecs
# Each returns (compressed bytes, decoded float64 depth on the valid samples or None, enc s, dec s).


def _quantised16(z: np.ndarray, step: float, near: int = 0) -> np.ndarray | None:
    """Depth quantised at ``step`` as uint16, holes 0, valid samples from 2 near + 1 (so that a
    near-lossless codec erring by ``near`` still tells holes from samples)."""
    m = ~np.isnan(z)
    zmin = float(np.nanmin(z))
    q = np.zeros(z.shape, np.int64)
    q[m] = np.rint((z[m].astype(np.float64) - zmin) / step).astype(np.int64) + 2 * near + 1
    return q.astype(np.uint16) if q.max() < 65536 else None


def _from16(q: np.ndarray, z: np.ndarray, step: float, near: int = 0) -> np.ndarray:
    zmin = float(np.nanmin(z))
    m = ~np.isnan(z)
    if not np.array_equal(q > near, m):
        raise AssertionError("peer lost the mask")
    return (q[m].astype(np.float64) - 2 * near - 1) * step + zmin


def ours_lossless(z: np.ndarray, q: float, reps: int) -> tuple[int, np.ndarray, float, float]:
    img = RangeImage(z)
    te, blob = _best(lambda: encode_range(img, quantum=q), reps)
    td, out = _best(lambda: read_range(blob), reps)
    m = ~np.isnan(z)
    assert np.array_equal(np.isnan(out.z), ~m) and np.array_equal(out.z[m], expected_lossless(z, q)[m])
    return len(blob), out.z[m].astype(np.float64), te, td


def ours_bounded(z: np.ndarray, e: float, reps: int) -> tuple[int, np.ndarray, float, float]:
    img = RangeImage(z)
    te, blob = _best(lambda: encode_range(img, max_error=e), reps)
    td, out = _best(lambda: read_range(blob), reps)
    assert np.array_equal(np.isnan(out.z), np.isnan(z))
    return len(blob), out.z[~np.isnan(z)].astype(np.float64), te, td


def peer16(encode: Callable[[np.ndarray], bytes], decode: Callable[[bytes], np.ndarray], z: np.ndarray, step: float,
           reps: int, near: int = 0) -> tuple[int, np.ndarray, float, float] | None:
    q = _quantised16(z, step, near)
    if q is None:
        return None
    te, blob = _best(lambda: encode(q), reps)
    td, back = _best(lambda: decode(blob), reps)
    return len(blob), _from16(np.asarray(back).reshape(q.shape), z, step, near), te, td


def peer_lerc(z: np.ndarray, maxerr: float, reps: int) -> tuple[int, np.ndarray, float, float]:
    import imagecodecs

    m = ~np.isnan(z)
    data = np.where(m, z, 0).astype(np.float32)
    te, blob = _best(lambda: imagecodecs.lerc_encode(data, level=maxerr, masks=m), reps)
    td, back = _best(lambda: imagecodecs.lerc_decode(blob, masks=True), reps)
    arr, masks = back
    assert np.array_equal(np.asarray(masks, bool), m)
    return len(blob), np.asarray(arr)[m].astype(np.float64), te, td


def peer_sz3(z: np.ndarray, maxerr: float, reps: int) -> tuple[int, np.ndarray, float, float] | None:
    try:
        from pysz import sz, szConfig, szErrorBoundMode
    except ImportError:
        return None
    import imagecodecs

    m = ~np.isnan(z)
    # SZ3 has no holes: fill them with the row's previous valid depth (no jumps to code) and
    # send the mask beside it, zstd-packed.
    filled = z.copy()
    idx = np.where(m, np.arange(z.shape[1])[None, :], 0)
    np.maximum.accumulate(idx, axis=1, out=idx)
    filled = np.take_along_axis(np.where(m, z, np.nanmean(z)), idx, axis=1).astype(np.float32)
    cfg = szConfig()
    cfg.errorBoundMode = szErrorBoundMode.ABS
    cfg.absErrorBound = maxerr

    def enc() -> tuple[np.ndarray, bytes]:
        c, _ = sz.compress(filled, cfg)
        return c, imagecodecs.zstd_encode(np.packbits(m).tobytes(), level=9)

    te, (blob, mblob) = _best(enc, reps)
    td, (back, _) = _best(lambda: sz.decompress(blob, np.float32, filled.shape), reps)
    mask = np.unpackbits(np.frombuffer(imagecodecs.zstd_decode(mblob), np.uint8))[: z.size].reshape(z.shape).astype(bool)
    assert np.array_equal(mask, m)
    return blob.nbytes + len(mblob), back[m].astype(np.float64), te, td


def range_rows(z: np.ndarray, quick: bool = False) -> list[tuple]:
    """Every codec on ``z``: rows (name, the step of its noise floor, bits per valid sample, max
    error, encode and decode MP/s wall, encode and decode MP per CPU second). Error-bounded E
    is compared with the floor at step 2E."""
    import imagecodecs

    m = ~np.isnan(z)
    nvalid = int(m.sum())
    zv = z[m].astype(np.float64)
    mp = z.size / 1e6
    rows: list[tuple] = []
    step = Q

    def add(name: str, r: tuple[int, np.ndarray, float, float] | None) -> None:
        if r is None:
            rows.append((name, step, None, None, math.nan, math.nan, math.nan, math.nan))
            return
        size, dec, te, td = r
        rows.append((name, step, size * 8 / nvalid, float(np.abs(dec - zv).max()), mp / te.wall, mp / td.wall,
                     mp / max(te.cpu, 1e-9), mp / max(td.cpu, 1e-9)))

    reps = 1 if quick else 3
    add(f"ours lossless q={Q}", ours_lossless(z, Q, reps))
    jxl_d = imagecodecs.jpegxl_decode
    efforts = (1, 3) if quick else (1, 3, 7)
    for e in efforts:
        add(f"JPEG-XL lossless e{e} q={Q}",
            peer16(lambda a, e=e: imagecodecs.jpegxl_encode(a, lossless=True, effort=e), jxl_d, z, Q, 1 if e == 7 else reps))
    add(f"JPEG-LS lossless q={Q}", peer16(lambda a: imagecodecs.jpegls_encode(a, level=0), imagecodecs.jpegls_decode, z, Q, reps))
    add(f"PNG-16 q={Q}", peer16(lambda a: imagecodecs.png_encode(a, level=9), imagecodecs.png_decode, z, Q, reps))
    add(f"zstd-19 of q={Q} depth", peer16(lambda a: imagecodecs.zstd_encode(a.tobytes(), level=19),
                                      lambda b: np.frombuffer(imagecodecs.zstd_decode(b), np.uint16), z, Q, reps))
    add(f"LERC maxZErr={Q / 2}", peer_lerc(z, Q / 2, reps))
    add(f"SZ3 abs {Q / 2}", peer_sz3(z, Q / 2, reps))
    for e in BOUNDS:
        step = 2 * e
        add(f"ours max-error {e}", ours_bounded(z, e, reps))
        # JPEG-LS NEAR=2 on depth quantised at e / 2.5: |error| <= 2 steps + half a step = e.
        add(f"JPEG-LS NEAR=2 (step {e / 2.5:g})", peer16(lambda a: imagecodecs.jpegls_encode(a, level=2),
                                                        imagecodecs.jpegls_decode, z, e / 2.5, reps, near=2))
        add(f"JPEG-XL e3 of depth quantised at {2 * e:g}",
            peer16(lambda a: imagecodecs.jpegxl_encode(a, lossless=True, effort=3), jxl_d, z, 2 * e, reps))
        add(f"LERC maxZErr={e}", peer_lerc(z, e, reps))
        add(f"SZ3 abs {e}", peer_sz3(z, e, reps))
    return rows


def print_rows(title: str, z: np.ndarray, rows: list, sigma: float) -> dict[str, float | None]:
    print(f"\n{title}: {z.shape[1]}x{z.shape[0]}, {100 * np.mean(~np.isnan(z)):.1f} % valid, noise sigma {sigma:.3f} mm (plane fits)")
    print(f"  {'codec':44s} {'bits/valid':>10s} {'floor':>6s} {'vs floor':>8s} {'max err':>9s} {'enc MP/s':>9s} {'dec MP/s':>9s}"
          f" {'enc MP/cpu-s':>12s} {'dec MP/cpu-s':>12s}")
    ours: dict[str, float | None] = {}
    for name, step, bits, err, enc, dec, enc_cpu, dec_cpu in rows:
        fl = floor_bits(sigma, step)
        if bits is None:
            print(f"  {name:44s} {'n/a (more than 65535 quanta)':>30s}")
            continue
        vs = f"{100 * (bits / fl - 1):+7.1f}%" if fl else "     n/a"
        fls = f"{fl:6.2f}" if fl else "   n/a"
        print(f"  {name:44s} {bits:10.3f} {fls} {vs} {err:9.4f} {enc:9.1f} {dec:9.1f} {enc_cpu:12.1f} {dec_cpu:12.1f}")
        if name.startswith("ours"):
            ours[name] = bits
            ours[name + " enc"] = enc
            ours[name + " dec"] = dec
            ours[name + " enc cpu"] = enc_cpu
            ours[name + " dec cpu"] = dec_cpu
            ours[name + " floor"] = fl
    return ours


def verdict(what: str, value: float, target: float, higher_is_better: bool = False) -> None:
    ok = value >= target if higher_is_better else value <= target
    rel = ">=" if higher_is_better else "<="
    print(f"  target {what}: {value:.3f} ({rel} {target:g}) {'reached' if ok else 'NOT reached'}")


def section_synthetic() -> None:
    z = synthetic_range(1536, 2048, 0.2, seed=0)
    sigma = noise_sigma(z)
    ours = print_rows("synthetic range image", z, range_rows(z), sigma)
    name = f"ours lossless q={Q}"
    fl = ours[name + " floor"]
    assert fl is not None
    verdict(f"lossless q={Q} within 5 % of the floor {fl:.2f} (ratio)", ours[name] / fl, 1.05)  # type: ignore[operator]
    verdict(f"lossless q={Q} encode MP/s (wall, 2 threads)", ours[name + " enc"], 30, higher_is_better=True)  # type: ignore[arg-type]
    # Extrapolated, not measured: both cores to ourselves would give about twice the MP per CPU
    # second (bands are independent); the wall figure above is the measured one.
    verdict(f"lossless q={Q} encode MP/s on 2 idle cores, extrapolated (2 x MP/cpu-s)", 2 * ours[name + " enc cpu"], 30,  # type: ignore[operator]
            higher_is_better=True)
    for e, t in TARGETS_BOUNDED.items():
        verdict(f"max-error {e} bits/sample", ours[f"ours max-error {e}"], t)  # type: ignore[arg-type]
    for key in (name, "ours max-error 0.1"):
        verdict(f"decode MP/s, {key[5:]} (wall, 2 threads)", ours[key + " dec"], 100, higher_is_better=True)  # type: ignore[arg-type]
        verdict(f"decode MP/s, {key[5:]} on 2 idle cores, extrapolated (2 x MP/cpu-s)", 2 * ours[key + " dec cpu"], 100,  # type: ignore[operator]
                higher_is_better=True)


def _real_capture_ranges() -> dict[str, Path]:
    cache = Path(tempfile.gettempdir()) / "graylight-bench-real-ranges"
    files = {n: cache / n / "range.npz" for n in real_ranges.CAPTURES}
    if not all(p.is_file() for p in files.values()):
        print("calibrating the real session and scanning its five captures (kept for later runs) ...", flush=True)
        files = real_ranges.scan_real_ranges(cache)
    return files


def table_images() -> list[tuple[str, np.ndarray]]:
    """Every range image of the table: the virtual rig's detailed scenes at 1:1, 2:1 and 4:1
    sampling (cached in a temp folder), the real captures, real Cyberware scans, the synthetic image."""
    out: list[tuple[str, np.ndarray]] = []
    for name, scene, ratio in BENCH_IMAGES:
        out.append((f"sim {name} (2048x1536)", load_range_npz(bench_range(scene, ratio)).z))
    if real_ranges.available():
        for name, path in _real_capture_ranges().items():
            out.append((f"real {name} (kamino410)", load_range_npz(path).z))
    for k in (0, 5):
        out.append(dragon_range(k))
    out.append(("synthetic 0.2 mm noise", synthetic_range(1536, 2048, 0.2, seed=0)))
    return out


#: The table's codecs: (group, name). Group "L": lossless at Q (or within Q / 2); "B": within 0.1 mm.
TABLE_CODECS = [("L", "ours"), ("L", "ours effort 2"), ("L", "JPEG-XL e7"), ("L", "JPEG-LS"), ("L", "PNG-16"), ("L", f"LERC {Q / 2:g}"),
                ("L", f"SZ3 {Q / 2:g}"), ("B", "ours"), ("B", "JPEG-LS NEAR"), ("B", "SZ3"), ("B", "LERC"),
                ("B", "JPEG-XL e3 q0.2")]


def table_row(z: np.ndarray) -> tuple[dict[tuple[str, str], float | None], dict[str, float]]:
    """Bits per valid sample of every codec of :data:`TABLE_CODECS` on ``z`` (None: n/a), and our
    encode/decode MP per CPU second."""
    import imagecodecs

    m = ~np.isnan(z)
    nv = int(m.sum())
    bits: dict[tuple[str, str], float | None] = {}

    def put(key: tuple[str, str], r: tuple | None) -> None:
        bits[key] = None if r is None else r[0] * 8 / nv

    mp = z.size / 1e6
    lo = ours_lossless(z, Q, 1)
    hi = ours_bounded(z, 0.1, 1)
    assert np.abs(hi[1] - z[m]).max() <= 0.1
    put(("L", "ours"), lo)
    put(("B", "ours"), hi)
    # effort 2 (the weighted predictor tried per lossless band): its size only, the speed is effort 1's
    bits[("L", "ours effort 2")] = len(encode_range(RangeImage(z), quantum=Q, effort=2)) * 8 / nv
    speed = {"enc L": mp / lo[2].cpu, "dec L": mp / lo[3].cpu, "enc B": mp / hi[2].cpu, "dec B": mp / hi[3].cpu}
    jd = imagecodecs.jpegxl_decode
    put(("L", "JPEG-XL e7"), peer16(lambda a: imagecodecs.jpegxl_encode(a, lossless=True, effort=7), jd, z, Q, 0))
    put(("L", "JPEG-LS"), peer16(lambda a: imagecodecs.jpegls_encode(a, level=0), imagecodecs.jpegls_decode, z, Q, 0))
    put(("L", "PNG-16"), peer16(lambda a: imagecodecs.png_encode(a, level=9), imagecodecs.png_decode, z, Q, 0))
    put(("L", f"LERC {Q / 2:g}"), peer_lerc(z, Q / 2, 0))
    put(("L", f"SZ3 {Q / 2:g}"), peer_sz3(z, Q / 2, 0))
    put(("B", "JPEG-LS NEAR"), peer16(lambda a: imagecodecs.jpegls_encode(a, level=2), imagecodecs.jpegls_decode, z,
                                      0.1 / 2.5, 0, near=2))
    put(("B", "SZ3"), peer_sz3(z, 0.1, 0))
    put(("B", "LERC"), peer_lerc(z, 0.1, 0))
    put(("B", "JPEG-XL e3 q0.2"), peer16(lambda a: imagecodecs.jpegxl_encode(a, lossless=True, effort=3), jd, z, 0.2, 0))
    return bits, speed


def _ratio(ours: float | None, *peers: float | None) -> float | None:
    known = [p for p in peers if p is not None]
    return None if ours is None or not known else ours / min(known)


def section_table() -> None:
    """Every codec on every range image in one table (bits per valid sample), our rank per image
    in each group, and the issue-26 targets: lossless at q 0.02 at most 0.95x the smaller of
    JPEG-XL e7 and JPEG-LS, within 0.1 mm at most 0.9x the smaller of JPEG-LS NEAR and SZ3."""
    print(f"\nrange images, bits per valid sample. L: lossless at q={Q} (LERC, SZ3 within {Q / 2:g});"
          " B: within 0.1 mm (JPEG-LS NEAR=2 on depth at 0.04, JPEG-XL e3 on depth at 0.2)."
          " Peers code the depth as uint16 (n/a beyond 65535 quanta) or float with a zstd mask.")
    print("building the images (rendered and scanned once, then cached) ...", flush=True)
    images = table_images()
    heads = [f"{g}:{n}" for g, n in TABLE_CODECS]
    print(f"  {'image':40s} {'valid':>6s} " + " ".join(f"{h[:13]:>13s}" for h in heads)
          + f" {'rank L':>6s} {'rank B':>6s} {'L/target':>9s} {'B/target':>9s} {'enc/dec MP/cpu-s L':>19s} {'B':>11s}")
    misses: list[str] = []
    notes: list[str] = []
    for name, z in images:
        bits, speed = table_row(z)
        ranks = {}
        for g in "LB":
            vals = sorted(v for (gg, n), v in bits.items() if gg == g and v is not None and n != "ours effort 2")
            ranks[g] = 1 + vals.index(bits[(g, "ours")])  # type: ignore[arg-type]
        rl = _ratio(bits[("L", "ours")], bits[("L", "JPEG-XL e7")], bits[("L", "JPEG-LS")])
        rb = _ratio(bits[("B", "ours")], bits[("B", "JPEG-LS NEAR")], bits[("B", "SZ3")])
        cells = " ".join(f"{'n/a':>13s}" if bits[k] is None else f"{bits[k]:13.3f}" for k in TABLE_CODECS)
        fl = "n/a" if rl is None else f"{rl / 0.95:.3f}"
        fb = "n/a" if rb is None else f"{rb / 0.9:.3f}"
        print(f"  {name[:40]:40s} {100 * np.mean(~np.isnan(z)):5.1f}% {cells} {ranks['L']:6d} {ranks['B']:6d} {fl:>9s} {fb:>9s}"
              f" {speed['enc L']:9.0f}/{speed['dec L']:<9.0f} {speed['enc B']:5.0f}/{speed['dec B']:<5.0f}", flush=True)
        if rl is not None and rl > 0.95:
            r2 = _ratio(bits[("L", "ours effort 2")], bits[("L", "JPEG-XL e7")], bits[("L", "JPEG-LS")])
            misses.append(f"{name}: lossless {rl:.3f} (effort 2: {r2:.3f}) x the better of JPEG-XL e7 / JPEG-LS "
                          "(target 0.95)")
        if rb is not None and rb > 0.9:
            misses.append(f"{name}: 0.1 mm {rb:.3f} x the better of JPEG-LS NEAR / SZ3 (target 0.9)")
        if name.startswith("synthetic") and rl is not None:
            # Its noise is white and Gaussian (0.2 mm): no coder goes below the noise's entropy
            # given the surface, so the target's distance from that floor is the budget left
            # for coding the surfaces, their rims and the mask.
            fl = floor_bits(0.2, Q)
            target = 0.95 * bits[("L", "ours")] / rl  # type: ignore[operator]
            notes.append(f"{name}: the noise's own entropy (sigma 0.2 mm at q {Q}) {fl:.3f} bits; the lossless target "
                         f"{target:.3f} leaves {target - fl:.3f} for the rest (ours spends {bits[('L', 'ours')] - fl:.3f}, "
                         f"JPEG-XL e7 {bits[('L', 'JPEG-XL e7')] - fl:.3f})")  # type: ignore[operator]
    print("  (L/target, B/target: our size over the target size; <= 1 reaches it)")
    print("  targets NOT reached:" if misses else "  every target reached")
    for line in misses:
        print(f"    {line}")
    for line in notes:
        print(f"  {line}")


def section_15mp() -> None:
    import imagecodecs

    z = synthetic_range(3360, 4480, 0.2, seed=1)
    m = ~np.isnan(z)
    mp = z.size / 1e6
    print(f"\n15 MP range image: {z.shape[1]}x{z.shape[0]} ({mp:.1f} MP), {100 * m.mean():.1f} % valid")
    print(f"  {'codec':36s} {'bits/valid':>10s} {'enc MP/s':>9s} {'dec MP/s':>9s} {'decode ms':>9s} {'dec cpu ms':>10s}")
    # best of 5 runs each, ours and the peers alike: on this shared machine the wall time of two
    # runs in a row varied by a third (the CPU time too: the host, not this process)
    reps = 5
    rows = [("ours lossless q=0.02", ours_lossless(z, Q, reps)), ("ours max-error 0.1", ours_bounded(z, 0.1, reps)),
            ("LERC maxZErr=0.01", peer_lerc(z, Q / 2, reps)), ("LERC maxZErr=0.1", peer_lerc(z, 0.1, reps)),
            ("JPEG-LS lossless q=0.02", peer16(lambda a: imagecodecs.jpegls_encode(a, level=0), imagecodecs.jpegls_decode, z, Q, reps)),
            ("zstd-3 of q=0.02 depth", peer16(lambda a: imagecodecs.zstd_encode(a.tobytes(), level=3),
                                              lambda b: np.frombuffer(imagecodecs.zstd_decode(b), np.uint16), z, Q, reps))]  # fmt: skip
    for name, r in rows:
        if r is None:
            print(f"  {name:36s} n/a")
            continue
        size, _, te, td = r
        print(f"  {name:36s} {size * 8 / m.sum():10.3f} {mp / te.wall:9.1f} {mp / td.wall:9.1f} {1000 * td.wall:9.0f} {1000 * td.cpu:10.0f}")
        if name.startswith("ours"):
            verdict(f"{name}: a 15 MP view decodes in 150 ms (wall ms)", 1000 * td.wall, 150)
            verdict(f"{name}: ... on 2 idle cores, extrapolated (CPU ms / 2)", 500 * td.cpu, 150)


def _cloud_of(z: np.ndarray) -> np.ndarray:
    h, w = z.shape
    f = 1.4 * w
    yy, xx = np.mgrid[0:h, 0:w]
    m = ~np.isnan(z)
    zz = z[m].astype(np.float64)
    rec = np.empty(int(m.sum()), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    rec["x"] = (xx[m] - w / 2) / f * zz
    rec["y"] = (yy[m] - h / 2) / f * zz
    rec["z"] = zz
    return rec


def section_clouds() -> None:
    import DracoPy
    import laspy
    from scipy.spatial import cKDTree

    rec = _cloud_of(synthetic_range(1536, 2048, 0.2, seed=0))
    n = len(rec)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], 1).astype(np.float64)
    extent = float((xyz.max(0) - xyz.min(0)).max())
    print(f"\nclouds: the synthetic scan as {n / 1e6:.2f} M points (geometry only), extent {extent:.0f} mm")
    print(f"  {'codec':40s} {'bits/point':>10s} {'max err':>9s} {'enc Mpt/s':>9s} {'dec Mpt/s':>9s}")
    for g in (0.1, 0.5):
        te, blob = _best(lambda g=g: encode_cloud(rec, g), 1)
        td, out = _best(lambda blob=blob: decode_cloud(blob), 2)
        back = np.stack([out["x"], out["y"], out["z"]], 1).astype(np.float64)
        err = float(cKDTree(back).query(xyz, p=np.inf)[0].max())
        bpp = len(blob) * 8 / n
        print(f"  {f'ours octree grid {g}':40s} {bpp:10.3f} {err:9.4f} {n / te.wall / 1e6:9.2f} {n / td.wall / 1e6:9.2f}"
              f"  ({n / td.cpu / 1e6:.2f} M points per CPU second)")
        target = {0.1: 6.5, 0.5: 2.1}[g]
        verdict(f"cloud grid {g} bits/point", bpp, target)
        verdict(f"cloud grid {g} decode M points/s (wall)", n / td.wall / 1e6, 10, higher_is_better=True)
        # As for the range images: both cores to ourselves would give about twice the points per
        # CPU second (the chunks are independent and equal); the wall figure is the measured one.
        verdict(f"cloud grid {g} decode M points/s on 2 idle cores, extrapolated (2 x M points per CPU second)",
                2 * n / td.cpu / 1e6, 10, higher_is_better=True)
        bits = math.ceil(math.log2(extent / g))
        for level in (7, 10):
            te, dblob = _best(lambda bits=bits, level=level: DracoPy.encode(xyz.astype(np.float32), quantization_bits=bits,
                                                                          compression_level=level), 1)
            td, dec = _best(lambda dblob=dblob: DracoPy.decode(dblob), 2)
            dpts = np.asarray(dec.points, np.float64)
            derr = float(cKDTree(dpts).query(xyz, p=np.inf)[0].max())
            print(f"  {f'Draco {bits} bits, level {level}':40s} {len(dblob) * 8 / n:10.3f} {derr:9.4f} {n / te.wall / 1e6:9.2f}"
                  f" {n / td.wall / 1e6:9.2f}")

        def laz_enc(g: float = g) -> bytes:
            header = laspy.LasHeader(point_format=0, version="1.4")
            header.scales = np.array([g, g, g])
            header.offsets = xyz.min(0)
            las = laspy.LasData(header)
            las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            buf = io.BytesIO()
            las.write(buf, do_compress=True, laz_backend=laspy.LazBackend.LazrsParallel)
            return buf.getvalue()

        te, lblob = _best(laz_enc, 1)
        td, las = _best(lambda lblob=lblob: laspy.read(io.BytesIO(lblob), laz_backend=laspy.LazBackend.LazrsParallel), 2)
        lerr = float(np.abs(np.stack([las.x, las.y, las.z], 1) - xyz).max())
        print(f"  {f'LAZ (lazrs) scale {g}, scan order':40s} {len(lblob) * 8 / n:10.3f} {lerr:9.4f} {n / te.wall / 1e6:9.2f}"
              f" {n / td.wall / 1e6:9.2f}")
    # The same points on their camera grid, for the comparison the field notes make.
    z = synthetic_range(1536, 2048, 0.2, seed=0)
    blob = encode_range(RangeImage(z), max_error=0.05)
    print(f"  the same scan as a range image within 0.05 mm (a 0.1 mm grid's bound): {len(blob) * 8 / n:.3f} bits/point")


def section_models() -> None:
    """Which depth representation a block model predicts best: the median over 32x32 fully valid
    blocks of the RMS error (mm, noise included) of plane and quadratic fits to z, log z and 1/z,
    errors mapped back to depth. (The median: blocks across a depth jump are the quadtree's to split.)"""
    print("\nsurface model of a 32x32 block: median RMS prediction error in mm (noise included), by representation")
    images = [("synthetic", synthetic_range(1536, 2048, 0.2, seed=0))]
    cache = Path(tempfile.gettempdir()) / "graylight-bench-real-ranges" / "capture_0" / "range.npz"
    if cache.is_file():
        images.append(("real capture_0", load_range_npz(cache).z))
    b = 32
    yy, xx = np.mgrid[0:b, 0:b]
    X, Y = (xx.ravel() - 15.5) / b, (yy.ravel() - 15.5) / b
    plane = np.stack([np.ones(b * b), X, Y], 1)
    quad = np.stack([np.ones(b * b), X, Y, X * Y, X * X, Y * Y], 1)
    for label, z in images:
        h, w = (z.shape[0] // b) * b, (z.shape[1] // b) * b
        blocks = z[:h, :w].reshape(h // b, b, w // b, b).transpose(0, 2, 1, 3).reshape(-1, b * b).astype(np.float64)
        blocks = blocks[~np.isnan(blocks).any(axis=1)]
        cells = []
        for rep, fwd, inv in (("depth", lambda v: v, lambda v: v), ("log depth", np.log, np.exp),
                              ("inverse depth", lambda v: 1 / v, lambda v: 1 / v)):
            for mname, A in (("plane", plane), ("quadratic", quad)):
                t = fwd(blocks).T
                coef, *_ = np.linalg.lstsq(A, t, rcond=None)
                pred = inv(A @ coef)
                rms = float(np.median(np.sqrt(np.mean((pred - blocks.T) ** 2, axis=0))))
                cells.append(f"{rep} {mname} {rms:.4f}")
        print(f"  {label} ({len(blocks)} blocks): " + ", ".join(cells))


def section_views_vs_merged() -> None:
    """One object, stored two ways: its views' range images (our quadtree codec, plus 4x4 poses)
    or the merged cloud of all views (our octree codec), at the same bound on every coordinate
    (depth within E; the cloud on a grid of 2E, so within E per axis)."""
    from shared.merge.pipeline import merge_scanset
    from tests.support.scansets import cached_scanset

    root = Path(tempfile.gettempdir()) / "graylight-bench-compress-views"
    scanset = cached_scanset(root, "bunny", views=8, size=(640, 480), projector=(512, 384))
    out = root / "merged"
    if not (out / "merged.ply").is_file():
        print("merging the simulated 8-view bunny scan set (kept for later runs) ...", flush=True)
        merge_scanset(scanset, out)
    ranges = sorted((out / "ranges").glob("*.npz"))
    merged = np.concatenate(list(iter_ply_records(out / "merged.ply")))
    geo = np.empty(len(merged), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for a in "xyz":
        geo[a] = merged[a]
    nvalid = sum(int((~np.isnan(load_range_npz(p).z)).sum()) for p in ranges)
    print(f"\nper-view range images + poses vs the merged cloud: {len(ranges)} views ({nvalid / 1e6:.2f} M valid samples),"
          f" merged cloud {len(geo) / 1e6:.2f} M points")
    for e in (0.1, 0.5):
        views = sum(len(encode_range(load_range_npz(p), max_error=e)) for p in ranges) + 16 * 8 * len(ranges)
        cloud = len(encode_cloud(geo, 2 * e))
        smaller = "per-view range images" if views < cloud else "the merged cloud"
        print(f"  within {e} mm: views {views / 1e3:.0f} kB ({views * 8 / nvalid:.2f} bits/sample), merged cloud geometry"
              f" {cloud / 1e3:.0f} kB ({cloud * 8 / len(geo):.2f} bits/point): {smaller} smaller by"
              f" {max(views, cloud) / min(views, cloud):.2f}x")
    print(f"  (the fused cloud keeps {len(geo) / nvalid:.0%} of the views' samples: it is a resampling, not the raw data;"
          " the views are what can be re-fused later)")


def main() -> None:
    section_table()
    section_synthetic()
    section_15mp()
    section_clouds()
    section_models()
    section_views_vs_merged()


if __name__ == "__main__":
    main()
