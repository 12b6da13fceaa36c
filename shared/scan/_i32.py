"""32-bit integer arithmetic and index compaction for the scan kernels' vector loops.

numba widens every integer operation to 64 bits (``int32 & int32`` is an int64), and LLVM
narrows it back only where it can prove the high bits unused, which a comparison or a variable
shift prevents: a loop over 16-bit code words then runs 8 pixels a 512-bit vector instead of 16.
These helpers take integers, cast them to int32 and apply the operation in 32 bits (results
int32, comparisons signed, bool), so the loop stays in 32-bit lanes. Used on values that fit in
32 bits (code words of at most 16 bits, levels, counts of one row), where they agree with the
64-bit operation exactly; ``shr`` is the logical shift, equal to numba's ``>>`` for values >= 0.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


def _int32_op(name: str, doc: str, result: Any, emit: Any) -> Any:
    """An intrinsic ``name(a, b)`` of two integers: both cast to int32, then ``emit(builder, x, y)``
    builds the operation, typed ``result`` (int32 or boolean)."""

    def typer(typingctx: Any, a: Any, b: Any) -> Any:
        if not (isinstance(a, types.Integer) and isinstance(b, types.Integer)):
            return None
        sig = result(a, b)

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            x = context.cast(builder, args[0], signature.args[0], types.int32)
            y = context.cast(builder, args[1], signature.args[1], types.int32)
            return emit(builder, x, y)

        return sig, codegen

    typer.__name__ = typer.__qualname__ = name
    typer.__doc__ = doc
    return intrinsic(typer)


def _binary(name: str, method: str, doc: str) -> Any:
    return _int32_op(name, doc, types.int32, lambda builder, x, y: getattr(builder, method)(x, y))


def _compare(name: str, op: str, doc: str) -> Any:
    return _int32_op(name, doc, types.boolean, lambda builder, x, y: builder.icmp_signed(op, x, y))


and32 = _binary("and32", "and_", "``a & b`` in int32.")
or32 = _binary("or32", "or_", "``a | b`` in int32.")
xor32 = _binary("xor32", "xor", "``a ^ b`` in int32.")
add32 = _binary("add32", "add", "``a + b`` in int32 (wraps; callers keep sums in range).")
sub32 = _binary("sub32", "sub", "``a - b`` in int32 (wraps; callers keep differences in range).")
shl32 = _binary("shl32", "shl", "``a << b`` in int32 (``0 <= b < 32``).")
shr32 = _binary("shr32", "lshr", "``a >> b`` in int32, logical (``0 <= b < 32``; numba's ``>>`` for ``a >= 0``).")
eq32 = _compare("eq32", "==", "``a == b`` in int32.")
ne32 = _compare("ne32", "!=", "``a != b`` in int32.")
lt32 = _compare("lt32", "<", "``a < b`` in int32, signed.")
le32 = _compare("le32", "<=", "``a <= b`` in int32, signed.")
gt32 = _compare("gt32", ">", "``a > b`` in int32, signed.")
ge32 = _compare("ge32", ">=", "``a >= b`` in int32, signed.")


#: Lanes of :func:`compress_index` (one 512-bit vector of int32 indices).
LANES = 16


@intrinsic
def compress_index(typingctx: Any, src: Any, x0: Any, dst: Any, n: Any) -> Any:  # pragma: no cover - compiled
    """Index compaction of ``LANES`` elements: of ``src[x0 : x0 + LANES]`` (a 1-D float64 or bool
    array; the caller keeps the slice inside it), the indices ``x0 + i`` of those that are
    ``>= 0.0`` (float64; NaN is not) or true (bool) are written in order to ``dst[n:]`` (1-D
    int32, room for them); returns their mask as an int64 (bit i for ``src[x0 + i]``).

    What a scalar loop ``dst[n] = x; n += cond`` does, 16 elements at a time (one compare, one
    ``vpcompressd`` store where the CPU has AVX-512; LLVM emulates it elsewhere): that loop, run
    over every pixel pair of a camera row, was a tenth of the column decode."""
    if not (isinstance(src, types.Array) and src.ndim == 1 and src.dtype in (types.float64, types.boolean)
            and isinstance(dst, types.Array) and dst.ndim == 1 and dst.dtype == types.int32
            and isinstance(x0, types.Integer) and isinstance(n, types.Integer)):  # fmt: skip
        return None
    sig = types.int64(src, x0, dst, n)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        srcty, x0ty, dstty, nty = signature.args
        s = context.make_array(srcty)(context, builder, args[0])
        d = context.make_array(dstty)(context, builder, args[2])
        start = context.cast(builder, args[1], x0ty, types.intp)
        at = context.cast(builder, args[3], nty, types.intp)
        sp = cgutils.get_item_pointer(context, builder, srcty, s, [start])
        dp = cgutils.get_item_pointer(context, builder, dstty, d, [at])
        i1, i8, i32 = ir.IntType(1), ir.IntType(8), ir.IntType(32)
        if srcty.dtype == types.float64:
            vt = ir.VectorType(ir.DoubleType(), LANES)
            v = builder.load(builder.bitcast(sp, vt.as_pointer()), align=8)
            mask = builder.fcmp_ordered(">=", v, ir.Constant(vt, [0.0] * LANES))
        else:
            vt = ir.VectorType(i8, LANES)
            v = builder.load(builder.bitcast(sp, vt.as_pointer()), align=1)
            mask = builder.icmp_unsigned("!=", v, ir.Constant(vt, [0] * LANES))
        iv = ir.VectorType(i32, LANES)
        base = builder.insert_element(ir.Constant(iv, ir.Undefined), builder.trunc(start, i32), ir.Constant(i32, 0))
        base = builder.shuffle_vector(base, ir.Constant(iv, ir.Undefined), ir.Constant(iv, [0] * LANES))
        idx = builder.add(base, ir.Constant(iv, list(range(LANES))))
        fnty = ir.FunctionType(ir.VoidType(), [iv, i32.as_pointer(), ir.VectorType(i1, LANES)])
        fn = cgutils.get_or_insert_function(builder.module, fnty, f"llvm.masked.compressstore.v{LANES}i32")
        builder.call(fn, [idx, builder.bitcast(dp, i32.as_pointer()), mask])
        return builder.zext(builder.bitcast(mask, ir.IntType(LANES)), ir.IntType(64))

    return sig, codegen
