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

from cfsr._jit import njit
from cfsr._words import (
    ROW_PAD,
    WORD_STEPS,
    geometry,
    leading_zeros,
    n_words,
    popcount,
    row_words,
    trailing_zeros,
)
from cfsr.methods._spiketimes import pixel_times, row_gather

__all__ = [
    "distinct_isi_counts",
    "distinct_isi_counts_packed",
    "distinct_in_words",
    "sliding_distinct",
    "coarse_masks",
]


@njit(helper=True)
def sliding_distinct(times, ns, ends, span, hist, out, y, x):  # pragma: no cover - numba
    """Eq. 5 for one pixel at every step of ``ends`` (ascending): ``out[k, y, x]`` = distinct
    ISI values whose two spikes lie in ``(ends[k] - span, ends[k]]``.

    One pass over the pixel's spike steps ``times[:ns]``: a sliding window adds the ISI of each
    spike that enters and removes the ISI of each spike that leaves, with a histogram of ISI
    values (``hist``, ``span + 1`` bins, empty on entry and on return) and a running count of
    non-empty bins, so K evaluation steps cost one scan, not K.
    """
    a = 0  # first spike inside the window
    b = 0  # one past the last spike inside the window
    distinct = 0
    for k in range(ends.shape[0]):
        e = ends[k]
        s = e - span + 1
        # an ISI longer than span never lies inside one window: not counted, so not removed
        # either; the count itself is branch-free
        while b < ns and times[b] <= e:
            if b > a:
                d = times[b] - times[b - 1]
                if d <= span:
                    distinct += hist[d] == 0
                    hist[d] += 1
            b += 1
        while a < b and times[a] < s:
            if a + 1 < b:
                d = times[a + 1] - times[a]
                if d <= span:
                    hist[d] -= 1
                    distinct -= hist[d] == 0
            a += 1
        out[k, y, x] = distinct
    # leave the histogram empty for the next pixel
    while a + 1 < b:
        d = times[a + 1] - times[a]
        if d <= span:
            hist[d] = 0
        a += 1


@njit
def _distinct_kernel(spikes, ends, span, out):  # pragma: no cover - numba
    """:func:`sliding_distinct` for every pixel of unpacked frames, for sorted ``ends``."""
    n, h, w = spikes.shape
    k_count = ends.shape[0]
    lo = max(0, ends[0] - span + 1)
    hi = min(n, ends[k_count - 1] + 1)
    length = max(0, hi - lo)
    for y in range(h):
        # copy the row's time slab once: the per-pixel scans below then stay in cache
        slab, times = row_gather(spikes, lo, length, y)
        hist = np.zeros(span + 1, np.int32)
        for x in range(w):
            ns = pixel_times(slab, x, lo, times)
            sliding_distinct(times, ns, ends, span, hist, out, y, x)
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


@njit(helper=True)
def long_isi_buffer(lo, hi):  # pragma: no cover - numba
    """The ``big`` buffer of :func:`distinct_in_words` over steps ``[lo, hi)``: room for its
    ISIs of a word or more (at most one per :data:`~cfsr._words.WORD_STEPS` steps)."""
    return np.empty((hi - lo) // WORD_STEPS + 1, np.int64)


@njit(helper=True)
def distinct_in_words(words, k, nw, lo, a, b, span, big, cap):  # pragma: no cover - numba
    """Distinct ISI values ``d <= span`` between consecutive spikes that both lie in
    ``[a, b)``, walking word row ``k`` (:mod:`cfsr._words`, first step ``lo``).

    With ``a = t - T + 1, b = t + 1, span = T`` it is ``|S_x(t)|`` of Eq. 5. Over a longer
    range it bounds the count of every ``T``-window inside it from above (their ISI sets are
    subsets), which the fused CFSR scan uses to prove a pixel static. ISI values below 64 steps
    (nearly all) are bits of one uint64, counted by one popcount; the few longer ones (at most
    ``(b - a) // 64``) go to ``big``. ``cap > 0`` stops the walk once the count reaches
    ``cap`` (the count returned is then ``>= cap``, not exact).
    """
    one = np.uint64(1)
    small = np.uint64(0)
    nbig = 0
    last = np.int64(-1)
    q0 = (a - lo) >> 6
    q1 = min(nw - 1, (b - 1 - lo) >> 6)
    for q in range(q0, q1 + 1):
        w = words[k, q]
        base = lo + 64 * q
        if base < a:  # drop steps before a
            w &= ~((one << np.uint64(a - base)) - one)
        if base + 64 > b:  # and from b on
            w &= (one << np.uint64(b - base)) - one
        if w == 0:
            continue
        first = np.int64(trailing_zeros(w))
        top = 63 - np.int64(leading_zeros(w))
        if last >= 0:  # the ISI that crosses into this word
            d = base + first - last
            if d < 64:
                small |= one << np.uint64(d)
            elif d <= span:
                for j in range(nbig):
                    if big[j] == d:
                        break
                else:
                    big[nbig] = d
                    nbig += 1
        last = base + top
        if popcount(w) >= 8:
            # dense word: find every spike's successor at once, distance by distance (the
            # loop runs up to the word's longest ISI, a few steps for a bright pixel)
            rem = w & ~(one << np.uint64(top))
            d = 1
            while rem:
                hit = rem & (w >> np.uint64(d))
                small |= np.uint64(hit != 0) << np.uint64(d)
                rem &= ~hit
                d += 1
        else:
            prev = first
            w &= w - one
            while w:
                s = np.int64(trailing_zeros(w))
                w &= w - one
                small |= one << np.uint64(s - prev)
                prev = s
        if cap > 0 and np.int64(popcount(small)) + nbig >= cap:
            break
    return np.int64(popcount(small)) + nbig


@njit
def _distinct_words_kernel(packed, geo, lo, hi, span, out):  # pragma: no cover - numba
    """:func:`distinct_in_words` over ``[lo, hi)`` for every pixel, image order."""
    h, w = out.shape
    nw = n_words(lo, hi)
    for y in range(h):
        words = np.empty((w + ROW_PAD, nw), np.uint64)
        big = long_isi_buffer(lo, hi)
        base, step = row_words(packed, geo, lo, hi, y, 0, w, words)
        for x in range(w):
            out[y, x] = distinct_in_words(words, base + step * x, nw, lo, lo, hi, span, big, 0)
    return out


def distinct_isi_counts_packed(packed: np.ndarray, layout, end: int, span: int) -> np.ndarray:
    """:func:`distinct_isi_counts` at one step, straight from packed frames.

    Parameters
    ----------
    packed : ndarray (n, frame_bytes) uint8
        Packed frames (``.dat`` layout described by ``layout``).
    layout : cfsr.layout.Layout
        Geometry of the frames.
    end : int
        Index of the evaluation step t in ``packed``.
    span : int
        The paper's ``T`` (steps).

    Returns
    -------
    counts : ndarray (H, W) int32
        ``|S_x(t)|`` of Eq. 5, upright.
    """
    if span < 1:
        raise ValueError(f"span T must be >= 1 step, got {span}")
    n = packed.shape[0]
    if not 0 <= end < n:
        raise ValueError(f"evaluation step {end} outside the window of {n} steps")
    lo, hi = max(0, end - span + 1), end + 1
    out = np.empty((layout.height, layout.width), np.int32)
    return _distinct_words_kernel(
        np.ascontiguousarray(packed, dtype=np.uint8), geometry(layout), lo, hi, int(span), out
    )
