"""Derivatives bench: the whole derivative set of the simulated 12-view 2048x1536 merge, and one
4096 px bake.

1. ``graylight merge`` of the 12-view 2048x1536 bunny turntable set (the one bench_merge renders;
   kept between runs in the bench's temporary folder), measured as the reference: the issue's
   target is a derivative set that takes no longer than the merge itself, in under 6 GB.
2. ``graylight derivatives`` of that merge with Voyager's default levels (Thumb, Low, Medium,
   High): wall, CPU and peak memory of the command, then per level its faces and bytes beside the
   budget, and the High level's seconds (the 4096 px bake: simplify, unwrap, bake, encode).
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

from tests.bench._child import run_graylight
from tests.bench.bench_merge import _sim_scanset

MERGED = Path(tempfile.gettempdir()) / "graylight-bench" / "merge-bunny-turntable-12-2048x1536"


def _merge() -> tuple[Path, float | None]:
    """The merge folder, and the merge's wall time when it ran now (None when it was kept)."""
    folder = _sim_scanset()
    done = MERGED / "report.json"
    if done.is_file() and done.stat().st_mtime > (folder / "scanset.json").stat().st_mtime:
        return MERGED, json.loads(done.read_text()).get("seconds", {}).get("total")
    run = run_graylight(["merge", str(folder), "--out", str(MERGED)])
    print(f"  merge (reference): wall {run.wall:.1f} s, CPU {run.cpu:.1f} s, peak {run.peak_gb:.2f} GB")
    return MERGED, run.wall


def bench_derivatives() -> None:
    merge_dir, merge_s = _merge()
    out = Path(tempfile.mkdtemp(prefix="graylight-bench-derive-"))
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    run = run_graylight(["derivatives", str(merge_dir), "--out", str(out)])
    report = json.loads((out / "derivatives.json").read_text())
    print("graylight derivatives (Thumb, Low, Medium, High) of the 12-view 2048x1536 bunny merge:")
    print(f"  wall {run.wall:.1f} s (target: no more than the merge, {merge_s or float('nan'):.1f} s), CPU {run.cpu:.1f} s,"
          f" peak memory {run.peak_gb:.2f} GB (target < 6 GB); load average at start {load:.1f}")
    print(f"  master {report['master']['faces']} faces; colour baked: {report['colour_baked']}")
    print(f"  {'level':<8} {'faces':>8} {'budget':>8} {'px':>5} {'kB':>7} {'kB budget':>9} {'seconds':>8}")
    for lv in report["levels"]:
        budget = "-" if lv["max_bytes"] is None else f"{lv['max_bytes'] / 1000:.0f}"
        print(f"  {lv['level']:<8} {lv['faces']:>8} {lv['faces_budget']:>8} {lv['texture_px']:>5} "
              f"{lv['bytes'] / 1000:>7.0f} {budget:>9} {lv['seconds']['total']:>8.1f}")
    high = next((lv for lv in report["levels"] if lv["texture_px"] == 4096), None)
    if high is not None:
        print(f"  one 4096 px level ({high['level']}): {high['seconds']} s; bake {high['bake']['seconds']}")
    print(f"  (bench wall {time.perf_counter() - t0:.1f} s; files in {out})")


def main(argv: list[str] | None = None) -> None:
    bench_derivatives()


if __name__ == "__main__":
    main(sys.argv[1:])
