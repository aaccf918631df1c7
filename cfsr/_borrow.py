"""Borrowed arrays: what a kernel reads and writes, without reference counting.

numba counts references to every array a compiled function holds: each view it takes (a row
``a[y]``, an array handed to an inlined helper, a tuple unpacked) adds one and drops it
again, with an atomic add on the array's owner each time. In a kernel's inner loops those
atomic operations cost time of their own and, worse, keep LLVM from holding values in
registers or vectorising across them. numba's parallel loops (``prange`` with
``parallel=True``) do not pay them: the loop body sees its arrays through views with no
owner, whose counting compiles to nothing. That, not the threads, is why a parallel loop
ran faster even on one thread -- and it costs several times the compile.

:func:`borrow` gives a plain loop the same: a view of an array (or of every array in a
tuple) with no owner, so that it and every view taken from it count nothing. The owner must
outlive the view: a kernel's arguments do (the caller holds them for the call); an array
the kernel allocates is passed to :func:`keep` after the borrowed view's last use, which
keeps it alive until there. A borrowed view must never be returned or stored in anything
that outlives the kernel.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["borrow", "keep"]


def _holds_array(ty: Any) -> bool:
    if isinstance(ty, types.Array):
        return True
    return isinstance(ty, types.BaseTuple) and any(_holds_array(t) for t in ty)


def _ownerless(context: Any, builder: Any, ty: Any, val: Any) -> Any:
    """``val`` (of numba type ``ty``) with every array in it rebuilt without its owner
    (meminfo) and its Python parent: the same data, shape and strides."""
    if isinstance(ty, types.Array):
        src = context.make_array(ty)(context, builder, val)
        out = context.make_array(ty)(context, builder)
        for name in ("nitems", "itemsize", "data", "shape", "strides"):
            setattr(out, name, getattr(src, name))
        out.meminfo = ir.Constant(out.meminfo.type, None)
        out.parent = ir.Constant(out.parent.type, None)
        return out._getvalue()
    if isinstance(ty, types.BaseTuple):
        for i, t in enumerate(ty):
            if _holds_array(t):
                val = builder.insert_value(
                    val, _ownerless(context, builder, t, builder.extract_value(val, i)), i
                )
    return val


@intrinsic
def borrow(typingctx: Any, arr: Any) -> Any:  # pragma: no cover - compiled
    """A view of ``arr`` (an array, or a tuple or named tuple holding arrays) that takes no
    reference: counting it, and every view taken from it, compiles to nothing. The owner
    must outlive it (see the module docstring)."""
    if not _holds_array(arr):
        return None

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return _ownerless(context, builder, arr, args[0])

    return arr(arr), codegen


@intrinsic
def keep(typingctx: Any, arr: Any) -> Any:  # pragma: no cover - compiled
    """No code: a use of ``arr``, so that numba keeps it (the owner of views borrowed from
    it) alive until here."""

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return context.get_dummy_value()

    return types.void(arr), codegen
