"""Dynamic scheduling of the scan kernels' work items (bands of camera rows).

numba's ``prange`` splits its range into one equal chunk per thread, fixed at the launch. On
a machine whose cores are shared (other processes, or this one's own image readers), one
descheduled thread then holds up the whole launch while the others wait: two threads
measured slower than one (47 ms against 33 ms for the 1.3 MP 42-frame decode beside two
busy processes). The kernels here run ``prange`` over the threads instead, and every thread
takes the next band from a shared counter (an atomic fetch-and-add) until none is left: a
thread that runs takes the work of one that does not, and a quiet machine still splits the
work evenly. (A launch still ends only when every thread has arrived, so on a machine with
no core free a worker's wait for one still costs: ``kernel_threads()`` counts free cores.)

Use in a kernel::

    counter = np.zeros(1, np.int64)
    for _ in numba.prange(numba.get_num_threads()):
        while True:
            band = next_item(counter)
            if band >= n_bands:
                break
            ...  # the band's rows

Importing this module also fixes numba's threading layer
(:func:`shared.core.threads.pin_threading_layer`).
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from shared.core.threads import pin_threading_layer


@intrinsic
def next_item(typingctx: Any, counter: Any) -> Any:  # pragma: no cover - compiled
    """``counter[0] += 1`` atomically (int64 (1,) array); returns the value before: the index of
    the caller's next work item. Relaxed ordering: items are independent, and the launch's end
    joins the threads."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and counter.ndim == 1):
        return None
    sig = types.int64(counter)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [context.get_constant(types.intp, 0)])
        return builder.atomic_rmw("add", ptr, context.get_constant(types.int64, 1), "monotonic")

    return sig, codegen


@intrinsic
def prefetch(typingctx: Any, ary: Any, index: Any) -> Any:  # pragma: no cover - compiled
    """Ask the CPU to bring the cache line of ``ary[index]`` (a 1-D array) into cache: a hint
    (``llvm.prefetch``, a read, kept in every level), never a fault, no result. The scan
    kernels read a row from each of 20-odd images in turn, too many short streams for the
    hardware prefetcher; they ask for the next row of each while the current one is worked."""
    if not (isinstance(ary, types.Array) and ary.ndim == 1 and isinstance(index, types.Integer)):
        return None
    sig = types.void(ary, index)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        aryty = signature.args[0]
        a = context.make_array(aryty)(context, builder, args[0])
        idx = context.cast(builder, args[1], signature.args[1], types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, a, [idx])
        i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        # read (0), highest locality (3), data cache (1)
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


pin_threading_layer()
