"""Coarse region-adaptive distinction (CFSR paper Eq. 5-6).

For pixel x and output step t, collect the inter-spike intervals (ISIs) of the spikes that fall
inside the ``T`` steps ending at t, and count how many *distinct* ISI values that set holds:

.. math::  \\mathcal{S}_x(t) = \\{ s_k - s_{k-1} : t - T < s_{k-1} < s_k \\le t \\}   (Eq. 5)
.. math::  M_x(t) = 1 \\text{ (dynamic) if } |\\mathcal{S}_x(t)| \\ge \\theta   (Eq. 6)

We read "the cardinality of the set" literally: a static pixel of any brightness fires with a
(near) constant period p, so its ISIs alternate between floor(p) and ceil(p) -- at most two
distinct values -- while a pixel under moving texture sees its period change and collects many.
Counting *all* ISIs instead would call every bright static pixel dynamic.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from cfsr.methods._spiketimes import pixel_times, row_slab

__all__ = ["distinct_isi_counts", "distinct_isi_counts_packed", "coarse_masks"]


@njit(parallel=True, cache=True)
def _distinct_kernel(spikes, ends, span, out):  # pragma: no cover - numba
    """Distinct ISI values in ``(ends[k] - span, ends[k]]`` per pixel, for sorted ``ends``.

    One pass per pixel over its spike times: a sliding window adds the ISI of each spike that
    enters and removes the ISI of each spike that leaves, with a histogram of ISI values and a
    running count of non-empty bins, so K evaluation steps cost one scan, not K.
    """
    n, h, w = spikes.shape
    k_count = ends.shape[0]
    lo = max(0, ends[0] - span + 1)
    hi = min(n, ends[k_count - 1] + 1)
    length = max(0, hi - lo)
    for y in prange(h):
        # copy the row's time slab once: the per-pixel scans below then stay in cache
        slab = row_slab(spikes, lo, length, y)
        times = np.empty(length + 1, np.int64)
        hist = np.zeros(span + 1, np.int32)
        for x in range(w):
            ns = pixel_times(slab, x, lo, times)
            a = 0  # first spike inside the window
            b = 0  # one past the last spike inside the window
            distinct = 0
            for k in range(k_count):
                e = ends[k]
                s = e - span + 1
                while b < ns and times[b] <= e:
                    if b > a:
                        d = times[b] - times[b - 1]
                        if d <= span:
                            hist[d] += 1
                            if hist[d] == 1:
                                distinct += 1
                    b += 1
                while a < b and times[a] < s:
                    if a + 1 < b:
                        d = times[a + 1] - times[a]
                        if d <= span:
                            hist[d] -= 1
                            if hist[d] == 0:
                                distinct -= 1
                    a += 1
                out[k, y, x] = distinct
            # leave the histogram empty for the next pixel
            while a + 1 < b:
                d = times[a + 1] - times[a]
                if d <= span:
                    hist[d] = 0
                a += 1
    return out


def distinct_isi_counts(spikes: np.ndarray, ends, span: int) -> np.ndarray:
    """Number of distinct ISI values per pixel in the ``span`` steps ending at each of ``ends``.

    Parameters
    ----------
    spikes : ndarray (n, H, W) uint8 0/1
        Upright spike frames.
    ends : int or sequence of int
        Indices into ``spikes`` of the evaluation steps t (any order).
    span : int
        The paper's window ``T`` (steps): ISIs whose two spikes both fall in ``(t - T, t]``
        count (Eq. 5). Clipped at the start of ``spikes``.

    Returns
    -------
    counts : ndarray (len(ends), H, W) int32
        ``|S_x(t)|`` of Eq. 5, in the order of ``ends``.
    """
    if span < 1:
        raise ValueError(f"span T must be >= 1 step, got {span}")
    n, h, w = spikes.shape
    e = np.atleast_1d(np.asarray(ends, dtype=np.int64))
    if e.size == 0:
        return np.zeros((0, h, w), np.int32)
    if e.min() < 0 or e.max() >= n:
        raise ValueError(f"evaluation steps {e.tolist()} outside the window of {n} steps")
    order = np.argsort(e, kind="stable")
    out = np.empty((e.size, h, w), np.int32)
    _distinct_kernel(np.ascontiguousarray(spikes, dtype=np.uint8), e[order], int(span), out)
    res = np.empty_like(out)
    res[order] = out
    return res


def coarse_masks(spikes: np.ndarray, ends, span: int, theta: int) -> np.ndarray:
    """Coarse dynamic masks (Eq. 6): ``|S_x(t)| >= theta``, bool ``(len(ends), H, W)``."""
    return distinct_isi_counts(spikes, ends, span) >= int(theta)


# index of the lowest set bit of each byte value: walks only the spikes of a byte
_LOW_BIT = np.array([(v & -v).bit_length() - 1 if v else 8 for v in range(256)], np.int64)


@njit(parallel=True, cache=True)
def _distinct_packed_kernel(packed, lo, hi, span, low, out):  # pragma: no cover - numba
    """Distinct ISI values in frames ``[lo, hi)`` per stored pixel, read from packed bytes.

    Each task owns one cache line of byte columns (512 pixels) and reads it frame by frame, in
    memory order, visiting only set bits. ISI values below 64 steps (nearly all of them) are
    kept as bits of one uint64 per pixel, so the count is a popcount at the end; the few longer
    ones (at most ``span // 64`` per pixel) go to a short list.
    """
    nb = packed.shape[1]
    nchunks = (nb + 63) // 64
    maxbig = span // 64 + 1
    one = np.uint64(1)
    for c in prange(nchunks):
        b0 = c * 64
        m = min(nb, b0 + 64) - b0
        small = np.zeros(m * 8, np.uint64)
        big = np.empty((m * 8, maxbig), np.int64)
        nbig = np.zeros(m * 8, np.int64)
        last = np.full(m * 8, -1, np.int64)
        for t in range(lo, hi):
            row = packed[t]
            for i in range(m):
                v = np.int64(row[b0 + i])
                while v:
                    j = i * 8 + low[v]
                    v &= v - 1
                    lk = last[j]
                    last[j] = t
                    if lk < 0:
                        continue
                    d = t - lk
                    if d < 64:
                        small[j] |= one << np.uint64(d)
                        continue
                    nbj = nbig[j]
                    for q in range(nbj):
                        if big[j, q] == d:
                            break
                    else:
                        big[j, nbj] = d
                        nbig[j] = nbj + 1
        for j in range(m * 8):
            x = small[j]
            cnt = 0
            while x:
                x &= x - one
                cnt += 1
            out[b0 * 8 + j] = cnt + nbig[j]
    return out


def distinct_isi_counts_packed(packed: np.ndarray, end: int, span: int) -> np.ndarray:
    """:func:`distinct_isi_counts` at one step, straight from packed frames.

    Parameters
    ----------
    packed : ndarray (n, frame_bytes) uint8
        Packed frames (``.dat`` layout).
    end : int
        Index of the evaluation step t in ``packed``.
    span : int
        The paper's ``T`` (steps).

    Returns
    -------
    counts : ndarray int32, stored pixel order
        ``|S_x(t)|`` of Eq. 5; view it upright with :func:`cfsr._packed.stored_to_image`.
    """
    if span < 1:
        raise ValueError(f"span T must be >= 1 step, got {span}")
    n = packed.shape[0]
    if not 0 <= end < n:
        raise ValueError(f"evaluation step {end} outside the window of {n} steps")
    lo, hi = max(0, end - span + 1), end + 1
    out = np.empty(packed.shape[1] * 8, np.int32)
    return _distinct_packed_kernel(
        np.ascontiguousarray(packed, dtype=np.uint8), lo, hi, int(span), _LOW_BIT, out
    )
