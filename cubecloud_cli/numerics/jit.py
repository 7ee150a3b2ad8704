"""The numba settings every parallel CPU kernel compiles with.

``PRANGE_ONLY`` parallelises the loops written as ``prange`` and nothing else. With plain
``parallel=True`` numba also turns every ``np.zeros``, ``np.ones``, ``np.full``, slice
assignment and array expression of a kernel into a parallel loop of its own, each compiled as a
separate function: that made up most of the 19 s a new user waited for the rasterizer's first
compilation, for allocations that take microseconds. The ``prange`` loops, and so the kernels'
arithmetic and results, are the same either way.

``FASTMATH`` and ``EXACT_FASTMATH`` keep a seeded run's bits the same whether numba compiled its
kernels in this process or loaded them from its cache. Numba builds a ``prange`` loop twice: as a
function of its own, and inlined into the kernel, where it is optimised again. A kernel compiled
in the process runs the first copy (the process already holds it under the same name); one
loaded from the cache runs the second. Where the fast-math flags let LLVM round differently in
the two (fusing a multiply and an add into one FMA, or summing a reduction in another order),
a run from an empty cache gave other bits than a warm one (docs/history/first-compilation.md).

* ``FASTMATH``, for the rasterizer: every freedom but ``contract`` (no FMA that LLVM chooses; the
  kernels write theirs out with ``fused_multiply_add``, the same in both copies). Its reductions count
  pixels or sum gradients, and LLVM vectorised them alike in both copies (tests/test_jit.py); dropping
  ``reassoc`` as well made it 2.3× slower (bench/raster.py), and the backward 1.24–1.38× slower
  even with its float column counter replaced (a float induction needs ``reassoc`` to vectorise).
  What ``reassoc`` may regroup must then read the same in both copies: a product of three or
  more factors did not (the backward's conic terms), so the kernels multiply values that have
  other uses, which it leaves whole (``raster/cpu/compositing.pair_geometry_gradients``).
* ``EXACT_FASTMATH``, for the grid field's MLP: no freedom that changes a finite result, so both
  copies must agree. Its hidden-unit sums did differ with ``reassoc``; without it the kernels are
  as fast.

``as_real`` types a kernel's constants like its inputs. A literal such as ``0.5`` is float64 to
numba and would turn float32 arithmetic into float64 (and halve its SIMD width).

For whoever edits the kernels: numba's cache checks only the file of the kernel it caches, not
the files of the helpers compiled into it. After editing ``raster/cpu/projection_blocks.py`` alone, a
cached ``projection_kernels.project_forward`` still runs the old helper, until its own file changes
or its ``__pycache__`` entries are removed. An install from a release rewrites every file and is
not affected.
"""

import llvmlite.binding as llvm
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.core.cpu import ParallelOptions
from numba.extending import intrinsic, overload

# A ParallelOptions, not a dict: numba pops the keys of a dict it is given as it reads them.
PRANGE_ONLY = ParallelOptions(
    {
        "prange": True,
        "numpy": False,
        "setitem": False,
        "reduction": False,
        "inplace_binop": False,
        "comprehension": False,
        "stencil": False,
        "fusion": False,
    }
)


# LLVM vectorizes a loop that writes several arrays only behind run-time checks that none of
# them overlap, and gives up when the checks would exceed 128 (``vectorize-memory-check-threshold``).
# The projection kernels read up to fifteen columns and write up to ten per Gaussian: a few
# hundred checks, once per block of 256 Gaussians, and then its forward and backward take 2.7
# instead of 4.6 ms at 50k Gaussians (cubecloud_cli/raster/cpu/projection_blocks.py). The compositing
# kernels give the same bits either way (compared at float32 and float64). Set when the kernels'
# modules are imported, before numba compiles them; other numba code in the process may be
# vectorized behind more checks too, which changes no result unless a loop reassociates a sum.
MEMORY_CHECK_LIMIT = 1024
llvm.set_option("cubecloud", f"-vectorize-memory-check-threshold={MEMORY_CHECK_LIMIT}")
# LLVM leaves a loop of a known trip count under 16 scalar (``vectorizer-min-trip-count``) unless
# its cost model finds no scalar remainder. The compositing kernels' narrow rows are loops of 8
# pixels: one AVX2 vector of float32 (cubecloud_cli/raster/cpu/compositing.py, NARROW).
MIN_VECTOR_TRIP_COUNT = 8
llvm.set_option("cubecloud", f"-vectorizer-min-trip-count={MIN_VECTOR_TRIP_COUNT}")

FASTMATH = {"nnan", "ninf", "nsz", "arcp", "afn", "reassoc"}
EXACT_FASTMATH = {"nnan", "ninf", "nsz"}


