"""Two LLVM operations numba does not expose, for the rasterizer's kernels (docs/performance.md).

- `fma32(a, b, c)`: a * b + c rounded once (llvm.fma.f32, one vfmadd instruction). The kernels
  are compiled without LLVM's 'contract' flag, because contraction let a JIT-compiled and a
  cached copy of the same kernel fuse different multiply-adds (and differ in the last bit from
  process to process, see kernels.py). An explicit fma is an IEEE operation with one answer, so
  the kernels get the speed of fused multiply-adds and keep bit-identical frames everywhere.
- `prefetch_row(array, i)`: ask the cache for row i of a 2D C-contiguous array (llvm.prefetch):
  the next tile entry's 64-byte Gaussian record, fetched while the current one is drawn.
"""

from __future__ import annotations

from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic


#: Fast-math flags that leave a kernel's rounding to its code: neither 'contract' nor 'reassoc'.
#: With either, a kernel JIT-compiled in a process and the same kernel loaded from numba's cache
#: rounded differently ('reassoc': the rasterizer's backward and the hex-plane lookup, measured
#: 2026-12-03; 'contract': the forward kernel, 2026-11-25; docs/development.md). Kernels with
#: these flags write their fused multiply-adds with `fma32` and their sums in a fixed order.
EXACT_FASTMATH = {"nnan", "ninf", "nsz", "arcp", "afn"}


@intrinsic
def fma32(typingctx, a, b, c):
    """float32 a * b + c with a single rounding (vectorises to vfmadd)."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        f32 = ir.FloatType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(f32, [f32] * 3),
                                            "llvm.fma.f32")
        return builder.call(fn, list(args))

    return sig, codegen


@intrinsic
def prefetch_row(typingctx, array, i):
    """Prefetch array[i, 0] for reading (no effect on results; i must be a valid row)."""
    sig = types.void(array, i)

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        row = context.cast(builder, args[1], signature.args[1], types.int64)
        zero = ir.Constant(ir.IntType(64), 0)
        ptr = cgutils.get_item_pointer2(context, builder, data=view.data,
                                        shape=cgutils.unpack_tuple(builder, view.shape),
                                        strides=cgutils.unpack_tuple(builder, view.strides),
                                        layout=array_type.layout, inds=[row, zero],
                                        wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module,
                                            ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                            "llvm.prefetch.p0i8")
        # read, keep in all cache levels, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0), ir.Constant(i32, 3),
                          ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen
