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
:func:`cfsr.methods.cfsr.pipeline.fine_stage`; docs/methods.md, "Windows as long as the motion
allows").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from cfsr._jit import njit
from cfsr._words import (
    ROW_PAD,
    Words,
    count_range,
    n_words,
    next_spike,
    prefix_counts,
    prev_spike,
    row_words,
)
from cfsr.methods._spiketimes import candidate_run
from cfsr.methods.registry import MAX_WINDOW_STEPS, MethodSettings, Param

__all__ = [
    "SLOW_PARAMS",
    "HALVES",
    "slow_window",
    "slow_rates",
    "slow_reach",
    "slow_fuse",
    "slow_class",
]

#: Half-widths (steps) of the centred windows tried, shortest first, doubling: the longest
#: consistent window is found to within half its length (``slow_rungs`` = 2, the default,
#: adds the 1.5x rungs between them: within a third).
HALVES = (2, 4, 8, 16, 32, 64, 128, 256, 512)

#: The window rule outside the fine region; the fine region's own rule (slow_fine_min,
#: slow_fine_intervals) is the same parameter with another default.
_SLOW_MIN = Param.steps(
    8,
    "slow motion: half-width a pixel's consistent window must reach for its rate to be "
    "taken, outside the fine region",
    maximum=MAX_WINDOW_STEPS // 4,
)
_SLOW_INTERVALS = Param(
    4,
    "intervals",
    "slow motion: whole inter-spike intervals that window must hold, outside the fine region",
    minimum=0,
    maximum=MAX_WINDOW_STEPS,
)

