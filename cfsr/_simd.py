"""Vector kernel of PatchMatch's block search: eight 6 x 6 SSDs at once, with a pure-numba twin.

:func:`box6x8_min` is hand-written LLVM IR (a numba ``@intrinsic``): the SSDs of eight
horizontally adjacent 6 x 6 patches as one ``<8 x float>`` value (AVX width), folded into the
block's per-lane bests with a vector compare-and-select (no early exit, no per-lane branches).
:func:`box6x8_min_numba` computes the same numbers in plain numba, in the same order of float32
operations, so the two give bit-identical results (``tests/test_simd.py`` compares them on
random inputs).

Which one PatchMatch uses is :data:`ENABLED`, read from the environment variable ``CFSR_SIMD``
when this module is imported (``0``, ``off``, ``false`` or ``no``: the numba twin; anything
else, or unset: the intrinsic). The callers read it on every call (:func:`choice`) and pass it
to their kernels, which call :func:`box6x8_update`: each choice compiles a kernel of its own,
both live in numba's cache side by side, and a change takes effect without clearing it.
"""

from __future__ import annotations

import os
import platform
from typing import NamedTuple

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic, overload

from cfsr._jit import njit

__all__ = [
    "ENABLED",
    "LANES",
    "PATCH",
    "READ_COLS",
    "Lanes",
    "box6x8_update",
    "choice",
    "box6x8_min",
    "box6x8_min_numba",
]

#: Patch side (pixels) the vector kernel handles (the paper's default 6 x 6 patch).
PATCH = 6
#: Patches per call: horizontally adjacent patch positions, one float32 vector lane each.
LANES = 8
#: Columns read per patch row (two ``LANES``-wide vectors); the patches use the first
#: ``LANES + PATCH - 1``. Callers pad their images so these reads stay inside them.
READ_COLS = 2 * LANES

#: Use the LLVM intrinsic (True) or its pure-numba twin (False); see the module docstring.
ENABLED = os.environ.get("CFSR_SIMD", "1").strip().lower() not in ("0", "off", "false", "no")

_X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")


class Lanes(NamedTuple):
    """The running bests of a block's ``LANES`` patch positions (one entry per lane)."""

    cost: np.ndarray  #: float32 (LANES,): lowest SSD so far
    dy: np.ndarray  #: int32 (LANES,): its offset, rows
    dx: np.ndarray  #: int32 (LANES,): its offset, columns


def _box6x8_sums(context, builder, rty, tty, ra, ta, rb_, tb_, st_):
    """IR of the SSDs of eight horizontally adjacent 6 x 6 patches, one ``<8 x float>`` value
    (AVX-width vectors, no early exit).

    The patches start at flat positions ``rb + k`` and ``tb + k`` (k = 0..7) of the
    C-contiguous float32 ``ref``/``tgt`` with row length ``stride``, reading 16 columns per
    row: squared differences summed over the 6 rows per column, then 6-column box sums.
    """
    i64 = ir.IntType(64)
    rp = context.make_array(rty)(context, builder, ra).data
    tp = context.make_array(tty)(context, builder, ta).data
    v8 = ir.VectorType(ir.FloatType(), LANES)

    def load(p, idx):
        return builder.load(builder.bitcast(builder.gep(p, [idx]), v8.as_pointer()), align=4)

    lo = hi = None
    width = ir.Constant(i64, LANES)
    for r in range(PATCH):
        rr = builder.add(rb_, builder.mul(st_, ir.Constant(i64, r)))
        tr = builder.add(tb_, builder.mul(st_, ir.Constant(i64, r)))
        d0 = builder.fsub(load(rp, rr), load(tp, tr))
        d1 = builder.fsub(load(rp, builder.add(rr, width)), load(tp, builder.add(tr, width)))
        q0 = builder.fmul(d0, d0)
        q1 = builder.fmul(d1, d1)
        lo = q0 if lo is None else builder.fadd(lo, q0)
        hi = q1 if hi is None else builder.fadd(hi, q1)
    s = lo
    for j in range(1, PATCH):
        mask = ir.Constant(ir.VectorType(ir.IntType(32), LANES), list(range(j, j + LANES)))
        s = builder.fadd(s, builder.shuffle_vector(lo, hi, mask))
    return s


