"""numba's start-up without scipy.linalg: the BLAS check sees the real extension, nothing of it
stays behind, and scipy.linalg (and numba's BLAS kernels) still work afterwards. Each case runs
in a fresh interpreter, as the start-up it checks happens once a process."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("scipy")


def _run(code: str) -> str:
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout


def test_the_first_kernel_inits_numba_without_scipy_linalg_and_blas_still_works() -> None:
    out = _run("""
        import sys
        import numba
        import numpy as np
        from shared.core.numba_start import blas_check_without_scipy_linalg

        @numba.njit
        def add(a):
            return a + 1

        with blas_check_without_scipy_linalg():
            assert add(1) == 2  # initialises numba's target: its BLAS check runs in here
            blas = sys.modules["scipy.linalg.cython_blas"]
        assert "scipy.linalg" not in sys.modules, "scipy.linalg was imported"
        assert "scipy.linalg.cython_blas" not in sys.modules, "the extension stayed in sys.modules"
        import numba.np.arraymath
        assert numba.np.arraymath._HAVE_BLAS  # the same decision as numba's own import makes

        import scipy.linalg
        import scipy.linalg.cython_blas
        assert scipy.linalg.cython_blas is blas  # initialised once, bound to its package as usual

        @numba.njit
        def dot(a, b):
            return np.dot(a, b)

        a = np.arange(12.0).reshape(3, 4)
        assert np.allclose(dot(a, a.T), a @ a.T)
        assert np.allclose(scipy.linalg.solve(np.eye(3) * 2, np.ones(3)), 0.5)
        print("ok")
    """)
    assert out.strip() == "ok"


def test_it_does_nothing_once_numba_or_scipy_linalg_is_loaded() -> None:
    out = _run("""
        import sys
        import scipy.linalg
        from shared.core.numba_start import blas_check_without_scipy_linalg

        with blas_check_without_scipy_linalg():
            before = dict(sys.modules)
        assert "scipy.linalg.cython_blas" not in before or before["scipy.linalg.cython_blas"] is scipy.linalg.cython_blas
        assert sys.modules["scipy.linalg"] is scipy.linalg
        print("ok")
    """)
    assert out.strip() == "ok"
