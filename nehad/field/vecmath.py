"""exp and log1p that LLVM vectorises, for the Numba kernels of the HNN decoder
(`nehad.field.hnn_fused`).

Numba without Intel's SVML calls libm's scalar expf and log1pf one element at a time: a softplus
pass (value, first and second derivative) over 10,000 x 128 float32 took 11.8 ms on this
project's 2-core machine, three times torch's vectorised softplus and sigmoid (docs/performance.md,
"The HNN decoder as one fused pass"). Written with plain arithmetic, as here, the loops vectorise:
0.6 ns an element for each function on one thread, against 3.2 ns for libm's expf.

Both functions are dtype-generic: on float32 they are the polynomials below (a few ulp from the
correctly rounded result, tested against float64 in tests/test_hnn_fused.py); on float64 they are
numpy's exp and log1p, so a float64 kernel computes to float64 precision (which is how the tests
check the kernels' algebra against autograd).

- `exp_nonpositive(x)`, x <= 0: Cody-Waite reduction x = n ln 2 + r, |r| <= ln 2 / 2, exp(r) by
  Cephes' expf polynomial, 2^n written into the float's exponent bits; below -87.33 (exp < 1.18e-38,
  float32's smallest normal) the result is exp(-87.33) instead of a denormal or 0.
- `log1p_unit(t)`, 0 <= t <= 1: log(1 + t) = 2 atanh(w), w = t / (2 + t) in [0, 1/3], by the
  odd series of atanh to w^15 (truncation below 2e-9 relative; accurate for tiny t too).

The kernels that call these must not allow floating-point reassociation (`KERNEL_FASTMATH`):
it could merge the two parts of the Cody-Waite constant and lose the reduction's precision.
Numba's on-disk cache of those kernels (cache=True) checks only their own file: after editing
this one, touch nehad/field/hnn_kernels.py so that they are compiled anew.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic, overload

#: LLVM fast-math flags of the kernels that use these functions: every flag of fastmath=True
#: except "reassoc" (vectorising an element-wise loop needs none of them; see the module doc).
KERNEL_FASTMATH = {"nnan", "ninf", "nsz", "arcp", "contract", "afn"}

_LOG2E = 1.4426950408889634
_LN2_HI = 0.693359375  # ln 2 = _LN2_HI + _LN2_LO, _LN2_HI exact in 9 bits (Cephes)
_LN2_LO = -2.12194440e-4
_EXP_CLAMP = -87.33  # exp(-87.33) = 1.18e-38 >= float32's smallest normal, 2^-126


@intrinsic
def _float32_from_bits(typingctx, bits):
    """The float32 whose bit pattern is the int32 `bits`."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())
    return types.float32(types.int32), codegen


def exp_nonpositive(x):
    """exp(x) for x <= 0 (module doc); inside Numba kernels only."""
    return np.exp(x)


def log1p_unit(t):
    """log(1 + t) for 0 <= t <= 1 (module doc); inside Numba kernels only."""
    return np.log1p(t)


@overload(exp_nonpositive, inline="always", jit_options={"fastmath": KERNEL_FASTMATH})
def _exp_nonpositive(x):
    if x != types.float32:
        return lambda x: np.exp(x)

    def exp_f32(x):
        x = max(x, np.float32(_EXP_CLAMP))
        n = np.floor(x * np.float32(_LOG2E) + np.float32(0.5))
        r = x - n * np.float32(_LN2_HI)
        r = r - n * np.float32(_LN2_LO)
        p = np.float32(1.9875691500e-4)
        p = p * r + np.float32(1.3981999507e-3)
        p = p * r + np.float32(8.3334519073e-3)
        p = p * r + np.float32(4.1665795894e-2)
        p = p * r + np.float32(1.6666665459e-1)
        p = p * r + np.float32(5.0000001201e-1)
        e = p * (r * r) + r + np.float32(1.0)
        return e * _float32_from_bits(np.int32((np.int32(n) + np.int32(127)) << np.int32(23)))
    return exp_f32


@overload(log1p_unit, inline="always", jit_options={"fastmath": KERNEL_FASTMATH})
def _log1p_unit(t):
    if t != types.float32:
        return lambda t: np.log1p(t)

    def log1p_f32(t):
        w = t / (np.float32(2.0) + t)
        w2 = w * w
        p = np.float32(1.0 / 15.0)
        p = p * w2 + np.float32(1.0 / 13.0)
        p = p * w2 + np.float32(1.0 / 11.0)
        p = p * w2 + np.float32(1.0 / 9.0)
        p = p * w2 + np.float32(1.0 / 7.0)
        p = p * w2 + np.float32(1.0 / 5.0)
        p = p * w2 + np.float32(1.0 / 3.0)
        p = p * w2 + np.float32(1.0)
        return np.float32(2.0) * w * p
    return log1p_f32


__all__ = ["KERNEL_FASTMATH", "exp_nonpositive", "log1p_unit"]
