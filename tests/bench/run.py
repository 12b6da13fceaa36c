"""``make bench``: every ``tests/bench/bench_*.py`` module's ``main()``, in name order.

Each section measures our figure and a peer's in the same run, on the same data, and
prints both with their ratio: this machine is shared and noisy, so only ratios measured
side by side mean anything. Sections can be chosen: ``python -m tests.bench.run decode tiles``.
"""

from __future__ import annotations

import importlib
import sys
import time
import traceback
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    wanted = set(argv if argv is not None else sys.argv[1:])
    here = Path(__file__).parent
    modules = sorted(p.stem for p in here.glob("bench_*.py"))
    failed = []
    for name in modules:
        if wanted and name.removeprefix("bench_") not in wanted:
            continue
        print(f"\n=== {name.removeprefix('bench_')} ===", flush=True)
        t0 = time.perf_counter()
        try:
            importlib.import_module(f"tests.bench.{name}").main()
        except Exception:
            traceback.print_exc()
            failed.append(name)
        print(f"--- {name.removeprefix('bench_')}: {time.perf_counter() - t0:.1f} s", flush=True)
    if failed:
        print(f"\nbench sections that failed: {', '.join(failed)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
