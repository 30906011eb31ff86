"""A vectorisable exp for the rasterizer's inner loops.

Without SVML, numba's `math.exp` is a scalar libm call that blocks vectorisation of the 16-pixel
inner loops (../shared/notes/cpu-raster.md). This one is exp(x) = 2^n * 2^f with n = round(x log2 e),
f in [-1/2, 1/2], 2^f from a degree-6 Taylor polynomial evaluated with explicit fused multiply-adds
(intrinsics.py; relative error < 2e-7 on the range that matters, x in [-87, 0]), and 2^n assembled
from its IEEE bits, so LLVM keeps the loop in SIMD lanes.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from .intrinsics import fma32


@intrinsic
def _int32_bits_as_float32(typingctx, bits):
    """Reinterpret an int32's bits as a float32 (an LLVM bitcast; vectorises)."""
    sig = types.float32(types.int32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return sig, codegen


_LN2 = math.log(2.0)
_C1 = np.float32(_LN2)
_C2 = np.float32(_LN2 ** 2 / 2)
_C3 = np.float32(_LN2 ** 3 / 6)
_C4 = np.float32(_LN2 ** 4 / 24)
_C5 = np.float32(_LN2 ** 5 / 120)
_C6 = np.float32(_LN2 ** 6 / 720)
_LOG2E = np.float32(1.0 / _LN2)


@numba.njit(inline="always", fastmath=True)
def fast_exp(x):
    """exp(x) for float32 x <= 0 (inputs below -87 return about exp(-87))."""
    x = max(x, np.float32(-87.0))
    y = x * _LOG2E
    n = np.floor(y + np.float32(0.5))  # stays float32 (math.floor would give int64 -> float64)
    f = y - n
    p = fma32(f, _C6, _C5)
    p = fma32(f, p, _C4)
    p = fma32(f, p, _C3)
    p = fma32(f, p, _C2)
    p = fma32(f, p, _C1)
    p = fma32(f, p, np.float32(1.0))
    return p * _int32_bits_as_float32((np.int32(n) + np.int32(127)) << np.int32(23))
