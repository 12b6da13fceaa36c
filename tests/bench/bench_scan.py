"""Scanner benchmark: decode throughput against OpenCV, real-capture robustness, PNG-to-PLY scans
at 3 MP and 15 MP, and the first run of the CLI stages against their second (the compile tax).

1. Decode throughput on one in-memory image stack (real capture_0, 1280x1024, 42 frames):
   ours (:func:`shared.scan.decode.decode_stack`, sub-pixel, columns and rows) against OpenCV's
   ``GrayCodePattern.decode`` (its only mode takes two cameras: the same stack is passed twice and
   its time halved), alternating in three rounds; the median of the rounds' ratios is the figure.
   Target: ours >= 50x OpenCV.
2. Real captures (data/procam-kamino410, five poses): the share of projector-lit pixels that decode
   (column and row). Projector-lit is defined the same for both decoders: white - black > 40 grey
   levels (OpenCV's default blackThreshold, which masks the rest). OpenCV's share is measured with
   ``getProjPixel`` (default whiteThreshold 5) on 3000 random lit pixels per capture (a per-pixel
   Python call costs tens of microseconds, so all pixels would take minutes). Target: ours >= 90 %.
3. ``graylight scan`` of simulated 2048x1536 and 4480x3360 (15 MP) captures from PNG files to PLY,
   each in a child process: wall time, CPU time and peak memory (the child's own ru_maxrss).
   Targets: 3 MP <= 2 s, 15 MP <= 5 s, peak < 3 GB. The captures are rendered once by the
   virtual rig and kept in the temporary folder for later runs.
4. Triangulation of the 2048x1536 capture's decode (in-process, warm): points per CPU-second of
   the process (all threads), the figure that does not depend on what else loads the cores.
   Target: >= 10 M points per CPU-second.
5. ``scan``, ``tiles`` and ``preview`` of the 2048x1536 capture on an empty numba cache (a fresh
   ``NUMBA_CACHE_DIR``: compiles), and on one that ``python -m workers.warmup`` filled (what
   ``make setup`` does), first and second run. Target: first run after set-up <= 1.3x the second.
6. Start-up: ``graylight --help`` and every command's ``--help``, each a new process (best of 5
   wall), beside the bare interpreter's start-up (``python -c pass``, the floor of any Python
   command), and whether the command imported numba (``python -X importtime``). Target: < 0.3 s
   for every command that needs no numba.

Sections can be run alone: ``python -m tests.bench.bench_scan [decode] [real] [triangulate] [sizes]
[first-run] [startup]`` (all without arguments).
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
import numba
import numpy as np

from shared.core.datapaths import shared_data_dir
from shared.formats.capture import numbered_frames, opencv_order_capture
from shared.scan.decode import decode_capture, decode_stack, kernel_threads
from tests.bench._child import run_graylight, run_measured

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
    cpu_cv, cpu_ours = [], []
    for _ in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        ok, _ = gp.decode([frames[:40], frames[:40]], None, [black, black], [white, white],
                          cv2.structured_light.DECODE_3D_UNDERWORLD)
        t_cv = (time.perf_counter() - t0) / 2  # two cameras
        cpu_cv.append((time.process_time() - c0) / 2)
        best = np.inf
        for _ in range(5):
            t0, c0 = time.perf_counter(), time.process_time()
            decode_stack(white, black, cols, rows, (1024, 768))
            best = min(best, time.perf_counter() - t0)
            cpu_ours.append(time.process_time() - c0)
        rounds.append((best, t_cv))
    ours_s, cv_s = (float(np.median([r[i] for r in rounds])) for i in (0, 1))
    ratios = sorted(cv / ours for ours, cv in rounds)
    print(f"decode {w}x{h}, 42 frames in memory (sub-pixel columns + rows), 3 alternating rounds:")
    print(f"  ours   {ours_s:6.3f} s  {h * w / ours_s / 1e6:7.2f} Mpx/s  (median round, best of 5 in each)")
    print(f"  OpenCV {cv_s:6.3f} s  {h * w / cv_s / 1e6:7.2f} Mpx/s per camera (GrayCodePattern.decode, two cameras "
          f"each round, ok={ok})")
    print(f"  ratio  {ratios[1]:.1f}x median of rounds ({', '.join(f'{r:.1f}' for r in ratios)})  (target >= 50x; "
          f"load average {os.getloadavg()[0]:.1f})")
    c_ours, c_cv = float(np.median(cpu_ours)), float(np.median(cpu_cv))
    print(f"  CPU seconds a decode (all threads, median): ours {c_ours:.4f} s, OpenCV {c_cv:.3f} s per camera, "
          f"ratio {c_cv / c_ours:.1f}x")  # fmt: skip
    # What differs between machines of one kind: numba's threading layer (TBB when libtbb is
    # installed, else OpenMP, else its own workqueue) and the threads kernel_threads() grants.
    print(f"  numba threading layer {numba.threading_layer()}, kernel threads now {kernel_threads()} of "
          f"{numba.config.NUMBA_NUM_THREADS}")  # fmt: skip


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


def bench_triangulation() -> None:
    """Triangulation of the 2048x1536 capture's decode, in-process and warm: wall and CPU
    seconds (process, all threads) of the best of five, points per CPU-second."""
    from shared.formats.capture import load_capture
    from shared.formats.rig import load_rig
    from shared.scan.triangulate import rig_tables, triangulate

    capture = _capture((2048, 1536))
    decoded = decode_capture(load_capture(capture))
    rig = load_rig(capture / "rig.json")
    tables = rig_tables(rig)
    triangulate(decoded, rig, tables=tables)  # kernels loaded, pages touched once
    runs = []
    for _ in range(5):
        t0, c0 = time.perf_counter(), time.process_time()
        tri = triangulate(decoded, rig, tables=tables)
        runs.append((time.process_time() - c0, time.perf_counter() - t0))
    cpu, wall = min(runs)
    n = len(tri)
    print(f"triangulation, 2048x1536 capture ({n / 1e6:.2f} M points), best of 5: wall {wall:.3f} s, CPU {cpu:.3f} s "
          f"-> {n / cpu / 1e6:.1f} M points per CPU-second (target >= 10), {n / wall / 1e6:.1f} M points/s wall; "
          f"load average {os.getloadavg()[0]:.1f}")  # fmt: skip


def _capture(size: tuple[int, int]) -> Path:
    """A simulated capture of ``size`` (bunny, or spheres without the shared meshes), rendered
    once and kept in the temporary folder for later runs."""
    from shared.sim.scenes import mesh_path
    from shared.sim.simulate import simulate_named

    scene = "bunny" if mesh_path("stanford-bunny").is_file() else "spheres"
    folder = Path(tempfile.gettempdir()) / "graylight-bench" / f"{scene}-{size[0]}x{size[1]}-s0"
    if (folder / "capture.json").is_file():
        return folder
    t0 = time.perf_counter()
    simulate_named(scene, folder, size=size, seed=0, overwrite=True)
    print(f"  (rendered the {size[0]}x{size[1]} capture once in {time.perf_counter() - t0:.0f} s: {folder})")
    return folder


def _cli(args: list[str], env: dict[str, str] | None = None) -> tuple[float, float, float, str]:
    """``graylight ARGS`` in a child process: wall seconds, CPU seconds (user + system), peak
    memory in GB (the command's own, not the bench's: :mod:`tests.bench._child`) and stdout."""
    run = run_graylight(args, env)
    return run.wall, run.cpu, run.peak_gb, run.stdout


def bench_scan_sizes() -> None:
    """``graylight scan`` from PNG files to PLY at 3 MP and 15 MP (warm numba cache)."""
    print("graylight scan, simulated capture (PNG files) -> PLY, a child process each, numba's cache warm:")
    for size, target in (((2048, 1536), 2.0), ((4480, 3360), 5.0)):
        capture = _capture(size)
        out = Path(tempfile.mkdtemp(prefix="graylight-bench-scan-"))
        try:
            load = os.getloadavg()[0]
            runs = [_cli(["scan", str(capture), "--out", str(out / f"scan{k}")]) for k in range(2)]
            wall, cpu, peak, stdout = min(runs)
            mb = sum(p.stat().st_size for p in capture.iterdir()) / 1e6
            print(f"  {size[0]}x{size[1]} ({mb:.0f} MB of PNG): wall {wall:5.2f} s (best of 2; target <= {target:.0f} s), "
                  f"CPU {cpu:5.2f} s, peak memory {peak:.2f} GB (target < 3 GB); load average {load:.1f}")  # fmt: skip
            print("    " + stdout.strip().splitlines()[0])
        finally:
            shutil.rmtree(out, ignore_errors=True)


def bench_first_run() -> None:
    """The compile tax: ``scan``, ``tiles`` and ``preview`` of a 2048x1536 capture, each run
    twice on an empty numba cache (a fresh ``NUMBA_CACHE_DIR``: the first run compiles), then
    on a cache filled by ``python -m workers.warmup`` alone (what ``make setup`` runs) first
    and second time. Target: the first run after set-up within 1.3x of the second."""
    capture = _capture((2048, 1536))
    work = Path(tempfile.mkdtemp(prefix="graylight-bench-first-"))
    try:
        steps = [
            ("scan", ["scan", str(capture), "--out", str(work / "scan")]),
            ("tiles", ["tiles", str(work / "scan" / "cloud.ply"), "--out", str(work / "tiles")]),
            ("preview", ["preview", str(work / "tiles"), "--out", str(work / "preview.mp4"), "--seconds", "4"]),
        ]
        times: dict[str, dict[str, float]] = {}
        for cache, label in (("empty", "no warm-up"), ("setup", "after warm-up")):
            env = {**os.environ, "NUMBA_CACHE_DIR": str(work / f"numba-{cache}")}
            if cache == "setup":
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "workers.warmup"], env=env, check=True, cwd=REPO,
                               stdout=subprocess.DEVNULL)  # fmt: skip
                times["warm-up"] = {"first": time.perf_counter() - t0}
            for run in ("first", "second"):
                for name, args in steps:
                    times.setdefault(f"{name} {label}", {})[run] = _cli(args, env)[0]
        print("first run against second run (wall s), 2048x1536 capture, a fresh NUMBA_CACHE_DIR each:")
        print(f"  python -m workers.warmup (make setup) on an empty cache: {times['warm-up']['first']:.1f} s")
        for name, _ in steps:
            a, b = times[f"{name} no warm-up"], times[f"{name} after warm-up"]
            print(f"  {name:8s} empty cache: first {a['first']:6.2f} s  second {a['second']:6.2f} s  | "
                  f"after warm-up: first {b['first']:6.2f} s  second {b['second']:6.2f} s  "
                  f"ratio {b['first'] / b['second']:.2f}x (target <= 1.3x)")  # fmt: skip
        print(f"  (load average {os.getloadavg()[0]:.1f}: on a shared machine single runs swing by tens of %)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _imports_numba(args: list[str]) -> bool:
    """Whether ``graylight ARGS`` imports numba (read from ``python -X importtime``)."""
    res = subprocess.run([sys.executable, "-X", "importtime", "-m", "services.cli.main", *args], cwd=REPO,
                         capture_output=True, text=True)  # fmt: skip
    return any(line.split("|")[-1].strip() == "numba" for line in res.stderr.splitlines())


def bench_startup() -> None:
    """``graylight --help`` and each command's ``--help`` in a new process: best of 5 wall
    seconds beside ``python -c pass``; target < 0.3 s where the command needs no numba."""
    from services.cli.main import COMMANDS

    def best(cmd: list[str]) -> float:
        return min(run_measured(cmd).wall for _ in range(5))

    bare = best([sys.executable, "-c", "pass"])
    exe = str(Path(sys.executable).parent / "graylight")
    rows = []
    for args in ([], *([c] for c in sorted(COMMANDS))):
        rows.append((" ".join(["graylight", *args, "--help"]), best([exe, *args, "--help"]),
                     _imports_numba([*args, "--help"])))  # fmt: skip
    print(f"start-up, a new process each (best of 5 wall; peer: python -c pass {bare * 1000:.0f} ms; "
          f"load average {os.getloadavg()[0]:.1f}):")  # fmt: skip
    for name, wall, numba_in in rows:
        verdict = "imports numba" if numba_in else ("reached" if wall < 0.3 else "NOT reached")
        print(f"  {name:34s} {wall * 1000:5.0f} ms  {wall / bare:4.1f}x the bare interpreter  "
              f"(target < 300 ms without numba: {verdict})")  # fmt: skip
    free = [wall for _, wall, numba_in in rows if not numba_in]
    print(f"  {len(free)} of {len(rows)} need no numba; the slowest of them {max(free) * 1000:.0f} ms (target < 300 ms)")


def main(argv: list[str] | None = None) -> None:
    sections = {"decode", "real", "triangulate", "sizes", "first-run", "startup"}
    # Other words (make bench's own arguments, when run from tests.bench.run) are not sections.
    wanted = (set(sys.argv[1:] if argv is None else argv) & sections) or sections
    if {"decode", "real"} & wanted and not (REAL / "capture_0").is_dir():
        print(f"real captures not found at {REAL}: skipping the decode and real-capture sections")
        wanted -= {"decode", "real"}
    if "decode" in wanted:
        bench_decode_throughput()
    if "real" in wanted:
        bench_real_captures()
    if "triangulate" in wanted:
        bench_triangulation()
    if "sizes" in wanted:
        bench_scan_sizes()
    if "first-run" in wanted:
        bench_first_run()
    if "startup" in wanted:
        bench_startup()


if __name__ == "__main__":
    main()
