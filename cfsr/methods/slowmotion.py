"""Slow motion: per pixel, the longest centred window the motion allows.

A pixel of constant brightness is an integrate-and-fire pixel at a constant rate r, and
every window of its spikes bounds r exactly (design section 3; :func:`cfsr.methods.tfp.
span_rate`): ``k`` spikes in ``L`` steps satisfy ``|k - L r| < 1`` (Eq. 4's count is off by
less than one spike), and the ``k - 1`` whole intervals from the first to the last spike span
``(k - 1) / r`` steps to within one step, so

    r in ((k - 1) / (d + 1), (k - 1) / (d - 1)),    d = last - first spike (steps).

Windows centred on t, ``[t - H, t + H]``, grow through ``halves``; each gives such an
interval, and the pixel's rate is constant over the longest window whose interval still
meets those of all shorter ones (the intersection-of-confidence-intervals rule, Katkovnik's
adaptive window). A still pixel reaches the longest window; under motion a pixel's rate
drifts and the intersection empties as soon as the change outgrows what the spikes can
resolve, i.e. when the window's motion blur would exceed its quantisation error. The rate is
the first-to-last rule over the window reached (the static-rate rule of CSR: Eq. 4 with whole
intervals), and the half-width reached is the per-pixel **speed estimate**: a long window
where the image moves by a fraction of a pixel over it (a vibrating mount, a drift, a slow
pan), a short one under a fast mover.

Intervals are widened by ``slack`` (a factor on their half-width about their centre): 1 is
the exact integrate-and-fire bound; more accepts a slow change as long as its blur stays
within ``slack`` times the window's own error, trading bias for the longer window's
precision, and absorbs temporal noise.

CFSR uses it where its fine region or a moving static pixel would otherwise take a short
interval or a trailing window (:func:`slow_rates`, hook in
:func:`cfsr.methods.cfsr_fine.fine_stage`; docs/methods.md, "Windows as long as the motion
allows").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
from numba import njit, prange

from cfsr._words import ROW_PAD, Words, n_words, range_times, row_words
from cfsr.methods.registry import MAX_WINDOW_STEPS, Param

__all__ = ["SLOW_PARAMS", "HALVES", "slow_window", "slow_rates", "slow_reach", "slow_fuse"]

#: Half-widths (steps) of the centred windows tried, shortest first (about x1.5 apart: the
#: longest consistent window is found to within a third of its length).
HALVES = (2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192)

#: CFSR's parameters of the slow-motion stage (inserted into its table).
SLOW_PARAMS: dict[str, Param] = {
    # the longest window tried: 257 steps (6 ms); longer ones gained nothing on the vibrating
    # mount and drift scenes (docs/methods.md, "Windows as long as the motion allows")
    "slow_reach": Param(
        128,
        "steps",
        "slow motion: half-width of the longest centred window tried (0: stage off)",
        minimum=0,
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    "slow_slack": Param(
        1.0,
        "",
        "slow motion: factor on the exact integrate-and-fire rate bounds (1: exact)",
        minimum=0.1,
        maximum=100.0,
    ),
    # outside the fine region a window of 17 steps holding 5 spikes already beats the static
    # estimate where the pixel moves slowly; a test with fewer spikes has too little power
    # (dark movers passed it: the lowlight scene lost 4 dB with no spike floor)
    "slow_min": Param(
        8,
        "steps",
        "slow motion: half-width a pixel's consistent window must reach for its rate to be "
        "taken, outside the fine region",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    "slow_intervals": Param(
        4,
        "intervals",
        "slow motion: whole inter-spike intervals that window must hold, outside the fine region",
        minimum=0,
        maximum=MAX_WINDOW_STEPS,
    ),
    # inside the fine region PatchMatch averages matches from other pixels, which cancels
    # per-pixel gain and dark-current spread that a single pixel's window keeps: a longer
    # window is asked for, and the two estimates are averaged (noisy scene: -1.2 dB in the
    # motion region replacing, +0.01 averaging)
    "slow_fine_min": Param(
        32,
        "steps",
        "slow motion: as slow_min, inside the fine region",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    "slow_fine_intervals": Param(
        12,
        "intervals",
        "slow motion: as slow_intervals, inside the fine region",
        minimum=0,
        maximum=MAX_WINDOW_STEPS,
    ),
    "slow_fine_weight": Param(
        0.5,
        "",
        "slow motion: weight of the window's rate against PatchMatch's inside the fine region "
        "(0: PatchMatch's alone)",
        minimum=0.0,
        maximum=1.0,
    ),
}


class _Rule(NamedTuple):
    """The window rule of :func:`_slow_kernel` (a kernel argument group)."""

    c: int  #: index of t in the window
    halves: np.ndarray  #: int64 half-widths, ascending
    slack: float
    y0: int
    x0: int


@njit(cache=True, inline="always")
def _bounds(times, i0, i1, ln):  # pragma: no cover - numba
    """Exact bounds ``(lo, hi)`` on a constant rate and its estimate, from the spikes
    ``times[i0:i1]`` of a window ``ln`` steps long (module docstring)."""
    k = i1 - i0
    lo = (k - 1.0) / ln
    hi = (k + 1.0) / ln
    est = k / ln
    if k >= 2:
        d = float(times[i1 - 1] - times[i0])
        est = (k - 1.0) / d
        lo = max(lo, (k - 1.0) / (d + 1.0))
        if d > 1.0:
            hi = min(hi, (k - 1.0) / (d - 1.0))
    return lo, hi, est


@njit(cache=True, inline="always")
def slow_window(times, ns, c, halves, slack):  # pragma: no cover - numba
    """Rate and half-width of the longest consistent centred window around step ``c``.

    ``times[:ns]`` are the pixel's spike steps (ascending) and cover every window tried. For
    each half-width ``H`` of ``halves`` the window ``[c - H, c + H]`` and its two halves
    ``[c - H, c]`` and ``[c, c + H]`` each bound a constant rate (count and first-to-last
    rules, widened by ``slack``; the halves catch a change symmetric about c, which the
    centred average alone hides). Returns ``(rate, half, spikes)``: ``half`` is the longest
    half-width whose bounds meet all the shorter ones', ``rate`` the whole window's
    first-to-last rate (the count rate below two spikes), ``spikes`` the window's spikes;
    ``(0, 0, 0)`` when even the shortest window's bounds disagree.
    """
    lo_b = -1.0
    hi_b = 2.0
    rate = 0.0
    half = 0
    spikes = 0
    ia = np.searchsorted(times[:ns], c, side="left")  # first spike >= c - H
    ic = ia  # first spike >= c
    id_ = np.searchsorted(times[:ns], c + 1, side="left")  # first spike >= c + 1
    ib = id_  # first spike >= c + H + 1
    for j in range(halves.shape[0]):
        hw = halves[j]
        a = c - hw
        b = c + hw + 1
        while ia > 0 and times[ia - 1] >= a:
            ia -= 1
        while ib < ns and times[ib] < b:
            ib += 1
        ok = True
        for part in range(3):
            if part == 0:
                lo, hi, est = _bounds(times, ia, ib, 2.0 * hw + 1.0)
                rest = est
                kk = ib - ia
            elif part == 1:
                lo, hi, est = _bounds(times, ia, id_, hw + 1.0)
            else:
                lo, hi, est = _bounds(times, ic, ib, hw + 1.0)
            mid = 0.5 * (lo + hi)
            rad = 0.5 * (hi - lo) * slack
            lo_b = max(lo_b, mid - rad)
            hi_b = min(hi_b, mid + rad)
            if lo_b > hi_b:
                ok = False
                break
        if not ok:
            break
        rate = rest
        half = hw
        spikes = kk
    return rate, half, spikes


@njit(parallel=True, cache=True)
def _slow_kernel(src, rule, cand, rate, half, count):  # pragma: no cover - numba
    """:func:`slow_window` of the pixels ``cand`` (crop at ``rule.y0, rule.x0``) from their
    spikes in ``[src.lo, src.hi)``, words gathered row by row over the candidates' span."""
    packed, geo, lo, hi = src
    c, halves, slack, y0, x0 = rule
    hh, ww = cand.shape
    nw = n_words(lo, hi)
    for i in prange(hh):
        a_x = -1
        b_x = -1
        for x in range(ww):
            if cand[i, x]:
                if a_x < 0:
                    a_x = x
                b_x = x + 1
        if a_x < 0:
            continue
        tm = np.empty(hi - lo, np.int64)
        words = np.empty((b_x - a_x + ROW_PAD, max(1, nw)), np.uint64)
        base, step = row_words(packed, geo, lo, hi, y0 + i, x0 + a_x, x0 + b_x, words)
        for x in range(a_x, b_x):
            if not cand[i, x]:
                continue
            ns = range_times(words, base + step * (x - a_x), lo, lo, hi, tm)
            r, hw, k = slow_window(tm, ns, c, halves, slack)
            rate[i, x] = np.float32(r)
            half[i, x] = hw
            count[i, x] = k