@intrinsic
def box6x8_min(typingctx, ref, tgt, rb, tb, stride, cy, cx, lanes):
    """Fold the SSDs of eight adjacent 6 x 6 patches into the lanes' running bests, without
    branches (LLVM IR).

    Lane ``k`` compares the patch at flat position ``rb + k`` of the C-contiguous float32
    ``ref`` with the one at ``tb + k`` of ``tgt`` (row length ``stride``; 16 columns are read
    per row, from ``rb`` and ``tb``). ``lanes`` is a :class:`Lanes`: where the new SSD is below
    ``lanes.cost`` (strictly, as ``c < best``), the lane takes it and the offset ``(cy, cx)``.
    """
    sig = types.void(ref, tgt, types.int64, types.int64, types.int64, cy, cx, lanes)

    def codegen(context, builder, signature, args):
        ra, ta, rb_, tb_, st_, cy_, cx_, la = args
        rty, tty, rbt, tbt, stt, cyt, cxt, lty = signature.args
        rb_ = context.cast(builder, rb_, rbt, types.int64)
        tb_ = context.cast(builder, tb_, tbt, types.int64)
        st_ = context.cast(builder, st_, stt, types.int64)
        s = _box6x8_sums(context, builder, rty, tty, ra, ta, rb_, tb_, st_)
        i32 = ir.IntType(32)
        vi = ir.VectorType(i32, LANES)

        def lane_ptr(k, vt):
            data = context.make_array(lty.types[k])(
                context, builder, builder.extract_value(la, k)
            ).data
            return builder.bitcast(data, vt.as_pointer())

        bp = lane_ptr(0, s.type)
        yp = lane_ptr(1, vi)
        xp = lane_ptr(2, vi)

        def load(p):
            # the loaded value passes an empty inline asm, so the backend does not fold the
            # select-and-store into a masked store (microcoded and slow on AMD Zen)
            v = builder.load(p, align=4)
            if not _X86:  # the "x" (SSE/AVX register) constraint exists only there
                return v
            return builder.asm(ir.FunctionType(v.type, [v.type]), "", "=x,0", [v], False)

        old = load(bp)
        m = builder.fcmp_ordered("<", s, old)
        builder.store(builder.select(m, s, old), bp, align=4)

        def splat(v, t):
            v = builder.trunc(context.cast(builder, v, t, types.int64), i32)
            u = builder.insert_element(ir.Constant(vi, ir.Undefined), v, ir.Constant(i32, 0))
            return builder.shuffle_vector(
                u, ir.Constant(vi, ir.Undefined), ir.Constant(vi, [0] * LANES)
            )

        builder.store(builder.select(m, splat(cy_, cyt), load(yp)), yp, align=4)
        builder.store(builder.select(m, splat(cx_, cxt), load(xp)), xp, align=4)
        return context.get_dummy_value()

    return sig, codegen


@njit
def box6x8_min_numba(ref, tgt, rb, tb, stride, cy, cx, lanes, cols):  # pragma: no cover - numba
    """:func:`box6x8_min` in plain numba: the same float32 operations in the same order.

    ``cols`` is float32 scratch of at least ``LANES + PATCH - 1`` entries (the per-column sums
    of the squared differences over the patch rows).
    """
    ry, rx = rb // stride, rb % stride
    ty, tx = tb // stride, tb % stride
    for c in range(LANES + PATCH - 1):
        d = ref[ry, rx + c] - tgt[ty, tx + c]
        cols[c] = d * d
    for r in range(1, PATCH):
        for c in range(LANES + PATCH - 1):
            d = ref[ry + r, rx + c] - tgt[ty + r, tx + c]
            cols[c] += d * d
    bc, boy, box = lanes
    for k in range(LANES):
        s = cols[k]
        for j in range(1, PATCH):
            s += cols[k + j]
        if s < bc[k]:
            bc[k] = s
            boy[k] = cy
            box[k] = cx


def choice():
    """The value callers pass to their kernels for :func:`box6x8_update`: ``True`` where
    :data:`ENABLED` (the intrinsic), ``None`` otherwise (the numba twin).

    The two values have different numba types, so numba compiles and caches one kernel for
    each and the implementation is picked at compile time. (A run-time branch between the two
    in one kernel lost the twin's lane updates at the default optimisation level, numba 0.68 /
    llvmlite 0.50, though not at ``NUMBA_OPT=0``; the cause was not pinned down.)
    """
    return True if ENABLED else None


def box6x8_update(simd, ref, tgt, rb, tb, stride, cy, cx, lanes, cols):
    """:func:`box6x8_min` (``simd`` True) or :func:`box6x8_min_numba` (``simd`` None), chosen
    when the caller is compiled; callable from jitted code only."""
    raise NotImplementedError("cfsr._simd.box6x8_update runs inside numba-compiled code only")


@overload(box6x8_update, inline="always")
def _box6x8_update(simd, ref, tgt, rb, tb, stride, cy, cx, lanes, cols):
    if isinstance(simd, types.NoneType):

        def twin(simd, ref, tgt, rb, tb, stride, cy, cx, lanes, cols):  # pragma: no cover
            box6x8_min_numba(ref, tgt, rb, tb, stride, cy, cx, lanes, cols)

        return twin

    def vector(simd, ref, tgt, rb, tb, stride, cy, cx, lanes, cols):  # pragma: no cover
        box6x8_min(ref, tgt, rb, tb, stride, cy, cx, lanes)

    return vector
