"""Bit counting for numba kernels: ``popcount``, LLVM's ``ctpop`` as one instruction.

numba has no popcount, and a table or a loop costs a load or a dozen instructions where the
CPU has one. The Gray-code decoder (``shared.scan.decode``: compacted pair counts, a pair's
flipped plane) and the octree cloud codec (``shared.compress._octree``: neighbour counts of a
slab, single children) both count bits in their innermost loops, so both take it from here.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["popcount"]


@intrinsic
def popcount(typingctx: Any, x: Any) -> Any:  # pragma: no cover - compiled
    """The set bits of an integer (any integer type, cast to int64; a negative value counts its
    two's-complement bits, 64 for -1). Returns int64."""
    if not isinstance(x, types.Integer):
        return None
    sig = types.int64(x)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        v = context.cast(builder, args[0], signature.args[0], types.int64)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.IntType(64), [ir.IntType(64)]),
                                            "llvm.ctpop.i64")  # fmt: skip
        return builder.call(fn, [v])

    return sig, codegen
