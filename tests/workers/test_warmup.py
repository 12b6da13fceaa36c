"""A set-up tree has its numba kernels compiled: the stages load every kernel from numba's
cache and compile none on first use (``make setup`` runs ``python -m workers.warmup``).

Both checks read numba's own records, not the clock: the cache index of every kernel, and
each dispatcher's cache hits and misses (a miss is a compilation) after a fresh process has
run the stages on inputs the warm-up never saw (other scenes, sizes and projector sizes).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from workers.warmup import (
    DOMAINS,
    cached_signatures,
    kernel_dependencies,
    kernel_dispatchers,
    stale_kernel_modules,
    uncovered_kernel_modules,
)

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


def _warmed_domains() -> tuple[str, ...]:
    from shared.sim.scenes import mesh_path

    # The merge's workload needs the shared meshes (the warm-up skips it without them).
    return tuple(d for d in DOMAINS if d != "merge" or mesh_path("stanford-bunny").is_file())


def test_every_kernel_module_is_warmed() -> None:
    assert uncovered_kernel_modules() == []


def test_kernel_dependencies_follow_imports_across_modules() -> None:
    # _quadtree's kernels call _rans's coder; render.octree reaches core.errors through tilenode too.
    deps = kernel_dependencies("shared.compress._quadtree")
    rans = REPO / "shared" / "compress" / "_rans.py"
    assert deps["shared.compress._rans"] == hashlib.sha256(rans.read_bytes()).hexdigest()
    assert "shared.compress._quadtree" not in deps  # numba itself watches the module's own file
    assert {"shared.compress.tilenode", "shared.formats.ply"} <= set(kernel_dependencies("shared.render.octree"))


def test_no_kernel_was_cached_from_older_imported_sources() -> None:
    """The warm-up recorded, beside each module's kernels, the sources the module imports; a
    kernel whose imported module changed since would load stale machine code."""
    assert stale_kernel_modules(_warmed_domains()) == []


def test_every_kernel_is_in_the_cache() -> None:
    domains = _warmed_domains()
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


def test_side_workloads_inputs_have_a_scans_types(tmp_path: Path) -> None:
    """The compress and render warm-ups run beside the scan on inputs of their own: they must
    carry the types a scan writes (numba compiles one signature per argument type), field for
    field."""
    import numpy as np

    from shared.formats.ply import read_header
    from shared.scan.pipeline import scan
    from shared.sim.simulate import simulate_named
    from workers.warmup import _compress_inputs, _render_inputs

    simulate_named("spheres", tmp_path / "cap", size=(64, 48), projector=(64, 48), seed=3)
    scan(tmp_path / "cap", tmp_path / "scan")
    (tmp_path / "own").mkdir()
    folders, cloud = _compress_inputs(tmp_path / "own")
    scan_dtype = read_header(tmp_path / "scan" / "cloud.ply").dtype
    assert read_header(cloud).dtype == scan_dtype
    for ply in _render_inputs(tmp_path / "own"):
        assert read_header(ply).dtype == scan_dtype
    with np.load(tmp_path / "scan" / "range.npz") as real:
        for folder in folders:
            with np.load(folder / "range.npz") as own:
                assert {k: (own[k].dtype, own[k].ndim) for k in own} == {k: (real[k].dtype, real[k].ndim) for k in real}
                assert np.isnan(own["z"]).any() and np.isfinite(own["z"]).any()
