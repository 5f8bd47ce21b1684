"""Elementary functions that LLVM can vectorise inside numba loops.

numba compiles ``math.exp`` to a call of the C library's scalar ``exp``; without Intel's SVML (which the
llvmlite wheels are not built with) a loop over SIMD lanes that calls it is split back into one call per
lane. :func:`exp_nonpositive` is written in operations that have vector instructions (a multiply-add
polynomial, rounding, an integer shift and a bit cast), so that the loops of the GPPOL kernel blocks
(eq. 19, one exponential per pair of training inputs) run as vector code.
"""

from __future__ import annotations

import math

import numba as nb
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

#: Below this argument the result is 0 (``exp(-708.4)`` is the smallest normal double).
EXP_UNDERFLOW = -708.0
_LOG2E = 1.4426950408889634
_LN2_HI = 0.6931471803691238  # ln 2 split so that k * _LN2_HI is exact for |k| < 2**11
_LN2_LO = 1.9082149292705877e-10
#: 1 / n! for n = 13 down to 0 (Horner's order): Taylor's series of exp on |r| <= ln(2) / 2, truncated where
#: the remainder is below float64's resolution.
_TAYLOR = tuple(1.0 / math.factorial(n) for n in range(13, -1, -1))


@intrinsic
def _double_from_bits(typingctx, bits):
    """The float64 whose IEEE-754 bits are the int64 ``bits`` (a bit cast, no conversion)."""
    sig = types.float64(types.int64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return sig, codegen


@nb.njit(cache=True, fastmath=True, inline="always")
def exp_nonpositive(x: float) -> float:
    """``exp(x)`` for ``x <= 0`` to within a few units in the last place (0 below :data:`EXP_UNDERFLOW`):
    ``x = k ln 2 + r`` with ``|r| <= ln(2) / 2``, ``exp(r)`` by its Taylor polynomial, ``2**k`` by
    placing ``k`` in the exponent bits."""
    xc = max(x, EXP_UNDERFLOW)
    k = math.floor(xc * _LOG2E + 0.5)
    r = (xc - k * _LN2_HI) - k * _LN2_LO
    p = 0.0
    for c in _TAYLOR:  # a constant trip count: unrolled by the compiler
        p = p * r + c
    scale = _double_from_bits((nb.int64(k) + 1023) << 52)
    return p * scale if x >= EXP_UNDERFLOW else 0.0
