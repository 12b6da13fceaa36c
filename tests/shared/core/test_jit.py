"""shared.core.jit: kernels and kernel helpers compile, run from kernels, and a helper called
from Python is refused by name (its compiled code has no Python entry point to jump to); the
kernels' allocations make what numpy's make, and are freed."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shared.core.jit import HelperDispatcher, at, empty, full, helper, kernel, set_at, zeros


@helper(cache=False)
def _twice(a, i):
    return 2 * a[i]


@helper(inline=False, cache=False)
def _plus(x, y):
    return x + y


@kernel(cache=False)
def _sum_twice(a):
    s = 0.0
    for i in range(a.shape[0]):
        s = _plus(s, _twice(a, i))
    # a constant argument: the helper's signature is the same as for the loop's variable
    return s + _twice(a, 0) - _twice(a, 0)


def test_helpers_run_inside_kernels_with_one_signature_each() -> None:
    a = np.arange(5.0)
    assert _sum_twice(a) == 2 * a.sum()
    assert isinstance(_twice, HelperDispatcher) and isinstance(_plus, HelperDispatcher)
    assert len(_twice.signatures) == 1 and len(_plus.signatures) == 1
    assert _twice.targetoptions["forceinline"] and "forceinline" not in _plus.targetoptions
    assert _sum_twice.targetoptions["nogil"] and _sum_twice.targetoptions["no_cfunc_wrapper"]


def test_a_helper_called_from_python_is_refused_by_name() -> None:
    a = np.arange(3.0)
    _sum_twice(a)  # compiled: a call from Python would find the signature and no entry point
    for fn in (_twice, _plus):
        with pytest.raises(TypeError, match=rf"{fn.py_func.__qualname__} is a kernel helper"):
            fn(a, 1) if fn is _twice else fn(1.0, 2.0)


def test_the_codecs_helpers_are_helpers() -> None:
    # The codecs' inner-loop helpers have no Python entry point (what the compile time needs),
    # and the kernels the Python glue calls keep theirs.
    from shared.compress import _lpred, _rans, _tables

    assert isinstance(_rans.adapt_state, HelperDispatcher) and isinstance(_lpred.local_pred, HelperDispatcher)
    assert not isinstance(_tables.quantise_tables, HelperDispatcher)
    assert not isinstance(_lpred.decode_residuals, HelperDispatcher)


@kernel(cache=False)
def _allocations(n, like):
    a = empty((n, 2), np.int16)
    a[:] = 3
    return a, zeros(n, like.dtype), full((2, n), -1, np.uint32), full(n, True, np.bool_), full(n, 1e300, np.float64)


def test_allocations_make_what_numpy_makes() -> None:
    a, z, f, b, big = _allocations(3, np.ones(1, np.uint8))
    expected = (np.full((3, 2), 3, np.int16), np.zeros(3, np.uint8), np.full((2, 3), -1, np.int64).astype(np.uint32),
                np.ones(3, np.bool_), np.full(3, 1e300))  # fmt: skip
    for got, want in zip((a, z, f, b, big), expected, strict=True):
        assert got.dtype == want.dtype and got.shape == want.shape and got.flags.c_contiguous
        assert np.array_equal(got, want)
    z0 = _allocations(0, np.ones(1))[1]
    assert z0.shape == (0,) and z0.dtype == np.float64
    with pytest.raises(ValueError, match="negative dimensions"):
        _allocations(-1, np.ones(1))


def test_allocations_are_freed() -> None:
    # numba's allocation counters are switched on only at start-up: a process of its own
    code = """
import numpy as np
from numba.core.runtime import rtsys
from shared.core.jit import empty, full, kernel, zeros

@kernel(cache=False)
def f(n):
    a = empty(n, np.int64)
    b = zeros((n, 2), np.float32)
    c = full(n, 7, np.uint8)
    a[:] = 1
    return b, c

f(3)
s0 = rtsys.get_allocation_stats()
for _ in range(10):
    f(5)
s1 = rtsys.get_allocation_stats()
print(s1.alloc - s0.alloc, s1.free - s0.free)
"""
    root = Path(__file__).resolve().parents[3]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, env={**os.environ, "NUMBA_NRT_STATS": "1"},
                         capture_output=True, text=True, check=True).stdout.split()  # fmt: skip
    assert int(out[0]) == 30 and int(out[1]) == 30  # three arrays a call, each freed


def test_kernels_allocate_with_the_jit_functions() -> None:
    # numpy's np.empty / np.zeros / np.full in a kernel compile an overload of their own per
    # caller's flags (see shared.core.jit): the kernels of shared/ use empty, zeros and full.
    root = Path(__file__).resolve().parents[3] / "shared"
    found = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef):
                continue
            decorators = [ast.unparse(d) for d in fn.decorator_list]
            if not any(re.match(r"(numba\.)?njit|kernel|helper", d) for d in decorators):
                continue
            for node in ast.walk(fn):
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and isinstance(node.func.value, ast.Name) and node.func.value.id == "np"
                        and node.func.attr in ("empty", "zeros", "full")):  # fmt: skip
                    found.append(f"{path.relative_to(root)}:{node.lineno} {fn.name}: {ast.unparse(node)}")
    assert not found, found


@kernel(cache=False)
def _element_access(a, b, flags, i):
    set_at(b, i, at(a, i) * 2.75)  # a float into an int array: cast as numba's assignment casts
    set_at(flags, i + 1, at(a, i) > 0)
    return at(a, i + 1), at(b, i), at(flags, 0)


def test_element_access_reads_and_writes_what_indexing_does() -> None:
    a = np.array([3, -4, 5], np.int64)
    a.setflags(write=False)  # a read-only array (a kernel's global constant) reads alike
    b = np.zeros(3, np.int32)
    flags = np.zeros(3, np.bool_)
    assert _element_access(a, b, flags, 0) == (-4, 8, False)
    assert b[0] == np.int32(3 * 2.75) and flags.tolist() == [False, True, False]
    assert _element_access(a, b, flags, 1) == (5, -11, False)
    assert b[1] == np.int32(-4 * 2.75) and flags.tolist() == [False, True, False]