def slow_reach(p: Mapping[str, Any]) -> int:
    """Steps on each side of t the slow-motion stage reads (0: off)."""
    return int(p.get("slow_reach", 0))


def _halves(reach: int, n_before: int, n_after: int) -> np.ndarray:
    top = min(int(reach), int(n_before), int(n_after))
    hs = [h for h in HALVES if h < top] + [top]
    return np.array(sorted(set(h for h in hs if h >= 1)), np.int64)


def slow_rates(
    src,
    center: int,
    cand: np.ndarray,
    *,
    reach: int,
    slack: float = 1.0,
    halves: Sequence[int] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rate over the longest consistent centred window, and its half-width, per pixel.

    Parameters
    ----------
    src : PackedWindow
        The window (:class:`cfsr._words.PackedWindow`).
    center : int
        Index of t in the window.
    cand : ndarray (H, W) bool
        Pixels to estimate (others get rate 0, half-width 0).
    reach : int
        Longest half-width tried (steps), clipped to the window on both sides of t.
    slack : float
        Factor on the exact bounds (1: exact integrate-and-fire bounds).
    halves : sequence of int, optional
        Half-widths to try (steps, ascending); default :data:`HALVES` up to ``reach``.

    Returns
    -------
    rate : ndarray (H, W) float32
        Spikes per step, in [0, 1].
    half : ndarray (H, W) int32
        Half-width (steps) of the window the rate comes from; 0 where not estimated.
    count : ndarray (H, W) int32
        Spikes in that window (the evidence the consistency test had).

    Examples
    --------
    >>> import numpy as np
    >>> from cfsr._words import PackedWindow
    >>> spikes = np.zeros((401, 1, 2), np.uint8)
    >>> spikes[::4, 0, 0] = 1                    # still: 0.25 spikes/step throughout
    >>> spikes[:200:4, 0, 1] = 1; spikes[200::2, 0, 1] = 1   # its rate doubles at t = 200
    >>> rate, half, _ = slow_rates(PackedWindow.from_frames(spikes), 200, np.ones((1, 2), bool),
    ...                         reach=192)
    >>> float(rate[0, 0]), int(half[0, 0]), int(half[0, 1]) < 8
    (0.25, 192, True)
    """
    h, w = cand.shape
    rate = np.zeros((h, w), np.float32)
    half = np.zeros((h, w), np.int32)
    count = np.zeros((h, w), np.int32)
    if not cand.any() or reach <= 0:
        return rate, half, count
    hs = (
        _halves(reach, center, src.n - 1 - center)
        if halves is None
        else np.asarray(sorted(halves), np.int64)
    )
    if hs.size == 0 or hs[0] < 1:
        return rate, half, count
    if center - hs[-1] < 0 or center + hs[-1] >= src.n:
        raise ValueError(
            f"half-width {int(hs[-1])} reaches outside the window (t = {center}, n = {src.n})"
        )
    ys, xs = np.nonzero(cand.any(axis=1))[0], np.nonzero(cand.any(axis=0))[0]
    y0, y1, x0, x1 = int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1
    lo, hi = center - int(hs[-1]), center + int(hs[-1]) + 1
    crop = np.ascontiguousarray(cand[y0:y1, x0:x1])
    r = np.zeros(crop.shape, np.float32)
    k = np.zeros(crop.shape, np.int32)
    m = np.zeros(crop.shape, np.int32)
    _slow_kernel(
        Words(src.packed, src.geo, int(lo), int(hi)),
        _Rule(int(center), hs, float(slack), y0, x0),
        crop,
        r,
        k,
        m,
    )
    rate[y0:y1, x0:x1] = r
    half[y0:y1, x0:x1] = k
    count[y0:y1, x0:x1] = m
    return rate, half, count


def slow_fuse(
    src, center: int, rate: np.ndarray, fine: np.ndarray | None, p: Mapping[str, Any]
) -> np.ndarray:
    """CFSR's output ``rate`` with the slow-motion windows where the motion allows them.

    Outside the fine region (``fine``, bool (H, W); None: empty) a pixel whose consistent
    centred window reaches ``slow_min`` steps each side with ``slow_intervals`` whole
    intervals takes that window's rate; inside it, the window must reach ``slow_fine_min``
    with ``slow_fine_intervals``, and its rate is averaged with PatchMatch's
    (``slow_fine_weight``). Elsewhere (fast motion, too few spikes) ``rate`` is kept.
    ``slow_reach = 0`` returns ``rate`` itself. Rates in spikes per step, float32 (H, W).
    """
    reach = slow_reach(p)
    if reach <= 0:
        return rate
    h, w = rate.shape
    slow, half, count = slow_rates(
        src, center, np.ones((h, w), bool), reach=reach, slack=float(p["slow_slack"])
    )
    whole = count - 1  # whole intervals between the window's first and last spike
    take = (half >= int(p["slow_min"])) & (whole >= int(p["slow_intervals"]))
    out = np.where(take, slow, rate)
    if fine is not None and fine.any():
        wgt = np.float32(p["slow_fine_weight"])
        inner = fine & (half >= int(p["slow_fine_min"])) & (whole >= int(p["slow_fine_intervals"]))
        out = np.where(fine, np.where(inner, wgt * slow + (1 - wgt) * rate, rate), out)
    return np.clip(out, 0.0, 1.0).astype(np.float32)
