"""The steady-interval distinction: is a pixel's rate steady around t?

A pixel of constant brightness is an integrate-and-fire pixel at a constant rate r: it fires
where its integral crosses a whole number, so every inter-spike interval is ``floor(1/r)`` or
``ceil(1/r)`` steps -- whatever r is. Light that changes under the pixel (a mover's texture or
edge) changes its intervals. Two tests follow, both per pixel and both from the intervals
around t (all read as spike words, :mod:`cfsr._words`):

* **coarse mask** (``distinction = steady``): the intervals that contain a step of
  ``[t - radius, t + radius]`` (the TFI values of those steps, Eq. 3) spread by
  ``(max - min - 1) / mean``; the pixel is dynamic where the spread exceeds the tolerance.
  A steady pixel's spread is at most 0 (its intervals differ by at most one step) at any
  brightness, so bright static pixels stay static (the paper's distinct-ISI set, Eq. 5-6, has
  the same aim) and dark ones cannot collect spurious values (the distinct-ISI count, over 300
  steps, counts every interval length a noisy dark pixel shows; see docs/methods.md). The
  per-pixel test sees only *change*: the flat interior of a mover is steady, so the mask is
  regularised (closing, hole filling: :func:`cfsr.methods.cfsr.fine_mask.regularise`).
* **static check** (``static_estimator = steady``): the static estimate over a long span
  (:func:`cfsr.methods.tfp.span_rate`, ~exact for a steady pixel) is kept only where t's own
  interval agrees with it, ``|ISI(t) - 1/rate| <= 1 + match / rate``; elsewhere the pixel's
  light changed within the span and its TFI at t (Eq. 3) is used. A mover the masks miss is
  then reconstructed like TFI instead of smeared over the span.

**Noise.** Temporal (shot) noise makes a steady pixel's intervals vary by a relative amount
that does not depend on its rate (a Poisson charge N per threshold gives intervals with
relative spread ~ 1/sqrt(N)). Both tolerances are therefore raised to the frame's noise
level: the median spread of the frame's pixels (most pixels of a camera frame are static;
when more than half move the level is overestimated and the masks err on the static side).
Without temporal noise the median spread is 0 and the fixed tolerances apply.
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple

import numpy as np

from cfsr._borrow import borrow, keep
from cfsr._isi import needs_after, needs_before, tfi_interval
from cfsr._jit import njit
from cfsr._words import (
    PackedWindow,
    Stored,
    Words,
    count_between,
    isi_in_words,
    next_spike,
    prev_spike,
    range_times,
    row_or_stored,
)
from cfsr.methods.registry import choices_of
from cfsr.methods.tfp import span_rate

__all__ = [
    "steadiness",
    "steady_range",
    "noise_level",
    "clipped_median",
    "steady_mask",
    "check_static",
    "DISTINCTIONS",
    "Distinction",
]


class Distinction(StrEnum):
    """The coarse distinction's rule."""

    STEADY = "steady"  #: the interval spread around t, regularised (this module)
    ISI_SET = "isi_set"  #: distinct ISIs in T >= theta (Eq. 5-6, the paper's)


#: Coarse distinctions: ``steady`` (this module) or ``isi_set`` (Eq. 5-6, the paper's).
DISTINCTIONS = choices_of(Distinction)