#: CFSR's parameters of the slow-motion stage (inserted into its table).
SLOW_PARAMS: dict[str, Param] = {
    # the longest window tried: 257 steps (6 ms); longer ones gained nothing on the vibrating
    # mount and drift scenes (docs/methods.md, "Windows as long as the motion allows")
    "slow_reach": Param.steps(
        128,
        "slow motion: half-width of the longest centred window tried (0: stage off)",
        minimum=0,
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    # one rung between doublings (1.5x) from 8 steps up: the window a pixel reaches is then
    # found to within a third of its length; a still pixel whose 257-step window fails kept 129
    # steps where 193 held (the 0.5 px 20 Hz vibration and the 0.001 px/step drift, where
    # CSR's 160-step rule beat CFSR outside its fine region); with the static span centred:
    # vibrate +0.29, drift +0.15, pan +0.17, no scene lower than -0.06 (noisy motion region),
    # REDS -0.01, about 1.5 % more CPU per frame
    "slow_rungs": Param(
        2,
        "rungs",
        "slow motion: windows tried per doubling of the half-width from 8 steps (1: 2, 4, 8, "
        "16, ...; 2: also 12, 24, 48, ...)",
        minimum=1,
        maximum=2,
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
    "slow_min": _SLOW_MIN,
    "slow_intervals": _SLOW_INTERVALS,
    # inside the fine region PatchMatch averages matches from other pixels, which cancels
    # per-pixel gain and dark-current spread that a single pixel's window keeps: a longer
    # window is asked for, and the two estimates are averaged (noisy scene: -1.2 dB in the
    # motion region replacing, +0.01 averaging); same units and ranges as outside it
    "slow_fine_min": replace(
        _SLOW_MIN, default=32, help="slow motion: as slow_min, inside the fine region"
    ),
    "slow_fine_intervals": replace(
        _SLOW_INTERVALS, default=12, help="slow motion: as slow_intervals, inside the fine region"
    ),
    # three eighths: with 24 PatchMatch targets 2 steps apart PatchMatch's average is the
    # better half inside the fine region; at 1/2 the windows cost the noisy scene's motion
    # region 0.10 dB against the stage off (30.43 against 30.53, 2000 steps), at 3/8 nothing,
    # and no other scene, REDS file or sweep cell moved by more than 0.04 (REDS mean +0.01)
    "slow_fine_weight": Param(
        0.375,
        "",
        "slow motion: weight of the window's rate against PatchMatch's inside the fine region "
        "(0: PatchMatch's alone)",
        minimum=0.0,
        maximum=1.0,
    ),
    # under temporal noise the bounds fail on still pixels: their windows end early and a
    # short window's rate replaced a 160-step static estimate (shot noise: disk -2.6 dB)
    "slow_noise": Param(
        0.0,
        "",
        "slow motion: frame temporal-noise level (median relative interval spread) above "
        "which the stage is off",
        minimum=0.0,
        maximum=10.0,
    ),
    "slow_fine_full": Param.steps(
        128,
        "slow motion: half-width from which the window's rate replaces PatchMatch's inside "
        "the fine region (0: never)",
        minimum=0,
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    # the slow class of a region (slow_fuse): a fine-region pixel whose neighbourhood's windows
    # are nearly all long moves by a fraction of a pixel over them (a vibrating mount, a drift,
    # a pan, the inside of a slow mover); there PatchMatch's integer offsets cannot follow the
    # motion and its average over +-48 steps blurs it, while the window is centred and tested
    "slow_region": Param(
        9,
        "pixels",
        "slow motion: side of the square over which the share of long windows is measured "
        "(0: no slow class)",
        minimum=0,
        maximum=255,
    ),
    "slow_region_half": Param.steps(
        16,
        "slow motion: half-width from which a window counts as long for the slow class (the "
        "pixel's own window must reach it too)",
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    "slow_region_share": Param(
        0.9,
        "",
        "slow motion: share of the square's pixels with a long window that makes the slow "
        "class",
        minimum=0.0,
        maximum=1.0,
    ),
    "slow_region_intervals": Param(
        6,
        "intervals",
        "slow motion: whole intervals a slow-class pixel's window must hold",
        minimum=0,
        maximum=MAX_WINDOW_STEPS,
    ),
    # three quarters: PatchMatch's average over other pixels cancels their gain spread, which
    # a single pixel's window keeps (full weight: noisy scene -0.8 dB in the motion region);
    # over half, the 0.5 px 200 Hz vibration's motion region +0.33 (first, TFA 39.93 before
    # 39.63), drift +0.12, pan +0.11, no scene lower (alone), REDS -0.01
    "slow_region_weight": Param(
        0.75,
        "",
        "slow motion: share of PatchMatch's weight the window's rate takes over in the slow "
        "class (0: class off, 1: the window's rate alone)",
        minimum=0.0,
        maximum=1.0,
    ),
    # the slow class compares a pixel's window with PatchMatch's average and asks a whole
    # square of long windows, which temporal noise rarely fakes: it stays on up to this level
    # (REDS' 203 files, 0.07-0.33: +0.15, +0.03, 0; shot noise on disk, fan, car: 0 to +0.05)
    "slow_region_noise": Param(
        0.5,
        "",
        "slow motion: frame temporal-noise level up to which the slow class stays on when the "
        "rest of the stage is off (slow_noise)",
        minimum=0.0,
        maximum=10.0,
    ),
    # a fixed-pattern spread (per-pixel gain, dark current) makes the windows' rates rougher
    # than PatchMatch's average of other pixels: 1.4-1.6x on the noisy scene, at most 1.13x
    # on every noiseless scene and REDS file
    "slow_rough": Param(
        1.3,
        "",
        "slow motion: ratio of the windows' high-pass energy to PatchMatch's in the slow class "
        "above which the class is off (a fixed-pattern spread)",
        minimum=0.0,
        maximum=100.0,
    ),
}


class _Rule(NamedTuple):
    """The window rule of :func:`_slow_kernel` (a kernel argument group)."""

    c: int  #: index of t in the window
    halves: np.ndarray  #: int64 half-widths, ascending
    slack: float
    y0: int
    x0: int


@njit(helper=True)
def _bounds(k, first, last, ln):  # pragma: no cover - numba
    """Exact bounds ``(lo, hi)`` on a constant rate and its estimate, from ``k`` spikes, the
    first at step ``first`` and the last at ``last``, of a window ``ln`` steps long (module
    docstring)."""
    lo = (k - 1.0) / ln
    hi = (k + 1.0) / ln
    est = k / ln
    if k >= 2:
        d = float(last - first)
        est = (k - 1.0) / d
        lo = max(lo, (k - 1.0) / (d + 1.0))
        if d > 1.0:
            hi = min(hi, (k - 1.0) / (d - 1.0))
    return lo, hi, est


@njit(helper=True)
def slow_window(words, r, lo, hi, prefix, c, halves, slack):  # pragma: no cover - numba
    """Rate, half-width and spikes of the longest consistent centred window around step ``c``.

    The pixel's spikes are word row ``r`` (:mod:`cfsr._words`) over ``[lo, hi)``, which
    holds every window tried, with its :func:`~cfsr._words.prefix_counts` ``prefix``: each
    window costs two popcounts and two bit scans, whatever its spikes. For each half-width
    ``H`` of ``halves`` the window ``[c - H, c + H]``
    and its two halves ``[c - H, c]`` and ``[c, c + H]`` each bound a constant rate (count
    and first-to-last rules, widened by ``slack``; the halves catch a change symmetric about
    c, which the centred average alone hides). Returns ``(rate, half, spikes)``: ``half`` is
    the longest half-width whose bounds meet all the shorter ones', ``rate`` the whole
    window's first-to-last rate (the count rate below two spikes), ``spikes`` the window's
    spikes; ``(0, 0, 0)`` when even the shortest window's bounds disagree.
    """
    lo_b = -1.0
    hi_b = 2.0
    rate = 0.0
    half = 0
    spikes = 0
    near_l = prev_spike(words, r, lo, c, lo)  # last spike <= c (-1: none)
    near_r = next_spike(words, r, lo, c, hi)  # first spike >= c (-1: none)
    # spikes before c and up to c: each window's counts are two more popcounts
    to_c = count_range(words, r, lo, prefix, lo, c)
    to_c1 = to_c + (1 if near_l == c else 0)
    for j in range(halves.shape[0]):
        hw = halves[j]
        a = c - hw
        b = c + hw + 1
        to_a = count_range(words, r, lo, prefix, lo, a)
        to_b = count_range(words, r, lo, prefix, lo, b)
        k = to_b - to_a
        nl = to_c1 - to_a
        nr = to_b - to_c
        first = next_spike(words, r, lo, a, b) if k > 0 else -1
        last = prev_spike(words, r, lo, b - 1, a) if k > 0 else -1
        lo0, hi0, est = _bounds(k, first, last, 2.0 * hw + 1.0)
        lo1, hi1, _ = _bounds(nl, first, near_l, hw + 1.0)
        lo2, hi2, _ = _bounds(nr, near_r, last, hw + 1.0)
        for lo_p, hi_p in ((lo0, hi0), (lo1, hi1), (lo2, hi2)):
            mid = 0.5 * (lo_p + hi_p)
            rad = 0.5 * (hi_p - lo_p) * slack
            lo_b = max(lo_b, mid - rad)
            hi_b = min(hi_b, mid + rad)
        if lo_b > hi_b:
            break
        rate = est
        half = hw
        spikes = k
    return rate, half, spikes


@njit
def _slow_kernel(src, rule, cand, rate, half, count):  # pragma: no cover - numba
    """:func:`slow_window` of the pixels ``cand`` (crop at ``rule.y0, rule.x0``) from their
    spikes in ``[src.lo, src.hi)``, words gathered row by row over the candidates' span."""
    packed, geo, lo, hi = src
    c, halves, slack, y0, x0 = rule
    hh = cand.shape[0]
    nw = n_words(lo, hi)
    for i in range(hh):
        a_x, b_x = candidate_run(cand, i)
        if a_x < 0:
            continue
        words = np.empty((b_x - a_x + ROW_PAD, max(1, nw)), np.uint64)
        prefix = np.empty(nw + 1, np.int64)
        base, step = row_words(packed, geo, lo, hi, y0 + i, x0 + a_x, x0 + b_x, words)
        for x in range(a_x, b_x):
            if not cand[i, x]:
                continue
            row = base + step * (x - a_x)
            prefix_counts(words, row, nw, prefix)
            r, hw, k = slow_window(words, row, lo, hi, prefix, c, halves, slack)
            rate[i, x] = np.float32(r)
            half[i, x] = hw
            count[i, x] = k


@dataclass(frozen=True)
class SlowSettings(MethodSettings):
    """The slow-motion stage's parameters (:data:`SLOW_PARAMS`: meaning, unit and range);
    CFSR's settings extend them."""

    slow_reach: int  #: steps, half-width of the longest window (0: stage off)
    slow_rungs: int  #: windows per doubling of the half-width (1 or 2)
    slow_slack: float
    slow_min: int  #: steps
    slow_intervals: int  #: intervals
    slow_fine_min: int  #: steps
    slow_fine_intervals: int  #: intervals
    slow_fine_weight: float
    slow_noise: float
    slow_fine_full: int  #: steps
    slow_region: int  #: pixels
    slow_region_half: int  #: steps
    slow_region_share: float
    slow_region_intervals: int  #: intervals
    slow_region_weight: float
    slow_region_noise: float
    slow_rough: float


def slow_reach(s: SlowSettings) -> int:
    """Steps on each side of t the slow-motion stage reads (0: off)."""
    return s.slow_reach


def _halves(reach: int, n_before: int, n_after: int, rungs: int = 1) -> np.ndarray:
    top = min(int(reach), int(n_before), int(n_after))
    ladder = list(HALVES) + ([h * 3 // 2 for h in HALVES if h >= 8] if rungs >= 2 else [])
    hs = [h for h in ladder if h < top] + [top]
    return np.array(sorted(set(h for h in hs if h >= 1)), np.int64)


def slow_rates(
    src,
    center: int,
    cand: np.ndarray,
    *,
    reach: int,
    slack: float = 1.0,
    halves: Sequence[int] | None = None,
    rungs: int = 1,
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
    rungs : int
        With the default ladder: 2 adds the 1.5x half-widths from 12 steps (``slow_rungs``).

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
        _halves(reach, center, src.n - 1 - center, rungs)
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
    src,
    center: int,
    rate: np.ndarray,
    fine: np.ndarray | None,
    s: SlowSettings,
    active: np.ndarray | None = None,
    noise: float | None = None,
) -> np.ndarray:
    """CFSR's output ``rate`` with the slow-motion windows where the motion allows them.

    Outside the fine region (``fine``, bool (H, W); None: empty) a pixel whose consistent
    centred window reaches ``slow_min`` steps each side with ``slow_intervals`` whole
    intervals takes that window's rate; inside it, the window must reach ``slow_fine_min``
    with ``slow_fine_intervals``, and its rate is averaged with PatchMatch's
    (``slow_fine_weight``). Elsewhere (fast motion, too few spikes) ``rate`` is kept.
    ``slow_reach = 0`` returns ``rate`` itself. Only the pixels of ``active`` (bool (H, W);
    None: all) are looked at: the tiles CFSR's static gate passes are still, and their rate
    is already a long window's (the cost follows the moving area). ``noise`` is the frame's
    temporal-noise level (:func:`cfsr.methods.cfsr.steady_distinction.noise_level`, the median
    relative interval spread; None: unknown): above ``slow_noise`` the exact integrate-and-fire
    bounds do not hold, noise ends still pixels' windows early and their short windows are worse
    than the static estimate, so ``rate`` is returned. Rates in spikes per step, float32
    (H, W).
    """
    reach = s.slow_reach
    noisy = noise is not None and noise > s.slow_noise
    has_fine = fine is not None and bool(fine.any())
    if reach <= 0 or (noisy and not (has_fine and noise <= s.slow_region_noise)):
        return rate
    h, w = rate.shape
    cand = np.ones((h, w), bool) if active is None else active
    slow, half, count = slow_rates(
        src, center, cand, reach=reach, slack=s.slow_slack, rungs=s.slow_rungs
    )
    whole = count - 1  # whole intervals between the window's first and last spike
    # under temporal noise only the slow class below: a still pixel's window ends early there
    take = (half >= s.slow_min) & (whole >= s.slow_intervals) & (not noisy)
    out = np.where(take, slow, rate)
    if has_fine:
        wgt = np.where(
            (half >= s.slow_fine_full) & (s.slow_fine_full > 0),
            np.float32(1.0),
            np.float32(s.slow_fine_weight),
        )
        inner = fine & (half >= s.slow_fine_min) & (whole >= s.slow_fine_intervals)
        wgt = np.where(inner & (not noisy), wgt, np.float32(0.0))
        wgt = _slow_class(slow, rate, half, whole, fine, cand, wgt, s)
        out = np.where(fine, wgt * slow + (1 - wgt) * rate, out)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def slow_class(
    half: np.ndarray,
    whole: np.ndarray,
    fine: np.ndarray,
    cand: np.ndarray,
    s: SlowSettings,
) -> np.ndarray:
    """The fine-region pixels of the slow class (bool (H, W)): a region whose windows are
    nearly all long, i.e. whose motion stays under a fraction of a pixel over them.

    A pixel is in it where its own consistent window reaches ``slow_region_half`` steps each
    side with ``slow_region_intervals`` whole intervals (``half``, ``whole``: the window's
    half-width and whole intervals, :func:`slow_rates`), and at least ``slow_region_share``
    of the ``slow_region``-pixel square around it reach ``slow_region_half`` too (pixels
    outside ``cand`` lie in tiles the static gate passes: still, so long). The share is the
    speed class of the region: a fast mover has short windows at its edges and within its
    texture, which a lone long window inside it does not outweigh.
    """
    side = s.slow_region
    if side <= 0:
        return np.zeros(fine.shape, bool)
    import cv2

    a = s.slow_region_half
    long_ = ((half >= a) | ~cand).astype(np.float32)
    share = cv2.blur(long_, (side, side))  # the square's mean, mirrored at the frame's edge
    return (
        fine
        & (half >= a)
        & (whole >= s.slow_region_intervals)
        & (share >= np.float32(s.slow_region_share) - np.float32(1e-6))
    )


def _rough(img: np.ndarray, sel: np.ndarray) -> float:
    """Mean high-pass energy (the image less its 3 x 3 mean, squared) over ``sel``."""
    import cv2

    hp = img - cv2.blur(img, (3, 3))
    return float(np.mean(np.square(hp[sel], dtype=np.float64)))


def _slow_class(slow, rate, half, whole, fine, cand, wgt, s: SlowSettings) -> np.ndarray:
    """``wgt`` (the window's weight against PatchMatch's, float32 (H, W)) with the slow class
    (:func:`slow_class`) moved ``slow_region_weight`` of the way to the window's rate, unless
    the windows' rates there are ``slow_rough`` times rougher than PatchMatch's (a
    fixed-pattern spread that only PatchMatch's average of other pixels cancels)."""
    rw = s.slow_region_weight
    if rw <= 0.0:
        return wgt
    cls = slow_class(half, whole, fine, cand, s)
    if not cls.any():
        return wgt
    if _rough(slow, cls) > s.slow_rough * _rough(rate, cls):
        return wgt
    return np.where(cls, wgt + (1 - wgt) * np.float32(rw), wgt).astype(np.float32)
