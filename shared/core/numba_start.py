"""numba's start-up in a process that only loads cached kernels, without ``scipy.linalg``.

The first kernel a process calls, even one numba loads from its cache without compiling,
initialises numba's CPU target, and that imports ``numba.np.arraymath``, whose import checks
for a BLAS by importing ``scipy.linalg.cython_blas``, so the whole of ``scipy.linalg``.
With scipy 1.17 that import cost 0.25-0.28 s of CPU (its array-API layer reads every numpy
attribute, importing numpy.f2py, numpy.testing and more), against 0.06 s for the
``cython_blas`` extension alone. For a short-lived ``graylight tiles`` (whose kernels use no
BLAS), that was a fifth of its CPU time.

Inside :func:`blas_check_without_scipy_linalg` that check finds the real ``cython_blas``
extension, loaded on its own, which leaves ``sys.modules`` again on the way out, so that numba
decides exactly as it would have (BLAS present, the same kernels) and a later
``import scipy.linalg`` (a kernel calling BLAS, scipy.spatial) runs in full as usual and gets
the same extension module object back.
"""

from __future__ import annotations

import contextlib
import importlib.machinery
import importlib.util
import logging
import sys
from collections.abc import Iterator
from pathlib import Path

log = logging.getLogger(__name__)

_BLAS_MODULE = "scipy.linalg.cython_blas"
_TARGET_MODULE = "numba.np.arraymath"  # the module whose import runs numba's BLAS check


def _cython_blas_spec() -> importlib.machinery.ModuleSpec | None:
    """The spec of scipy's ``linalg/cython_blas`` extension, found without importing
    ``scipy.linalg`` (None when scipy or the extension is not installed)."""
    scipy_spec = importlib.util.find_spec("scipy")  # a top-level spec imports nothing
    if scipy_spec is None or not scipy_spec.submodule_search_locations:
        return None
    for root in scipy_spec.submodule_search_locations:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = Path(root) / "linalg" / f"cython_blas{suffix}"
            if path.is_file():
                return importlib.util.spec_from_file_location(_BLAS_MODULE, path)
    return None


@contextlib.contextmanager
def blas_check_without_scipy_linalg() -> Iterator[None]:
    """While inside, numba's BLAS check finds ``scipy.linalg.cython_blas`` loaded on its own
    rather than through ``scipy.linalg``: call the process's first kernel in here.

    Does nothing when numba's check has already run (its CPU target is initialised),
    ``scipy.linalg`` is already imported, or the extension cannot be found or loaded (numba
    then imports ``scipy.linalg`` as usual). Not thread-safe: enter it before starting
    threads that call kernels.
    """
    if _TARGET_MODULE in sys.modules or _BLAS_MODULE in sys.modules or "scipy.linalg" in sys.modules:
        yield
        return
    spec = _cython_blas_spec()
    module = None
    if spec is not None and spec.loader is not None:
        module = importlib.util.module_from_spec(spec)
        sys.modules[_BLAS_MODULE] = module
        try:
            spec.loader.exec_module(module)
        except (ImportError, OSError) as exc:  # numba's own import will meet (and handle) it
            log.debug("scipy's cython_blas does not load on its own: %s", exc)
            del sys.modules[_BLAS_MODULE]
            module = None
    try:
        yield
    finally:
        if module is not None:
            # Later imports of the name go the usual way (scipy.linalg first) and get this same
            # module object back: the extension initialises once a process.
            sys.modules.pop(_BLAS_MODULE, None)
