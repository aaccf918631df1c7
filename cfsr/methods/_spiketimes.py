"""Gathering one pixel's spike times from a window: shared by the per-pixel ISI kernels.

The ISI-based kernels (TFI at many centers, TFA, DAISI, the coarse distinction) all walk each
pixel's spike times. Reading ``spikes[t, y, x]`` pixel by pixel strides through memory, so a
row's time slab is copied once (contiguous x) and each pixel's times are collected from it.
"""

from __future__ import annotations

import numpy as np

from cfsr._jit import njit

__all__ = ["row_slab", "row_gather", "pixel_times", "candidate_run"]


@njit(helper=True)
def row_slab(spikes, lo, length, y):  # pragma: no cover - numba
    """Frames ``lo .. lo+length-1`` of row ``y`` as a ``(length, W)`` uint8 copy."""
    w = spikes.shape[2]
    slab = np.empty((length, w), np.uint8)
    for t in range(length):
        for x in range(w):
            slab[t, x] = spikes[lo + t, y, x]
    return slab


@njit(helper=True)
def row_gather(spikes, lo, length, y):  # pragma: no cover - numba
    """:func:`row_slab` of row ``y`` and a buffer for one pixel's spike times in it
    (``length + 1`` int64, filled by :func:`pixel_times`): what a row of a per-pixel walk
    allocates."""
    return row_slab(spikes, lo, length, y), np.empty(length + 1, np.int64)


@njit(helper=True)
def pixel_times(slab, x, lo, times):  # pragma: no cover - numba
    """Write the absolute steps of column ``x``'s spikes into ``times``; return how many."""
    ns = 0
    for t in range(slab.shape[0]):
        if slab[t, x]:
            times[ns] = lo + t
            ns += 1
    return ns


@njit(helper=True)
def candidate_run(cand, i):  # pragma: no cover - numba
    """``(a, b)``: row ``i`` of the bool mask ``cand`` from its first candidate column ``a``
    to one past its last ``b``; ``(-1, -1)`` for a row without one (the span a kernel that
    gathers the row's spike words once reads)."""
    a = -1
    b = -1
    for x in range(cand.shape[1]):
        if cand[i, x]:
            if a < 0:
                a = x
            b = x + 1
    return a, b
