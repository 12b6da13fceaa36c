"""Dynamic scheduling of the scan kernels' work items (bands of camera rows), and their launch
on threads.

A fixed split of the rows (numba's ``prange`` splits its range into one equal chunk per
thread at the launch) lets one descheduled thread hold up the whole launch on a machine whose
cores are shared (other processes, or this one's own image readers): two threads measured
slower than one (47 ms against 33 ms for the 1.3 MP 42-frame decode beside two busy
processes). So every thread takes the next band from a shared counter (an atomic
fetch-and-add) until none is left: a thread that runs takes the work of one that does not,
and a quiet machine still splits the work evenly. (A launch still ends only when every thread
has arrived, so on a machine with no core free a worker's wait for one still costs:
``kernel_threads()`` counts free cores.)

A kernel is one thread's share, a plain ``nogil`` kernel that takes the counter last, and
:func:`run_bands` runs it on this thread and ``numba.get_num_threads() - 1`` threads of a pool::

    @kernel
    def _work(..., counter):
        while True:
            band = next_item(counter)
            if band >= n_bands:
                break
            ...  # the band's rows

    run_bands(_work, ...)

Importing this module also fixes numba's threading layer
(:func:`shared.core.threads.pin_threading_layer`).

Not numba's ``prange``: a parallel kernel goes through numba's parfor passes and compiles its
loop body as a function of its own, linked back and optimised again. The decoder's kernel
compiled in 13.7 s a signature that way, 3.7 s as a plain kernel (numba 0.63, this 2-core
machine), and the scan is the longest part of a fresh machine's set-up. Python threads
calling a ``nogil`` kernel run the same machine code; a launch costs tens of microseconds
more, a few a decode.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numba
import numpy as np
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


# The thread count is numba's (get_num_threads starts its threading layer, and the
# triangulation's _intersect_grid is a numba parallel loop): the same layer in every process.
pin_threading_layer()

_pool: ThreadPoolExecutor | None = None
_pool_pid = 0
_pool_lock = threading.Lock()


def _threads_pool() -> ThreadPoolExecutor:
    """The pool of band threads, made on first use in each process (a worker forked from a
    parent that had one inherits no threads with it)."""
    global _pool, _pool_pid
    with _pool_lock:
        if _pool is None or _pool_pid != os.getpid():
            # numba's thread count is at most NUMBA_NUM_THREADS: the caller is one of them
            _pool = ThreadPoolExecutor(max(1, int(numba.config.NUMBA_NUM_THREADS) - 1), thread_name_prefix="scan-bands")
            _pool_pid = os.getpid()
        return _pool


def run_bands(kernel: Callable[..., Any], *args: Any) -> None:
    """Run ``kernel(*args, counter)`` on ``numba.get_num_threads()`` threads at once (this one
    and the pool's), all with one int64 (1,) ``counter`` from which :func:`next_item` hands out
    work items; returns when every thread has finished. ``kernel`` releases the GIL (``nogil``).
    The count is numba's, so :func:`shared.scan.decode.kernel_thread_scope` sets it for these
    launches as for numba's own."""
    counter = np.zeros(1, np.int64)
    n = numba.get_num_threads()
    if n <= 1:
        kernel(*args, counter)
        return
    futures = [_threads_pool().submit(kernel, *args, counter) for _ in range(n - 1)]
    try:
        kernel(*args, counter)
    finally:
        for f in futures:
            f.result()
