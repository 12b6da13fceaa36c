"""numba's threading policy, one for every process that runs Graylight's parallel kernels.

Imported by the kernel modules that launch parallel work (``shared.scan._bands``,
``shared.render.raster``), so a process that scans, one that only renders (the preview CLI, a
render worker) and the bench all run on the same layer. Not imported by ``shared.core``'s
``__init__``: importing the package loads no numba.
"""

from __future__ import annotations

import os

import numba


def pin_threading_layer() -> None:
    """Prefer OpenMP among numba's threading layers, its workers waiting passively.

    numba picks TBB when a libtbb is installed, else OpenMP, else its own workqueue, so two
    machines of one kind ran the kernels on different layers (whether some package had pulled
    in libtbb). OpenMP is there wherever numba's wheels run (libgomp) and, unlike the
    workqueue, takes launches from several threads at once. Its workers spin for a while after
    each launch by default; on a shared machine that burnt CPU the image readers and other
    processes wanted. Measured on 2 cores: the 1.3 MP 42-frame decode took 60-77 ms of CPU a
    run on two spinning OpenMP threads, against 36-43 ms passive, 35-46 ms on TBB and 34 ms on
    one thread; 1280x720 preview batches (one frame a thread, 1.5 M points a frame, load 6-7)
    9.7-9.9 ms of CPU a frame on TBB (whose idle worker spins while the other frame draws, with
    rounds at twice that), 12.3 ms on OpenMP spinning, 8.3-9.1 ms on OpenMP passive.

    Either environment variable set by the user wins; so does a layer numba has already
    started (the setting is read at its first parallel launch). Idempotent.
    """
    if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
