"""DAISI: difference of adjacent inter-spike intervals, the edge cue of the fine stage.

CFSR paper Eq. 10-14. A static pixel fires with a constant period, so consecutive ISIs agree;
when a moving edge crosses the pixel its brightness jumps and so does its ISI. With the spikes
of pixel x at s_1 < s_2 < ... and ISI_k = s_k - s_(k-1):

* a spike at t (t = s_m): ``D(x, t) = |log ISI_m - log ISI_(m-1)|`` (Eq. 10-11);
* no spike at t (s_(m-1) < t < s_m): the three-ISI form compares the interval containing t with
  both neighbours, ``D = max(|log ISI_(m+1) - log ISI_m|, |log ISI_m - log ISI_(m-1)|)``
  (Eq. 12-13);
* edge where ``D >= phi`` (Eq. 14).

Logarithms are natural. The paper's phi = 4 would need two adjacent ISIs in a ratio of
e^4 = 55 (e.g. 1 and 55 steps), which real or simulated pixels essentially never produce, so
phi is a calibrated parameter (docs/methods.md). Note that the two ISIs of any static pixel are
floor(p) and ceil(p) for period p, so their log ratio is at most log 2 = 0.69 (ISIs 1 and 2):
any phi above that never marks a noise-free static pixel.

``span`` extends the test to every step in ``[t - span, t + span]`` (an edge that crossed the
pixel a few steps before or after t still counts); ``span = 0`` is the paper's test at t.
Pixels without enough spikes in the search range give D = 0 (no evidence of an edge).
"""

from __future__ import annotations

import math

import numpy as np

from cfsr._jit import njit
from cfsr._words import next_spike, prev_spike, range_times
from cfsr.methods._spiketimes import pixel_times, row_slab

__all__ = ["daisi_strength", "daisi_edges", "daisi_from_times", "daisi_words", "log_table"]


@njit
def log_table(n):  # pragma: no cover - numba
    """``logs[d] = log(d)`` for ISIs ``d = 1 .. n`` steps (``logs[0] = 0``): per-pixel DAISI
    then costs table reads, not logarithms, with the very same values."""
    logs = np.zeros(max(1, n + 1), np.float64)
    for d in range(1, n + 1):
        logs[d] = math.log(d)
    return logs


@njit(helper=True)
def daisi_from_times(tv, a_lo, a_hi, logs):  # pragma: no cover - numba
    """Largest adjacent-ISI log ratio D (Eq. 10-13) for steps in ``[a_lo, a_hi]``.

    ``tv`` holds one pixel's spike steps in order; interval k runs from ``tv[k-1]`` to ``tv[k]``.
    A spike inside the range compares its interval with the previous one (Eq. 10-11); a step
    strictly inside an interval uses the three-ISI form (Eq. 12-13). ``logs``: a
    :func:`log_table` covering the longest ISI in ``tv``. Shared by :func:`daisi_strength` and
    the fused CFSR pass.
    """
    ns = tv.shape[0]
    best = 0.0
    # only the intervals with s1 >= a_lo - 1 and s0 <= a_hi can count
    k0 = max(1, np.searchsorted(tv, a_lo - 1, side="left"))
    k1 = min(ns, np.searchsorted(tv, a_hi, side="right") + 1)
    for k in range(k0, k1):
        s0 = tv[k - 1]
        s1 = tv[k]
        if s1 < a_lo - 1 or s0 > a_hi:
            continue
        lk = logs[s1 - s0]
        if a_lo <= s1 <= a_hi and k >= 2:
            d = abs(lk - logs[tv[k - 1] - tv[k - 2]])
            if d > best:
                best = d
        if s1 - s0 >= 2 and s0 + 1 <= a_hi and s1 - 1 >= a_lo:
            if k >= 2:
                d = abs(lk - logs[tv[k - 1] - tv[k - 2]])
                if d > best:
                    best = d
            if k + 1 < ns:
                d = abs(logs[tv[k + 1] - tv[k]] - lk)
                if d > best:
                    best = d
    return best


@njit(helper=True)
def daisi_words(words, r, lo, c, dspan, read_start, read_end, loc, logs):
    # pragma: no cover - numba
    """:func:`daisi_from_times` at ``c +- dspan`` from the only spikes it reads: those in
    ``[c - dspan - 1, c + dspan]`` and two on each side, all inside ``[read_start,
    read_end)``, read from spike words (:mod:`cfsr._words`): CFSR's history scan computes
    DAISI at t this way in the same walk of every pixel's spikes
    (:mod:`cfsr.methods.cfsr._history_kernels`)."""
    a_lo = c - dspan
    a_hi = c + dspan
    nl = 0
    p1 = prev_spike(words, r, lo, a_lo - 2, read_start)
    if p1 >= 0:
        p2 = prev_spike(words, r, lo, p1 - 1, read_start)
        if p2 >= 0:
            loc[nl] = p2
            nl += 1
        loc[nl] = p1
        nl += 1
    nl += range_times(words, r, lo, max(read_start, a_lo - 1), min(read_end, a_hi + 1), loc[nl:])
    n1 = next_spike(words, r, lo, a_hi + 1, read_end)
    if n1 >= 0:
        loc[nl] = n1
        nl += 1
        n2 = next_spike(words, r, lo, n1 + 1, read_end)
        if n2 >= 0:
            loc[nl] = n2
            nl += 1
    return daisi_from_times(loc[:nl], a_lo, a_hi, logs)


@njit
def _daisi_kernel(spikes, c, span, lo, hi, logs, out):  # pragma: no cover - numba
    n, h, w = spikes.shape
    length = hi - lo
    a_lo = c - span
    a_hi = c + span
    for y in range(h):
        slab = row_slab(spikes, lo, length, y)
        times = np.empty(length + 1, np.int64)
        for x in range(w):
            ns = pixel_times(slab, x, lo, times)
            best = daisi_from_times(times[:ns], a_lo, a_hi, logs)
            out[y, x] = best
    return out


def daisi_strength(spikes: np.ndarray, center: int, *, span: int = 0, max_isi: int = 200):
    """Largest adjacent-ISI log ratio D (Eq. 10-13) per pixel around step ``center``.

    Parameters
    ----------
    spikes : ndarray (n, H, W) uint8 0/1
        Upright spike frames.
    center : int
        Index of t in ``spikes``.
    span : int
        Steps each side of t over which D is maximised (0: at t only).
    max_isi : int
        Search range beyond each end of ``[t - span, t + span]`` (steps).

    Returns
    -------
    ndarray (H, W) float32, >= 0, finite (log units).
    """
    n, h, w = spikes.shape
    if not 0 <= center < n:
        raise ValueError(f"center {center} outside window of {n} steps")
    lo = max(0, center - span - max_isi)
    hi = min(n, center + span + max_isi + 1)
    out = np.zeros((h, w), np.float32)
    return _daisi_kernel(
        np.ascontiguousarray(spikes, dtype=np.uint8),
        center,
        int(span),
        lo,
        hi,
        log_table(hi - lo),
        out,
    )


def daisi_edges(
    spikes: np.ndarray, center: int, phi: float, *, span: int = 0, max_isi: int = 200
) -> np.ndarray:
    """Edge mask of Eq. 14: ``D >= phi`` (bool ``(H, W)``)."""
    return daisi_strength(spikes, center, span=span, max_isi=max_isi) >= np.float32(phi)
