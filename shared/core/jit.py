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
same streams; LLVM inlines the helpers instead). Not everywhere: seven functions on the
decoders' chains keep numba's inlining (``kernel(inline="always")``), since LLVM-inlined they
left the cloud decoder 2.5-3.5 % slower (28.2-30.5 s of compilation with them as helpers), and
its duplicate counts a fifth slower; the range decoders' kernels call helper twins of two of them
instead (:func:`shared.compress._rans.read_symbol`), 3-6 % faster there.

A helper has no Python entry point: calling one from Python would jump to no code, so
:class:`HelperDispatcher` refuses such a call by name instead.

Kernels allocate with :func:`empty`, :func:`zeros` and :func:`full`, not numpy's functions of
those names. numba implements those as overloads: a function of its own, compiled (with both wrappers)
once per shape type, dtype and set of the *calling* function's flags, so a kernel and a helper
asking for the same array each compile one. In the warm-up that was 128 compiles of
``np.empty``, ``np.zeros``, ``np.full`` and the zero fill, 5.8 s of its 149 s. These emit the same
allocation (numba's own ``_empty_nd_impl``) into the caller's code instead, with nothing to
compile on their own; :func:`at` and :func:`set_at` do the same for unchecked element access.
With these the codecs compiled in 33.2-37.9 s against 36.3-42.3 s before (interleaved runs on a
slower machine than the figures above; 150 signatures against 220), 14-17 % less when the two
trees compiled side by side, one core each.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
from numba.core import cgutils, types
from numba.core.registry import CPUDispatcher
from numba.core.typing.npydecl import parse_dtype, parse_shape
from numba.extending import intrinsic

# numba's array allocation, as its np.empty uses it (private: the pinned numba version's, and
# tests/shared/core/test_jit.py checks the arrays it makes)
from numba.np.arrayobj import _empty_nd_impl, _parse_shape

__all__ = ["HelperDispatcher", "at", "empty", "full", "helper", "kernel", "set_at", "zeros"]


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


def _allocation(name: str, fill: str) -> Any:
    """An intrinsic returning a new C-ordered array: ``name(shape, dtype)`` uninitialised
    (``fill`` "none") or zero-filled ("zero"), ``name(shape, value, dtype)`` filled with
    ``value`` cast to ``dtype`` ("value")."""

    def typer(typingctx: Any, shape: Any, *rest: Any) -> Any:
        if len(rest) != (2 if fill == "value" else 1):
            return None
        ndim, dt = parse_shape(shape), parse_dtype(rest[-1])
        if ndim is None or dt is None or (fill == "value" and not isinstance(rest[0], types.Number | types.Boolean)):
            return None  # numba then reports the call's types as unsupported
        sig = types.Array(dt, ndim, "C")(shape, *rest)

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            # a negative dimension raises ValueError, as np.empty's does
            shapes = _parse_shape(context, builder, signature.args[0], args[0])
            ary = _empty_nd_impl(context, builder, signature.return_type, shapes)
            if fill == "zero":
                cgutils.memset(builder, ary.data, builder.mul(ary.itemsize, ary.nitems), 0)
            elif fill == "value":
                value = context.cast(builder, args[1], signature.args[1], dt)
                stored = context.get_value_as_data(builder, dt, value)
                with cgutils.for_range(builder, ary.nitems) as loop:
                    builder.store(stored, builder.gep(ary.data, [loop.index]))
            return ary._getvalue()

        return sig, codegen

    # numba's intrinsic takes the typer's signature for the call's: spelt out per kind
    if fill == "value":
        def typer3(typingctx: Any, shape: Any, value: Any, dtype: Any) -> Any:
            return typer(typingctx, shape, value, dtype)
        chosen = typer3
    else:
        def typer2(typingctx: Any, shape: Any, dtype: Any) -> Any:
            return typer(typingctx, shape, dtype)
        chosen = typer2
    chosen.__name__ = chosen.__qualname__ = name
    return intrinsic(chosen)


#: ``np.empty(shape, dtype)`` in a kernel: shape an integer or a tuple of integers, dtype a numpy
#: scalar type (``np.int64``) or an array's ``.dtype``; uninitialised.
empty = _allocation("empty", "none")
#: ``np.zeros(shape, dtype)`` in a kernel, as :func:`empty`, every byte zero.
zeros = _allocation("zeros", "zero")
#: ``np.full(shape, value, dtype)`` in a kernel, as :func:`empty`, every element ``value`` (a
#: number, cast to ``dtype`` as numpy's assignment casts it).
full = _allocation("full", "value")


def _element_pointer(context: Any, builder: Any, aryty: Any, ary_value: Any, index: Any, index_type: Any) -> Any:
    """The address of element ``index`` (an integer known not to be negative) of a 1-D array."""
    ary = context.make_array(aryty)(context, builder, ary_value)
    idx = context.cast(builder, index, index_type, types.intp)
    return cgutils.get_item_pointer(context, builder, aryty, ary, [idx], wraparound=False)


@intrinsic
def at(typingctx: Any, a: Any, i: Any) -> Any:
    """``a[i]`` of a 1-D array for an index ``i`` known not to be negative: numba's own indexing
    adds a negative-index wraparound (a compare and a select a load) that LLVM cannot remove
    where it cannot prove the index positive; here constant offsets fold into the address. Code
    in the caller, nothing compiled on its own (as a kernel helper it compiled once per array
    type: 10 signatures in the codecs)."""
    if not (isinstance(a, types.Array) and a.ndim == 1 and isinstance(i, types.Integer)):
        return None

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        aryty = signature.args[0]
        ptr = _element_pointer(context, builder, aryty, args[0], args[1], signature.args[1])
        return context.unpack_value(builder, aryty.dtype, ptr)

    return a.dtype(a, i), codegen


@intrinsic
def set_at(typingctx: Any, a: Any, i: Any, v: Any) -> Any:
    """``a[i] = v`` of a writable 1-D array for an index ``i`` known not to be negative (see
    :func:`at`); ``v`` a number, cast to the array's dtype as numba's assignment casts it."""
    if not (isinstance(a, types.Array) and a.ndim == 1 and a.mutable and isinstance(i, types.Integer)
            and isinstance(v, types.Number | types.Boolean)):  # fmt: skip
        return None

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        aryty, _, valty = signature.args
        ptr = _element_pointer(context, builder, aryty, args[0], args[1], signature.args[1])
        context.pack_value(builder, aryty.dtype, context.cast(builder, args[2], valty, aryty.dtype), ptr)
        return context.get_dummy_value()

    return types.void(a, i, v), codegen
