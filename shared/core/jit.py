"""How numba kernels are compiled: :func:`kernel` for one called from Python, :func:`helper` for
one called from kernels only.

numba compiles every signature of a ``njit`` function with two entry points besides the code
itself: a CPython wrapper (what a call from Python goes through) and a C-callable wrapper
(used only by ``cfunc`` and function pointers, neither of which the project uses). Each costs
LLVM work on its own; for a small function they are most of its compile time (measured with
numba 0.63 on this 2-core machine: 39 ms a trivial signature, 32 ms without the C wrapper,
12 ms without either). A helper needs neither, and numba's ``inline="always"`` copies its IR
into every call site and types it again there, which costs more than compiling it once:
the range and cloud codecs' kernels compiled in 39.0-39.9 s with those, 31.2-32.0 s with
:func:`kernel` and :func:`helper` (numba's compile events from an empty cache, both codecs in
one process as the warm-up runs them, three interleaved runs each), into code as fast (the
same streams; LLVM inlines the helpers instead). Not everywhere: five functions on the cloud
decoder's chain keep numba's inlining (``kernel(inline="always")``), since LLVM-inlined they
left it 2.5-3.5 % slower (28.2-30.5 s of compilation with them as helpers).

A helper has no Python entry point: calling one from Python would jump to no code, so
:class:`HelperDispatcher` refuses such a call by name instead.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
from numba.core import types
from numba.core.registry import CPUDispatcher

__all__ = ["HelperDispatcher", "helper", "kernel"]


def kernel(fn: Callable[..., Any] | None = None, *, cache: bool = True, **options: Any) -> Any:
    """``numba.njit`` for a kernel called from Python: compiled into numba's cache (``cache``;
    False for source run from text, which has no file to cache beside), the GIL released
    (``nogil``, so that bands and chunks run in threads), no C-callable wrapper. ``options``
    are numba's (``error_model``, ``fastmath``, ...)."""
    deco = numba.njit(cache=cache, **{"nogil": True, "no_cfunc_wrapper": True, **options})
    return deco if fn is None else deco(fn)


class HelperDispatcher(CPUDispatcher):
    """The dispatcher of a :func:`helper`: compiled when a kernel calling it is, with no
    Python entry point."""

    def __call__(self, *args: Any, **kws: Any) -> Any:
        func = self.py_func
        raise TypeError(f"{func.__module__}.{func.__qualname__} is a kernel helper, compiled without a Python "
                        "entry point: call it from a kernel")  # fmt: skip

    def get_call_template(self, args: Any, kws: Any) -> Any:
        # A constant argument at a call site would type as a literal and compile a signature
        # of its own; once inlined, LLVM propagates the constant anyway.
        return super().get_call_template(tuple(types.unliteral(a) for a in args),
                                         {k: types.unliteral(v) for k, v in kws.items()})  # fmt: skip


def helper(fn: Callable[..., Any] | None = None, *, inline: bool = True, cache: bool = True, **options: Any) -> Any:
    """A function called from kernels only, compiled once per signature with no Python or C
    entry point and cached (``cache`` as in :func:`kernel`). With ``inline`` (the default, for
    the small functions of inner loops) LLVM inlines it into every caller (``alwaysinline``);
    without, LLVM decides, as for any callee."""

    def wrap(f: Callable[..., Any]) -> HelperDispatcher:
        opts = {"nopython": True, "nogil": True, "no_cpython_wrapper": True, "no_cfunc_wrapper": True, **options}
        if inline:
            opts["forceinline"] = True
        disp = HelperDispatcher(py_func=f, locals={}, targetoptions=opts)
        if cache:
            disp.enable_caching()
        return disp

    return wrap if fn is None else wrap(fn)
