"""Still pixels: a proof, from a pixel's own spikes, that it is static background at t.

A pixel of constant brightness is an integrate-and-fire pixel at a constant rate r: its k-th
spike falls on the first step where its integral reaches k, so its spike times lie within one
step of the line ``t_k = t_0 + k / r`` (a tighter fact than "every interval is floor(1/r) or
ceil(1/r)", which any mixture of two neighbouring lengths satisfies: bright moving texture
has intervals of 2 and 3 steps at every brightness from 0.33 to 0.5 spikes/step). The **run
at t** is the longest stretch of spikes around t that fits such a line: grown from the two
spikes around t, alternately to the left and to the right, while some period T keeps every
spike of the stretch within one step of the line through the spike at (or before) t, a
feasible range of T that each added spike narrows by one comparison.

A pixel is **still** at t when t lies inside its run (at least ``EDGE`` steps from both ends:
a change at t disturbs the interval containing it) and either

* the run reaches an end of the searched range (``[t - reach, t + reach]``): the pixel did not
  change between t and that end, or
* its rate **returns**: the run is at least ``min_run`` steps long and, beyond a *jump* (an
  interval that differs from the run's period by at least ``max(2, jump * T)`` steps), the
  pixel holds a constant rate again for at least ``min_run`` steps with a period range that
  overlaps the run's (both ranges taken without the stretch's end spikes: the spike next to
  a change can fit the line by tilting it off the true period). Stretches are cut greedily,
  walking away from the run, by the same line rule. A mover that passes a pixel periodically
  (fan blades) makes its background come back after every pass, always at the same rate; a
  moving texture rarely holds an exact constant rate for ``min_run`` steps, let alone twice
  at the same rate across a change.

Still pixels are static at t; the fine mask leaves them out and its safety margin does not
grow into them (:func:`cfsr.methods.cfsr.fine_mask.fine_mask`), and their rate is the run's: spikes
minus one over the steps from its first to its last spike, a long exact static estimate. The
test has no noise tolerance: under temporal noise a static pixel's spikes leave the line, it
is not proven still, and the fine mask is what it was without the test.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cfsr._jit import njit
from cfsr._words import ROW_PAD, Words, n_words, range_times, row_words
from cfsr.methods._spiketimes import candidate_run

__all__ = ["still_pixels", "EDGE"]

#: Steps a still pixel's run must reach beyond t on each side.
EDGE = 2


# Period ranges are kept as fractions ``(ln / ld, hn / hd)`` of whole numbers (steps over
# spike counts), compared by cross-multiplying: no division in the walks.


@njit(helper=True)
def _narrow(ln, ld, hn, hd, dt, dk):  # pragma: no cover - numba
    """The period range narrowed by ``|dt - dk * T| < 1`` (a spike ``dk`` spikes and ``dt``
    steps from the anchor lies within one step of the line; ``dk > 0``): ``(fits, ln, ld,
    hn, hd)``, ``fits`` when the range is not empty."""
    if (dt - 1) * ld > ln * dk:
        ln = dt - 1
        ld = dk
    if (dt + 1) * hd < hn * dk:
        hn = dt + 1
        hd = dk
    return ln * hd < hn * ld, ln, ld, hn, hd


@njit
def _range(tm, i, j):  # pragma: no cover - numba
    """The period range ``(ln, ld, hn, hd)`` of spikes ``i .. j`` (``j > i``) on the line
    through spike ``i``; empty (``ln / ld >= hn / hd``) when they do not fit one."""
    d0 = tm[i + 1] - tm[i]
    ln, ld, hn, hd = d0 - 1, 1, d0 + 1, 1
    for k in range(i + 2, j + 1):
        _, ln, ld, hn, hd = _narrow(ln, ld, hn, hd, tm[k] - tm[i], k - i)
    return ln, ld, hn, hd


@njit
def _returns(tm, start, stop, direction, rng, period, min_run, jump):  # pragma: no cover
    """Whether, walking from spike ``start`` to spike ``stop`` (``direction`` +-1), a
    stretch of constant rate at least ``min_run`` steps long whose period range overlaps
    ``rng = (ln, ld, hn, hd)`` follows a jump (an interval ``max(2, jump * period)`` steps
    off the period)."""
    ln, ld, hn, hd = rng
    thr = max(2.0, jump * period)
    seen = False
    a = start
    while (stop - a) * direction > 0 and abs(tm[stop] - tm[a]) >= min_run:
        # the stretch anchored at spike a, grown away from the run (one interval always fits)
        b = a + direction
        d0 = abs(tm[b] - tm[a])
        jumped = abs(d0 - period) >= thr
        sln, sld, shn, shd = d0 - 1, 1, d0 + 1, 1
        while (stop - b) * direction > 0:
            d = abs(tm[b + direction] - tm[b])
            ok, n_ln, n_ld, n_hn, n_hd = _narrow(
                sln, sld, shn, shd, abs(tm[b + direction] - tm[a]), abs(b + direction - a)
            )
            if not ok:
                break
            sln, sld, shn, shd = n_ln, n_ld, n_hn, n_hd
            jumped |= abs(d - period) >= thr
            b += direction
        if seen and abs(b - a) >= 4 and abs(tm[b] - tm[a]) >= min_run:
            # the period range of the stretch without its end spikes (the one next to the
            # change may belong to it, tilting the line) overlaps the run's; that range lies
            # within the one its last spike alone allows, ((dt - 1) / dk, (dt + 1) / dk), so
            # where that one misses the run's the walk over the stretch is skipped (same
            # answer: the slow texture's stretches on the disk mostly miss)
            s0, s1 = min(a, b) + 1, max(a, b) - 1
            dt, dk = tm[s1] - tm[s0], s1 - s0
            if (dt - 1) * hd < hn * dk and (dt + 1) * ld > ln * dk:
                sln, sld, shn, shd = _range(tm, s0, s1)
                if sln * hd < hn * sld and shn * ld > ln * shd:
                    return True
        seen |= jumped
        a = b
    return False


@njit
def _run_at(tm, ns, c):  # pragma: no cover - numba
    """The run at step ``c`` in the ``ns`` spike steps ``tm``: ``(i0, i1, (ln, ld, hn,
    hd))``, its first and last spike and its period range; ``i0 = -1`` without a spike at or
    before ``c`` and one after it."""
    if ns < 2 or tm[0] > c or tm[ns - 1] <= c:
        return -1, -1, (0, 1, 0, 1)
    # j: the last spike at or before c (binary search)
    lo_i = 0
    hi_i = ns - 1
    while hi_i - lo_i > 1:
        mid = (lo_i + hi_i) >> 1
        if tm[mid] <= c:
            lo_i = mid
        else:
            hi_i = mid
    j = lo_i
    p = tm[j]
    d0 = tm[j + 1] - p
    ln, ld, hn, hd = d0 - 1, 1, d0 + 1, 1
    i0 = j
    i1 = j + 1
    left = True
    right = True
    while left or right:
        if left:
            if i0 > 0:
                ok, n_ln, n_ld, n_hn, n_hd = _narrow(ln, ld, hn, hd, p - tm[i0 - 1], j - i0 + 1)
                if ok:
                    ln, ld, hn, hd = n_ln, n_ld, n_hn, n_hd
                    i0 -= 1
                else:
                    left = False
            else:
                left = False
        if right:
            if i1 < ns - 1:
                ok, n_ln, n_ld, n_hn, n_hd = _narrow(ln, ld, hn, hd, tm[i1 + 1] - p, i1 + 1 - j)
                if ok:
                    ln, ld, hn, hd = n_ln, n_ld, n_hn, n_hd
                    i1 += 1
                else:
                    right = False
            else:
                right = False
    return i0, i1, (ln, ld, hn, hd)


@njit
def still_pixel(tm, ns, c, min_run, jump):  # pragma: no cover - numba
    """``(still, rate)`` of one pixel from its ``ns`` spike steps ``tm`` (int64, ascending, the
    searched range) at step ``c`` (see the module notes); ``rate`` is the run's, 0 when the
    pixel is not still."""
    if ns < 3:
        return False, 0.0
    i0, i1, rng = _run_at(tm, ns, c)
    if i0 < 0 or min(c - tm[i0], tm[i1] - c) < EDGE:
        return False, 0.0
    length = tm[i1] - tm[i0]
    rate = (i1 - i0) / length
    if i0 == 0 or i1 == ns - 1:  # no change between t and an end of the range
        return True, rate
    if length < min_run:
        return False, 0.0
    if i1 - i0 < 4:
        return False, 0.0
    rng = _range(tm, i0 + 1, i1 - 1)  # without its end spikes (see _returns)
    period = 0.5 * (rng[0] / rng[1] + rng[2] / rng[3])
    if _returns(tm, i0, 0, -1, rng, period, min_run, jump):
        return True, rate
    if _returns(tm, i1, ns - 1, 1, rng, period, min_run, jump):
        return True, rate
    return False, 0.0


class _Test(NamedTuple):
    """What :func:`still_pixel` is asked: at step ``c``, runs of ``min_run`` steps, a change of
    ``jump`` (relative) between them, on the crop whose corner is image pixel ``(y0, x0)``."""

    c: int
    min_run: int
    jump: float
    y0: int
    x0: int


@njit
def _still_kernel(src, kept, test, cand, still, rate):  # pragma: no cover - numba
    """:func:`still_pixel` (``test``: :class:`_Test`) of the pixels ``cand`` from their spikes
    in ``[src.lo, src.hi)`` (:class:`~cfsr._words.Words`): those in ``[lo, mid)`` from the
    words of a whole-frame scan ``kept = (store, bases, s_lo, s_hi)`` (``mid = min(hi,
    s_hi)``; an empty store: ``mid = lo``), the rest from words gathered row by row from the
    first to the last candidate."""
    packed, geo, lo, hi = src
    store, bases, s_lo, s_hi = kept
    c, min_run, jump, y0, x0 = test
    mid = lo
    if store.shape[0] > 0 and s_lo <= lo:
        mid = max(lo, min(hi, s_hi))
    hh = cand.shape[0]
    nw = n_words(mid, hi)
    for i in range(hh):
        a_x, b_x = candidate_run(cand, i)
        if a_x < 0:
            continue
        y = y0 + i
        tm = np.empty(hi - lo, np.int64)
        words = np.empty((b_x - a_x + ROW_PAD, max(1, nw)), np.uint64)
        base, step = 0, 0
        if hi > mid:
            base, step = row_words(packed, geo, mid, hi, y, x0 + a_x, x0 + b_x, words)
        for x in range(a_x, b_x):
            if not cand[i, x]:
                continue
            ns = 0
            if mid > lo:
                ns = range_times(store[y], bases[y, 0] + bases[y, 1] * (x0 + x), s_lo, lo, mid, tm)
            if hi > mid:
                r = base + step * (x - a_x)
                ns += range_times(words, r, mid, mid, hi, tm[ns:])
            s, v = still_pixel(tm, ns, c, min_run, jump)
            still[i, x] = s
            rate[i, x] = np.float32(v)


def still_pixels(
    src,
    center: int,
    cand: np.ndarray,
    *,
    reach: int,
    min_run: int,
    jump: float,
    words: tuple | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Still pixels at ``center`` among ``cand`` (bool ``(H, W)``) and their run rates.

    Parameters
    ----------
    src : PackedWindow
        The window.
    center : int
        Index of t in the window.
    cand : ndarray (H, W) bool
        The pixels to test (others come out not still).
    reach : int
        Steps searched on each side of t (clipped to the window).
    min_run : int
        Steps of constant rate a returning pixel needs, at t and after the jump.
    jump : float
        Relative size of the interval change that separates the two stretches.
    words : (store, bases, lo, hi), optional
        Words of the whole frame already gathered (CFSR's history scan, as
        :func:`cfsr.methods.cfsr.steady_distinction.steadiness` takes them): the spikes they cover
        from ``t - reach`` on are read there, only the rest is gathered.

    Returns
    -------
    still : ndarray (H, W) bool
    rate : ndarray (H, W) float32
        The run's rate (spikes per step) where still, 0 elsewhere.
    """
    h, w = cand.shape
    still = np.zeros((h, w), bool)
    rate = np.zeros((h, w), np.float32)
    if not cand.any() or reach <= 0:
        return still, rate
    ys, xs = np.nonzero(cand.any(axis=1))[0], np.nonzero(cand.any(axis=0))[0]
    y0, y1, x0, x1 = int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1
    lo, hi = max(0, center - reach), min(src.n, center + reach + 1)
    crop = np.ascontiguousarray(cand[y0:y1, x0:x1])
    s = np.zeros(crop.shape, np.bool_)
    v = np.zeros(crop.shape, np.float32)
    if words is None:
        kept = (np.empty((0, 0, 0), np.uint64), np.empty((0, 2), np.int64), 0, 0)
    else:
        store, bases, s_lo, s_hi = words
        kept = (store, bases, int(s_lo), int(s_hi))
    _still_kernel(
        Words(src.packed, src.geo, int(lo), int(hi)),
        kept,
        _Test(int(center), int(min_run), float(jump), y0, x0),
        crop,
        s,
        v,
    )
    still[y0:y1, x0:x1] = s
    rate[y0:y1, x0:x1] = v
    return still, rate
