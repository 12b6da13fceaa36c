"""Scanner benchmark: decode throughput against OpenCV, real-capture robustness, 15 MP end-to-end.

1. Decode throughput on one in-memory image stack (real capture_0, 1280x1024, 42 frames):
   ours (:func:`shared.scan.decode.decode_stack`, sub-pixel, columns and rows) against OpenCV's
   ``GrayCodePattern.decode`` (its only mode takes two cameras: the same stack is passed twice and
   its time halved), alternating in three rounds; the median of the rounds' ratios is the figure.
   Target: ours >= 20x OpenCV.
2. Real captures (data/procam-kamino410, five poses): the share of projector-lit pixels that decode
   (column and row). Projector-lit is defined the same for both decoders: white - black > 40 grey
   levels (OpenCV's default blackThreshold, which masks the rest). OpenCV's share is measured with
   ``getProjPixel`` (default whiteThreshold 5) on 3000 random lit pixels per capture (a per-pixel
   Python call costs tens of microseconds, so all pixels would take minutes). Target: ours >= 90 %.
3. ``graylight scan`` of a simulated 15 MP (4480x3360) capture from PNG files to PLY, in a subprocess:
   wall time, CPU time and peak memory (the child's own ru_maxrss). Targets: < 15 s on 2 cores, < 3 GB. The capture
   is rendered once by the virtual rig and kept in the temporary folder for later runs.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from shared.core.datapaths import shared_data_dir
from shared.formats.capture import numbered_frames, opencv_order_capture
from shared.scan.decode import decode_capture, decode_stack

REPO = Path(__file__).resolve().parents[2]
REAL = shared_data_dir() / "procam-kamino410"
LIT_THRESHOLD = 40


def _load_real(k: int) -> list[np.ndarray]:
    return [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in numbered_frames(REAL / f"capture_{k}")]


def _stack_planes(frames: list[np.ndarray]) -> tuple[list, list]:
    cols = [(9 - k, frames[2 * k], frames[2 * k + 1]) for k in range(10)]
    rows = [(9 - k, frames[20 + 2 * k], frames[21 + 2 * k]) for k in range(10)]
    return cols, rows


def bench_decode_throughput() -> None:
    frames = _load_real(0)
    h, w = frames[0].shape
    cols, rows = _stack_planes(frames)
    white, black = frames[40], frames[41]
    decode_stack(white, black, cols, rows, (1024, 768))  # compile / warm caches
    gp = cv2.structured_light.GrayCodePattern.create(1024, 768)
    # The machine is shared and its speed drifts over seconds: the two decoders alternate in
    # rounds (OpenCV once, ours best of 5), and each round's ratio compares neighbours in time.
    rounds = []
    for _ in range(3):
        t0 = time.perf_counter()
        ok, _ = gp.decode([frames[:40], frames[:40]], None, [black, black], [white, white],
                          cv2.structured_light.DECODE_3D_UNDERWORLD)
        t_cv = (time.perf_counter() - t0) / 2  # two cameras
        best = np.inf
        for _ in range(5):
            t0 = time.perf_counter()
            decode_stack(white, black, cols, rows, (1024, 768))
            best = min(best, time.perf_counter() - t0)
        rounds.append((best, t_cv))
    ours_s, cv_s = (float(np.median([r[i] for r in rounds])) for i in (0, 1))
    ratios = sorted(cv / ours for ours, cv in rounds)
    print(f"decode {w}x{h}, 42 frames in memory (sub-pixel columns + rows), 3 alternating rounds:")
    print(f"  ours   {ours_s:6.3f} s  {h * w / ours_s / 1e6:7.2f} Mpx/s  (median round, best of 5 in each)")
    print(f"  OpenCV {cv_s:6.3f} s  {h * w / cv_s / 1e6:7.2f} Mpx/s per camera (GrayCodePattern.decode, two cameras "
          f"each round, ok={ok})")
    print(f"  ratio  {ratios[1]:.1f}x median of rounds ({', '.join(f'{r:.1f}' for r in ratios)})  (target >= 20x; "
          f"load average {os.getloadavg()[0]:.1f})")


def bench_real_captures() -> None:
    gp = cv2.structured_light.GrayCodePattern.create(1024, 768)
    print(f"real captures: share of projector-lit pixels (white - black > {LIT_THRESHOLD}) decoding column and row")
    print("  capture   lit px    ours     OpenCV (default thresholds, 3000 sampled)")
    ours_all, cv_all = [], []
    for k in range(5):
        folder = REAL / f"capture_{k}"
        if not folder.is_dir():
            print(f"  capture_{k}: missing ({folder})")
            continue
        cap = opencv_order_capture(folder, numbered_frames(folder), 1024, 768)
        dec = decode_capture(cap)
        frames = _load_real(k)
        lit = frames[40].astype(int) - frames[41] > LIT_THRESHOLD
        ours = float((np.isfinite(dec.column) & np.isfinite(dec.row))[lit].mean())
        ys, xs = np.nonzero(lit)
        pick = np.random.default_rng(k).choice(len(xs), 3000, replace=False)
        fails = sum(bool(gp.getProjPixel(frames[:40], int(xs[i]), int(ys[i]))[0]) for i in pick)
        theirs = 1 - fails / len(pick)
        ours_all.append(ours)
        cv_all.append(theirs)
        print(f"  capture_{k} {lit.sum():8d}  {100 * ours:6.1f} %  {100 * theirs:6.1f} %")
    if ours_all:
        print(f"  worst: ours {100 * min(ours_all):.1f} %, OpenCV {100 * min(cv_all):.1f} %  (target: ours >= 90 %)")


def _capture_15mp() -> Path:
    folder = Path(tempfile.gettempdir()) / "graylight-bench" / "bunny-4480x3360-s0"
    if (folder / "capture.json").is_file():
        return folder
    from shared.sim.simulate import simulate_named

    t0 = time.perf_counter()
    simulate_named("bunny", folder, size=(4480, 3360), seed=0, overwrite=True)
    print(f"  (rendered the 15 MP capture once in {time.perf_counter() - t0:.0f} s: {folder})")
    return folder


def bench_scan_15mp() -> None:
    capture = _capture_15mp()
    out = Path(tempfile.mkdtemp(prefix="graylight-bench-scan-"))
    exe = REPO / ".venv" / "bin" / "graylight"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "services.cli.main"]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as so, tempfile.TemporaryFile("w+") as se:
        proc = subprocess.Popen([*cmd, "scan", str(capture), "--out", str(out / "scan")], stdout=so, stderr=se,
                                text=True)
        # wait4 gives this child's own usage: RUSAGE_CHILDREN would report the largest peak of
        # every child the bench has run so far (py3dtiles, in the render section).
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        so.seek(0)
        se.seek(0)
        stdout, stderr = so.read(), se.read()
    try:
        if proc.returncode != 0:
            print(f"  scan failed: {stderr.strip()}")
            return
        cpu = usage.ru_utime + usage.ru_stime
        peak_gb = usage.ru_maxrss / 1024**2
        size = sum(p.stat().st_size for p in capture.iterdir()) / 1e6
        print(f"graylight scan, 4480x3360 simulated bunny ({size:.0f} MB of PNG) -> PLY, subprocess:")
        print(f"  wall {wall:6.2f} s   (target < 15 s on 2 cores; load average at start {load:.1f})")
        print(f"  CPU  {cpu:6.2f} s   (user + system; wall on an idle 2-core machine is about half to all of this)")
        print(f"  peak memory {peak_gb:.2f} GB (target < 3 GB)")
        print("  " + stdout.strip().splitlines()[0])
    finally:
        shutil.rmtree(out, ignore_errors=True)


def main() -> None:
    if (REAL / "capture_0").is_dir():
        bench_decode_throughput()
        bench_real_captures()
    else:
        print(f"real captures not found at {REAL}: skipping the decode and real-capture sections")
    bench_scan_15mp()


if __name__ == "__main__":
    main()
