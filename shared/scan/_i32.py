"""32-bit integer arithmetic for the scan kernels' vector loops.

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

from numba import types
from numba.extending import intrinsic


def _binary(name: str, doc: str) -> Any:
    def typer(typingctx: Any, a: Any, b: Any) -> Any:
        if not (isinstance(a, types.Integer) and isinstance(b, types.Integer)):
            return None
        sig = types.int32(a, b)

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            x = context.cast(builder, args[0], signature.args[0], types.int32)
            y = context.cast(builder, args[1], signature.args[1], types.int32)
            return getattr(builder, name)(x, y)

        return sig, codegen

    typer.__name__ = typer.__qualname__ = f"{name.rstrip('_')}32"
    typer.__doc__ = doc
    return intrinsic(typer)


def _compare(op: str, doc: str) -> Any:
    def typer(typingctx: Any, a: Any, b: Any) -> Any:
        if not (isinstance(a, types.Integer) and isinstance(b, types.Integer)):
            return None
        sig = types.boolean(a, b)

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            x = context.cast(builder, args[0], signature.args[0], types.int32)
            y = context.cast(builder, args[1], signature.args[1], types.int32)
            return builder.icmp_signed(op, x, y)

        return sig, codegen

    typer.__name__ = typer.__qualname__ = {"==": "eq32", "!=": "ne32", "<": "lt32", "<=": "le32", ">": "gt32",
                                           ">=": "ge32"}[op]  # fmt: skip
    typer.__doc__ = doc
    return intrinsic(typer)


and32 = _binary("and_", "``a & b`` in int32.")
or32 = _binary("or_", "``a | b`` in int32.")
xor32 = _binary("xor", "``a ^ b`` in int32.")
add32 = _binary("add", "``a + b`` in int32 (wraps; callers keep sums in range).")
sub32 = _binary("sub", "``a - b`` in int32 (wraps; callers keep differences in range).")
shl32 = _binary("shl", "``a << b`` in int32 (``0 <= b < 32``).")
shr32 = _binary("lshr", "``a >> b`` in int32, logical (``0 <= b < 32``; numba's ``>>`` for ``a >= 0``).")
eq32 = _compare("==", "``a == b`` in int32.")
ne32 = _compare("!=", "``a != b`` in int32.")
lt32 = _compare("<", "``a < b`` in int32, signed.")
le32 = _compare("<=", "``a <= b`` in int32, signed.")
gt32 = _compare(">", "``a > b`` in int32, signed.")
ge32 = _compare(">=", "``a >= b`` in int32, signed.")
