"""shared.core.jit: kernels and kernel helpers compile, run from kernels, and a helper called
from Python is refused by name (its compiled code has no Python entry point to jump to)."""

from __future__ import annotations

import numpy as np
import pytest

from shared.core.jit import HelperDispatcher, helper, kernel


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

    assert isinstance(_rans.at, HelperDispatcher) and isinstance(_lpred.local_pred, HelperDispatcher)
    assert not isinstance(_tables.quantise_tables, HelperDispatcher)
    assert not isinstance(_lpred.decode_residuals, HelperDispatcher)