@njit(helper=True)
def interval_stats(words, r, lo, c, radius, a, b, loc):  # pragma: no cover - numba
    """``(spread, isi)`` of word row ``r``, spikes searched in ``[a, b)``: ``isi`` is the TFI
    interval at ``c`` (Eq. 3; :func:`cfsr._words.isi_in_words`'s numbers), ``spread`` is
    ``(max - min - 1) / mean`` of the whole intervals containing a step of ``[c - radius, c +
    radius]`` (clipped to ``[a, b)``): the one containing the first step, then one per spike
    inside, ending at the next spike. An interval open at the search range's end is only a
    bound on its length, so it is left out, and with fewer than two whole intervals the
    spread is 0 (no evidence of change). <= 0 for a steady pixel (lengths differ by at most
    one step). ``loc``: scratch of at least ``2 * radius + 1`` steps.

    One walk gives both; the two intervals that can be open (the first and the last) take
    :func:`cfsr._isi.tfi_interval` with the neighbours the walk already found (inlining
    ``isi_in_words`` at three places made this kernel take ~15 s to compile).
    """
    t0 = max(a, c - radius)
    t1 = min(b - 1, c + radius)
    p0 = prev_spike(words, r, lo, t0, a)  # the spike that opens the first interval
    ns = range_times(words, r, lo, t0 + 1, t1 + 1, loc)  # each later interval starts here
    nx = next_spike(words, r, lo, t1 + 1, b)  # the spike that closes the last one
    vmin = np.int64(1) << 40
    vmax = np.int64(0)
    tot = np.int64(0)
    k = 0  # closed intervals seen
    # the first interval, containing t0: from p0 to the first spike after t0
    end = loc[0] if ns > 0 else nx
    pp = prev_spike(words, r, lo, p0 - 1, a) if needs_before(p0, end) else -1
    nn = -1
    if needs_after(p0, end):  # the spike after end: the next one inside, or the first after
        if ns > 1:
            nn = loc[1]
        elif ns == 1:
            nn = nx
        else:
            nn = next_spike(words, r, lo, end + 1, b)
    v = tfi_interval(p0, end, pp, nn, a, b)
    if p0 >= 0 and end >= 0:  # a whole interval
        vmin = min(vmin, v)
        vmax = max(vmax, v)
        tot += v
        k += 1
    isi_c = v  # c lies in the first interval unless a spike falls in (t0, c]
    for i in range(ns):
        s = loc[i]
        if i + 1 < ns or nx >= 0:
            d = loc[i + 1] - s if i + 1 < ns else nx - s
            vmin = min(vmin, d)
            vmax = max(vmax, d)
            tot += d
            k += 1
        else:  # the last interval, open on the right
            d = tfi_interval(s, -1, loc[i - 1] if i > 0 else p0, -1, a, b)
        if s <= c:
            isi_c = d
    if k < 2:
        return 0.0, isi_c
    return (vmax - vmin - 1) / (tot / k), isi_c


class _Around(NamedTuple):
    """Where the steadiness is read: ``c`` in a window of ``n`` steps, the intervals within
    ``radius`` steps of it, the TFI's search ``m`` steps each side (Eq. 3)."""

    n: int
    c: int
    radius: int
    m: int


@njit(hot=True)
def _steady_kernel(src, kept, at, spans, spread, isi, rates, active):  # pragma: no cover - numba
    # the spread searches the TFI's range whatever range the words cover, so its open-ended
    # intervals do not depend on who gathered the words
    """Per pixel from its words of ``[src.lo, src.hi)`` (:class:`~cfsr._words.Words`):
    :func:`interval_stats` around ``at.c`` (:class:`_Around`), the TFI interval at it and, for
    each span ``[spans[j, 0], spans[j, 1])``, the ``isi`` span rate
    (:func:`cfsr.methods.tfp.span_rate`; the TFI at ``c`` below two spikes:
    :func:`cfsr.methods.tfp.static_rate`'s rule). Reads the words ``kept``
    (:class:`~cfsr._words.Stored`) when they hold one row per image row, as CFSR's history scan
    leaves them; otherwise gathers them. Where ``active`` (bool ``(H, W)``; empty: every
    pixel) is False the spread is 0 (a static tile), except on the pixels
    :func:`noise_level` samples (:func:`noise_step`), so the noise level stays the same."""
    packed, geo, lo, hi = borrow(src)
    store, bases = borrow(kept)
    spans, spread, isi, rates, active = borrow((spans, spread, isi, rates, active))
    n, c, radius, m = at
    h, w = spread.shape
    every = active.shape[0] == 0
    grid = noise_step(h * w)
    a = max(0, c - m)
    b = min(n, c + m + 1)
    k_spans = spans.shape[0]
    for y in range(h):
        loc_own = np.empty(2 * radius + 2, np.int64)
        words_own, base, step = row_or_stored(packed, geo, lo, hi, y, w, store, bases)
        loc, words = borrow((loc_own, words_own))
        sampled = y % grid == 0
        for x in range(w):
            r = base + step * x
            if every or active[y, x] or (sampled and x % grid == 0):
                sp, iv = interval_stats(words, r, lo, c, radius, a, b, loc)
            else:
                sp, iv = 0.0, isi_in_words(words, r, lo, c, a, b)
            isi[y, x] = iv
            spread[y, x] = np.float32(sp)
            for j in range(k_spans):
                sa = spans[j, 0]
                sb = spans[j, 1]
                cnt = count_between(words, r, lo, sa, sb)
                if cnt >= 2:
                    first = next_spike(words, r, lo, sa, sb)
                    last = prev_spike(words, r, lo, sb - 1, sa)
                    rates[j, y, x] = np.float32(span_rate(cnt, first, last, sb - sa))
                else:
                    rates[j, y, x] = np.float32(1.0 / iv)
        keep((loc_own, words_own))


