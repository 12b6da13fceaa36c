"""A set-up tree has its numba kernels compiled: the stages load every kernel from numba's
cache and compile none on first use (``make setup`` runs ``python -m workers.warmup``).

Both checks read numba's own records, not the clock: the cache index of every kernel, and
each dispatcher's cache hits and misses (a miss is a compilation) after a fresh process has
run the stages on inputs the warm-up never saw (other scenes, sizes and projector sizes).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from workers.warmup import DOMAINS, cached_signatures, kernel_dispatchers

REPO = Path(__file__).resolve().parents[2]

_WORKLOAD = r"""
import json, sys
from pathlib import Path
from shared.render.options import PreviewOptions
from shared.render.stages import preview_stage, tiles_stage
from shared.scan.pipeline import scan
from shared.sim.simulate import ImagingParams, simulate_named
from workers.warmup import kernel_dispatchers

work = Path(sys.argv[1])
kinds = [("plane", (120, 90), (300, 200), {}), ("corner", (100, 80), (128, 100), {"bits": 16, "colour": True}),
         ("spheres", (90, 70), (256, 64), {"inverses": False})]
for i, (scene, size, proj, kw) in enumerate(kinds):
    simulate_named(scene, work / f"c{i}", size=size, projector=proj, seed=7 + i, imaging=ImagingParams(**kw))
    scan(work / f"c{i}", work / f"s{i}")
tiles_stage(work / "s0" / "cloud.ply", work / "tiles", workers=2)
preview_stage(work / "tiles", work / "preview.mp4", PreviewOptions(size=(96, 64), seconds=0.2, fps=10))
print(json.dumps({name: [str(s) for s in d.stats.cache_misses] for name, d in kernel_dispatchers()}))
"""


def test_every_kernel_is_in_the_cache() -> None:
    from shared.sim.scenes import mesh_path

    # The merge's workload needs the shared meshes (the warm-up skips it without them).
    domains = tuple(d for d in DOMAINS if d != "merge" or mesh_path("stanford-bunny").is_file())
    kernels = kernel_dispatchers(domains)
    assert len(kernels) >= 20  # the scan, render and simulator kernels were all found
    missing = [name for name, d in kernels if not cached_signatures(d)]
    assert not missing, f"not compiled into numba's cache (run make setup): {missing}"


@pytest.mark.slow
def test_first_use_of_the_stages_compiles_nothing(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    res = subprocess.run([sys.executable, "-c", _WORKLOAD, str(tmp_path)], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=900)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    misses = json.loads(res.stdout.strip().splitlines()[-1])
    compiled = {name: sigs for name, sigs in misses.items() if sigs}
    assert not compiled, f"compiled on first use (missing from the warm-up or the cache): {compiled}"