def as_real(value, like):
    """``value`` as a number of ``like``'s float type (``like`` an array or a scalar), so that a
    kernel's constants keep float32 arithmetic float32 and float64 arithmetic exact."""
    dtype = like.dtype if isinstance(like, np.ndarray) else np.asarray(like).dtype
    return dtype.type(value)


@overload(as_real)
def _as_real(value, like):
    real = like.dtype if isinstance(like, types.Array) else like

    def cast(value, like):
        return real(value)

    return cast


@intrinsic
def fused_multiply_add(typingctx, a, b, c):
    """a·b + c rounded once (LLVM's ``llvm.fma``, one instruction on FMA hardware). Written out
    rather than left to ``contract``: an explicit FMA is the same in every copy LLVM makes of a
    loop, where a contraction it chooses need not be (see above). x86-64 CPUs with AVX2
    and all ARM64 CPUs have the instruction; elsewhere LLVM calls libm's fma, exact but slow."""
    if not (isinstance(a, types.Float) and a == b == c):
        return None

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return a(a, b, c), codegen


def _lane_sign_bits(width: int, positive: bool):
    """An intrinsic (tile, row, start) -> int64: bit i set where ``tile[row, start + i]`` is > 0
    (``positive``) or has its sign bit set (negative, −0 included), for i < ``width``."""

    @intrinsic
    def lane_sign_bits(typingctx, tile, row, start):
        if not (
            isinstance(tile, types.Array)
            and tile.ndim == 2
            and tile.dtype in (types.float32, types.float64)
            and isinstance(row, types.Integer)
            and isinstance(start, types.Integer)
        ):
            return None

        def codegen(context, builder, signature, args):
            tile_type, row_type, start_type = signature.args
            array = context.make_array(tile_type)(context, builder, args[0])
            indices = [
                context.cast(builder, args[1], row_type, types.intp),
                context.cast(builder, args[2], start_type, types.intp),
            ]
            pointer = cgutils.get_item_pointer2(
                context,
                builder,
                data=array.data,
                shape=cgutils.unpack_tuple(builder, array.shape),
                strides=cgutils.unpack_tuple(builder, array.strides),
                layout=tile_type.layout,
                inds=indices,
                wraparound=False,
                boundscheck=False,
            )
            lanes = ir.VectorType(ir.IntType(tile_type.dtype.bitwidth), width)
            values = builder.load(builder.bitcast(pointer, lanes.as_pointer()), align=tile_type.dtype.bitwidth // 8)
            test = builder.icmp_signed(">" if positive else "<", values, ir.Constant(lanes, None))
            return builder.zext(builder.bitcast(test, ir.IntType(width)), ir.IntType(64))

        return types.int64(tile, row, start), codegen

    return lane_sign_bits


# The bit masks of a row of 8 or 16 pixels (float32 or float64, contiguous along the row, as the
# compositing kernels' tile arrays are): a vector compare and one move of its mask (vmovmskps),
# where a mask summed inside a SIMD loop costs each row two horizontal reductions.
negative_lanes_8 = _lane_sign_bits(8, positive=False)
negative_lanes_16 = _lane_sign_bits(16, positive=False)
positive_lanes_8 = _lane_sign_bits(8, positive=True)
positive_lanes_16 = _lane_sign_bits(16, positive=True)


@intrinsic
def prefetch(typingctx, array, row):
    """Ask the cache for row ``row`` of ``array`` (1D or 2D, any dtype) ahead of its use, without
    waiting for it (LLVM's ``llvm.prefetch``: a hint that never faults, even out of bounds). The
    compositing kernels read each entry's Gaussian at an index that follows no order the
    hardware prefetcher sees."""
    if not (isinstance(array, types.Array) and array.ndim in (1, 2) and isinstance(row, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        array_type, row_type = signature.args
        data = context.make_array(array_type)(context, builder, args[0])
        strides = cgutils.unpack_tuple(builder, data.strides)
        offset = builder.mul(context.cast(builder, args[1], row_type, types.intp), strides[0])
        address = builder.gep(builder.bitcast(data.data, ir.IntType(8).as_pointer()), [offset])
        int32 = ir.IntType(32)
        hint = ir.FunctionType(ir.VoidType(), [ir.IntType(8).as_pointer(), int32, int32, int32])
        function = cgutils.get_or_insert_function(builder.module, hint, "llvm.prefetch.p0i8")
        # read (0), keep in all cache levels (3), data cache (1)
        builder.call(function, [address, ir.Constant(int32, 0), ir.Constant(int32, 3), ir.Constant(int32, 1)])
        return context.get_dummy_value()

    return types.none(array, row), codegen