@njit
def noise_step(size):  # pragma: no cover - numba
    """Every how many rows and columns :func:`noise_level` samples a frame of ``size``
    pixels: 2 above 4 x 4096 (the median of a quarter of a camera frame is as good, at a
    quarter of the cost), else 1."""
    return 2 if size > 4 * 4096 else 1


#: Stored words of a whole window (CFSR's history scan): ``(store, bases, lo, hi)``.
StoredWords = tuple


def steady_range(n: int, center: int, max_isi: int) -> tuple[int, int]:
    """Steps ``[lo, hi)`` whose words :func:`steadiness` reads: the TFI's search range at t
    (the compared intervals must lie in it too; ``radius`` is clipped to it)."""
    return max(0, center - max_isi), min(n, center + max_isi + 1)


def steadiness(
    src: PackedWindow,
    center: int,
    *,
    radius: int,
    max_isi: int,
    spans: tuple[tuple[int, int], ...] = (),
    words: StoredWords | None = None,
    active: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the interval spread around ``center``, the TFI interval at it, and the
    ``isi`` span rates of ``spans``, from one read of each pixel's spike words.

    Parameters
    ----------
    src : PackedWindow
        The window (packed frames or :meth:`PackedWindow.from_frames`).
    center : int
        Index of t in the window.
    radius : int
        Steps each side of t whose intervals are compared (clipped to ``max_isi``).
    max_isi : int
        Steps searched each side of t for spikes (Eq. 3's range), for the TFI at t and the
        compared intervals alike.
    spans : tuple of (a, b)
        Steps ``[a, b)`` of span rules to compute with the same words (the static region's
        span, CSR's dynamic span); each must lie within :func:`steady_range` or the words.
    words : (store, bases, lo, hi), optional
        Words already gathered for the whole frame (CFSR's history scan), covering
        :func:`steady_range`; None gathers them here.
    active : ndarray (H, W) bool, optional
        Pixels whose spread is computed (None: all); elsewhere it is 0 (static tiles, see
        :func:`cfsr.methods.cfsr.static_gate.active_tiles`), except on :func:`noise_level`'s sample.

    Returns
    -------
    spread : ndarray (H, W) float32
        :func:`interval_stats` (relative, unitless; <= 0 for a steady pixel).
    isi : ndarray (H, W) int32
        The TFI interval at ``center`` in steps (``1 / isi`` is :func:`tfi_rate`'s value).
    rates : ndarray (len(spans), H, W) float32
        Span rates in spikes per step (:func:`cfsr.methods.tfp.static_rate`, ``isi``).
    """
    n = src.n
    c, radius, m = int(center), int(radius), int(max_isi)
    if words is None:
        lo, hi = steady_range(n, c, m)
        for a, b in spans:
            lo, hi = min(lo, int(a)), max(hi, int(b))
        store = np.empty((0, 0, 0), np.uint64)
        bases = np.empty((0, 2), np.int64)
    else:
        store, bases, lo, hi = words
        want = steady_range(n, c, m)
        if lo > want[0] or hi < want[1] or any(a < lo or b > hi for a, b in spans):
            raise ValueError(f"stored words [{lo}, {hi}) do not cover what steadiness reads")
    sp = np.asarray(spans, np.int64).reshape(-1, 2)
    spread = np.empty((src.h, src.w), np.float32)
    isi = np.empty((src.h, src.w), np.int32)
    rates = np.empty((sp.shape[0], src.h, src.w), np.float32)
    _steady_kernel(
        Words(src.packed, src.geo, int(lo), int(hi)), Stored(store, bases),
        _Around(n, c, radius, m), sp, spread, isi, rates,
        np.empty((0, 0), np.bool_) if active is None else np.ascontiguousarray(active, np.bool_),
    )
    return spread, isi, rates


def noise_level(spread: np.ndarray, *, clip: float = 3.0, rounds: int = 3) -> float:
    """The frame's temporal-noise level: the median interval spread (0 without noise).

    Clipped: the median is taken again over the pixels within ``clip`` times the last
    estimate (``rounds`` times), so strong movers do not raise it; where most of the frame
    moves it still errs high (the masks then err static).
    """
    s = np.asarray(spread, np.float32)
    if s.ndim == 2:  # every other row and column of a camera frame (noise_step)
        k = noise_step(s.size)
        s = s[::k, ::k]
    s = s.ravel()
    s = s[np.isfinite(s)]
    if np.count_nonzero(s <= 0) > s.size // 2:
        # the middle value (both middle values of an even count) <= 0: the median is, and the
        # level 0, without sorting (a noiseless frame: most steady pixels' spread is <= 0)
        return 0.0
    return clipped_median(s, float(np.median(s)) if s.size else 0.0, clip=clip, rounds=rounds)


def clipped_median(s: np.ndarray, v: float, *, clip: float, rounds: int) -> float:
    """:func:`noise_level`'s rounds from the first estimate ``v`` (the median of the finite
    values ``s``): the median again over the values within ``clip * v``, ``rounds`` times; 0
    once an estimate is <= 0."""
    for _ in range(rounds):
        if v <= 0:
            return 0.0
        v = float(np.median(s[s <= clip * v]))
    return max(0.0, v)


def steady_mask(
    spread: np.ndarray,
    *,
    tol: float,
    noise: float,
    noise_factor: float,
    close_size: int,
    min_area: int = 16,
) -> np.ndarray:
    """Coarse dynamic mask: ``spread > max(tol, noise_factor * noise)``, regularised.

    ``tol`` and ``noise`` are relative interval spreads (see :func:`interval_stats`,
    :func:`noise_level`); ``close_size`` pixels (<= 1: the per-pixel test alone).
    """
    # deferred: a cycle (fine_mask -> settings -> coarse -> this module)
    from cfsr.methods.cfsr.fine_mask import regularise

    raw = spread > np.float32(max(tol, noise_factor * noise))
    return regularise(raw, close_size=close_size, min_area=min_area)


@njit
def _check_kernel(static, isi, match, out):  # pragma: no cover - numba
    h, w = static.shape
    for y in range(h):
        for x in range(w):
            r = static[y, x]
            v = isi[y, x]
            # 1e-6 * v: r is float32, so 1/r of a rate whose interval is exactly one step from
            # v's can land a rounding error past the bound (36 and 37 steps at 1/36.5)
            if r > 0 and abs(v - 1.0 / r) <= 1.0 + match / r + 1e-6 * v:
                out[y, x] = r
            else:
                out[y, x] = np.float32(1.0 / v)
    return out


def check_static(static: np.ndarray, isi: np.ndarray, *, match: float) -> np.ndarray:
    """The static estimate where t's interval agrees with it, the TFI at t elsewhere.

    ``static``: spikes per step; ``isi``: the TFI interval at t in steps (>= 1); kept where
    ``|isi - 1/static| <= 1 + match / static`` (relative tolerance ``match``). Returns
    float32 spikes per step in (0, 1].
    """
    static = np.ascontiguousarray(static, np.float32)
    isi = np.ascontiguousarray(isi, np.int32)
    if static.shape != isi.shape:
        raise ValueError(f"static {static.shape} and isi {isi.shape} differ")
    return _check_kernel(static, isi, float(match), np.empty_like(static))
