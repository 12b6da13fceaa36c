"""Root pytest fixtures: simulated captures from the virtual rig (:mod:`shared.sim.simulate`).

- ``sim_capture_factory(scene, size=(2048, 1536), seed=0, **kw) -> Path``: renders a capture once per
  test session (cached by its arguments) and returns the folder (``capture.json``, ``rig.json``,
  ``truth.npz``, images). ``kw`` goes to :class:`shared.sim.simulate.ImagingParams` (e.g. ``colour=True``,
  ``bits=16``, ``noise=False``, ``inverses=False``), plus ``projector=(w, h)``. Under pytest-xdist the
  workers share one cache (a file lock makes the first worker render and the others wait), so each
  capture is rendered once per run. Treat the folder as read-only: other tests share it.
- ``bunny_capture``: the ``bunny`` scene at 2048x1536, seed 0.
- ``scanset_factory(**kw) -> Path``: a simulated scan set (:func:`tests.support.scansets.cached_scanset`,
  ``kw`` its arguments) rendered once per test session and shared by the xdist workers like the
  captures above (the same set was rendered again by each module and each worker that used it).
  Read-only too: a test that changes a set copies it first.
- ``merge_factory(scanset) -> Path``: ``graylight merge SCANSET --out OUT`` run once per test session
  for each scan set folder (one of ``scanset_factory``'s), shared by the xdist workers; returns OUT
  (with its paradata). Read-only.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.support.locks import held


def _run_cache(tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    """The folder ``name`` shared by every xdist worker of this run (created on first use)."""
    base = tmp_path_factory.getbasetemp()
    # xdist gives each worker its own basetemp under one shared run folder: cache there.
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / name
    root.mkdir(parents=True, exist_ok=True)
    return root


@pytest.fixture(scope="session")
def sim_capture_factory(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Path]:
    from shared.sim.simulate import ImagingParams, simulate_named

    root = _run_cache(tmp_path_factory, "graylight-sim-cache")

    def make(scene: str, size: tuple[int, int] = (2048, 1536), seed: int = 0, **kw: Any) -> Path:
        projector = tuple(kw.pop("projector", (1024, 768)))
        w, h = size
        key = json.dumps([scene, [w, h], seed, list(projector), sorted(kw.items())], default=str)
        digest = hashlib.sha1(key.encode()).hexdigest()[:10]
        folder = root / f"{scene}-{w}x{h}-s{seed}-{digest}"
        with held(root / f"{folder.name}.lock"):
            # simulate_named renames a complete folder into place, so its presence means done.
            if not (folder / "capture.json").is_file():
                simulate_named(scene, folder, size=(w, h), projector=projector, seed=seed,
                               imaging=ImagingParams(**kw), overwrite=True)
        return folder

    return make


@pytest.fixture(scope="session")
def bunny_capture(sim_capture_factory: Callable[..., Path]) -> Path:
    """The ``bunny`` scene at 2048x1536 (seed 0): a capture folder with ``truth.npz``."""
    return sim_capture_factory("bunny", size=(2048, 1536), seed=0)


@pytest.fixture(scope="session")
def scanset_factory(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Path]:
    """``cached_scanset`` in a folder every xdist worker of the run shares: its file lock makes the
    first worker render a set and the others wait for it."""
    from tests.support.scansets import cached_scanset

    root = _run_cache(tmp_path_factory, "graylight-scanset-cache")

    def make(**kw: Any) -> Path:
        return cached_scanset(root, **kw)

    return make


@pytest.fixture(scope="session")
def merge_factory(tmp_path_factory: pytest.TempPathFactory) -> Callable[[Path], Path]:
    """The command line's merge of a scan set, made once a run: the publish tests and the
    multi-view job's comparison each ran the same merge of the same set (5-7 s of CPU each)."""
    from services.cli.main import main

    root = _run_cache(tmp_path_factory, "graylight-merge-cache")

    def make(scanset: Path) -> Path:
        key = hashlib.sha1(str(scanset.resolve()).encode()).hexdigest()[:10]
        out, done = root / key / "merge", root / f"{key}.done"
        with held(root / f"{key}.lock"):  # the first worker merges, the other waits
            if not done.is_file():
                shutil.rmtree(out.parent, ignore_errors=True)  # a merge cut short earlier
                out.parent.mkdir()
                assert main(["merge", str(scanset), "--out", str(out)]) == 0
                done.touch()
        return out

    return make
