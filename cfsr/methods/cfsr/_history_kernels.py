"""CFSR's compiled whole-frame scans (numba, cached): the private sibling of
:mod:`cfsr.methods.cfsr.history`, which orchestrates them (argument groups as NamedTuples,
buffers, the second pass's need).

Every per-pixel quantity of the pipeline is a function of the pixel's spike times: the scans
here read the packed window once per pixel as spike words (:mod:`cfsr._words`) and compute the
numbers of the stand-alone kernels (tests/test_methods_adaptive.py checks equality).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cfsr._borrow import borrow, keep
from cfsr._isi import search_range
from cfsr._jit import njit
from cfsr._words import (
    ROW_PAD,
    count_between,
    count_range,
    isi_in_words,
    n_words,
    next_spike,
    prefix_counts,
    prev_spike,
    row_or_stored,
    row_words,
)
from cfsr.methods.cfsr.daisi import daisi_words
from cfsr.methods.cfsr.distinction import distinct_in_words, long_isi_buffer
from cfsr.methods.tfp import span_rate

# --------------------------------------------------------------------------- fused scans
#
# Every per-pixel quantity of the pipeline is a function of the pixel's spike times. The
# stand-alone kernels (coarse distinction, TFI at many centers, TFP, DAISI, TFA) each gather
# those times again from the unpacked window, which costs more than the arithmetic; the
# scans below read the packed window once per pixel as spike words (:mod:`cfsr._words`:
# 64 steps per uint64, bit scans and popcounts instead of per-step loops) and compute, with
# the same rules and the same numbers as those kernels (tests/test_methods_adaptive.py
# checks equality):
#
# * :func:`static_kernel` (whole frame): proves pixels static in every history frame (one
#   walk of their spikes), the TFP counts of the history and at t, DAISI at t (its words rule,
#   :func:`cfsr.methods.cfsr.daisi.daisi_words`) -- all that a static window needs;
# * :func:`dynamic_kernel` (whole frame, only when some pixel is not proven static): TFI at
#   the K history steps and the coarse masks of the unproven pixels;
# * :mod:`cfsr.methods.cfsr.patchmatch_frames` (only the tiles PatchMatch can read): TFI and TFA at
#   the PatchMatch steps.


class HistUnion(NamedTuple):
    """The union ``[start, end)`` of the K distinction windows, their length ``span`` (T)
    and ``theta`` (Eq. 5-6)."""

    start: int
    end: int
    span: int
    theta: int


class Spans(NamedTuple):
    """The static-rate spans of the K history frames and of t: span j is ``[bounds[ia[j]],
    bounds[ib[j]])`` (shared edges counted once), ``isi_est[j]`` its rule, ``cents[j]`` the
    step whose TFI (``m`` steps each side) a sparse pixel takes."""

    bounds: np.ndarray  #: int64 (nb,): sorted distinct span edges
    ia: np.ndarray  #: int64 (K + 1,)
    ib: np.ndarray  #: int64 (K + 1,)
    isi_est: np.ndarray  #: bool (K + 1,)
    cents: np.ndarray  #: int64 (K + 1,)
    m: int


class Windows(NamedTuple):
    """The K history distinction windows of ``span`` (T) steps ending at ``ends``, ``theta``
    (Eq. 5-6), and the TFI search (``m`` steps each side of each end, Eq. 3)."""

    ends: np.ndarray  #: int64 (K,): sorted last steps of the windows
    span: int
    theta: int
    m: int


# a theta no distinct-ISI count reaches (T <= MAX_WINDOW_STEPS): the second pass then walks
# no coarse window and gives the TFI intervals alone (:func:`_tfi_at`)
NO_COARSE = 1 << 30


class Daisi(NamedTuple):
    """DAISI at ``c`` over ``c +- dspan`` (Eq. 10-14), spikes read in ``[read_start,
    read_end)``."""

    c: int
    dspan: int
    read_start: int
    read_end: int
    logs: np.ndarray  #: float64: :func:`cfsr.methods.cfsr.daisi.log_table`


@njit
def static_kernel(src, union, spans, dai, ub, tfp, daisi, kept, active):
    # pragma: no cover - numba
    """First pass of the history scan: what a static window needs, nothing more.

    Per pixel, on the words of ``src`` (:class:`~cfsr._words.Words`): ``ub``, the distinct
    ISIs of the union ``[union_start, union_end)`` of the K distinction windows (walk stopped at
    ``theta``): every window's ISI set is a subset, so ``ub < theta`` proves the pixel static
    in all K coarse masks;
    the TFP rates ``tfp[j]`` (Eq. 4: spikes in ``[bounds[ia[j]], bounds[ib[j]])`` over the
    window's length; the windows of the history frames and of t share edges, so each distinct
    edge is counted once), or where ``isi_est[j]`` the ``isi`` static rate over the same spans
    (:func:`cfsr.methods.tfp.span_rate`, first and last spike by two bit scans; the TFI at
    ``cents[j]``, ``m`` steps each side, below two spikes); DAISI at t. The words stay in
    ``kept`` (:class:`~cfsr._words.Stored`) for the second pass. Where ``active`` (bool ``(H,
    W)``, or empty: every pixel) is False -- a tile the static gate passes -- only the last two
    spans (the MOG frame at t and the static span at t) are computed, every history frame
    takes the first of them, and ``ub`` and DAISI are 0.
    """
    packed, geo, lo, hi = src
    union_start, union_end, span, theta = union
    bounds, ia, ib, isi_est, cents, m = spans
    c, dspan, daisi_start, daisi_end, logs = dai
    store, bases = kept
    h, w = ub.shape
    every = active.shape[0] == 0
    n_all = packed.shape[0]
    n_win = ia.shape[0]
    nb = bounds.shape[0]
    lens = np.empty(n_win, np.float64)
    for j in range(n_win):
        lens[j] = max(1, bounds[ib[j]] - bounds[ia[j]])
    nw = n_words(lo, hi)
    for y in range(h):
        words = store[y]
        big = long_isi_buffer(lo, hi)
        loc = np.empty(2 * dspan + 8, np.int64)
        prefix = np.empty(nw + 1, np.int64)
        before = np.empty(nb, np.int64)
        base, step = row_words(packed, geo, lo, hi, y, 0, w, words)
        bases[y, 0] = base
        bases[y, 1] = step
        for x in range(w):
            r = base + step * x
            prefix_counts(words, r, nw, prefix)
            j0 = 0
            if every or active[y, x]:
                ub[y, x] = distinct_in_words(words, r, nw, lo, union_start, union_end,
                                             span, big, theta)
                daisi[y, x] = daisi_words(words, r, lo, c, dspan, daisi_start, daisi_end,
                                          loc, logs)
                for i in range(nb):
                    before[i] = count_range(words, r, lo, prefix, lo, bounds[i])
            else:  # a static tile: the spans at t alone
                ub[y, x] = 0
                daisi[y, x] = 0.0
                j0 = max(0, n_win - 2)
                for j in range(j0, n_win):
                    before[ia[j]] = count_range(words, r, lo, prefix, lo, bounds[ia[j]])
                    before[ib[j]] = count_range(words, r, lo, prefix, lo, bounds[ib[j]])
            for j in range(j0, n_win):
                cnt = before[ib[j]] - before[ia[j]]
                if isi_est[j] and cnt >= 2:
                    sa = bounds[ia[j]]
                    sb = bounds[ib[j]]
                    first = next_spike(words, r, lo, sa, sb)
                    last = prev_spike(words, r, lo, sb - 1, sa)
                    tfp[j, y, x] = np.float32(span_rate(cnt, first, last, sb - sa))
                elif isi_est[j]:  # fewer than two spikes in the span: the TFI at its step
                    e = cents[j]
                    e_lo, e_hi = search_range(e, m, n_all)
                    iv = isi_in_words(words, r, lo, e, e_lo, e_hi)
                    tfp[j, y, x] = np.float32(1.0 / iv)
                else:
                    tfp[j, y, x] = np.float32(cnt / lens[j])
            for j in range(j0):  # a static tile's history: its MOG frame at t
                tfp[j, y, x] = tfp[j0, y, x]


@njit(hot=True)
def dynamic_kernel(src, wins, kept, ub, counts, isi, active):  # pragma: no cover - numba
    """Second pass, run only when some pixel was not proven static: the TFI interval at
    every history step (the ATSR scale of Eq. 7 needs it on the static region too) and,
    where ``ub >= theta``, each history window's distinct-ISI count (Eq. 5) by a walk that
    stops at ``theta`` (only ``count >= theta``, the coarse mask, is used: a moving pixel
    reaches it within a few words); elsewhere ``counts`` is ``ub``, below ``theta`` like
    every window's own count. ``src`` (:class:`~cfsr._words.Words`) gives the steps, ``wins``
    (:class:`Windows`) the windows. Reads the first pass's words (``kept``,
    :class:`~cfsr._words.Stored`) when it holds one row per image row; otherwise gathers them.
    Where ``active`` (bool ``(H, W)``, or empty: every pixel) is False, only the TFI interval at
    the last step (t) is computed (``ub`` is 0 there)."""
    packed, geo, lo, hi = borrow(src)
    ends, span, theta, m = borrow(wins)
    store, bases = borrow(kept)
    ub, counts, isi, active = borrow((ub, counts, isi, active))
    n = packed.shape[0]
    h, w = ub.shape
    k_count = ends.shape[0]
    every = active.shape[0] == 0
    nw = n_words(lo, hi)
    for y in range(h):
        big_own = long_isi_buffer(lo, hi)
        words_own, base, step = row_or_stored(packed, geo, lo, hi, y, w, store, bases)
        big, words = borrow((big_own, words_own))
        for x in range(w):
            r = base + step * x
            k_first = 0 if every or active[y, x] else k_count - 1
            for k in range(k_first, k_count):
                e = ends[k]
                e_lo, e_hi = search_range(e, m, n)
                isi[k, y, x] = isi_in_words(words, r, lo, e, e_lo, e_hi)
            if ub[y, x] < theta:
                for k in range(k_count):
                    counts[k, y, x] = ub[y, x]
                continue
            for k in range(k_count):
                e = ends[k]
                counts[k, y, x] = distinct_in_words(
                    words, r, nw, lo, max(0, e - span + 1), e + 1, span, big, theta
                )
        keep((big_own, words_own))



@njit
def crop_counts(packed, geo, lo, hi, starts, length, y0, x0, xa, xb, out):
    # pragma: no cover - numba
    """``out[k, i, x - x0]``: spikes of image pixel ``(y0 + i, x)``, ``xa[i] <= x <
    xb[i]`` (a row with ``xa[i] >= xb[i]`` is skipped), in steps ``[starts[k], starts[k] +
    length)`` (all inside ``[lo, hi)``), from the packed frames: those pixels' words
    (:func:`cfsr._words.row_words`, one transpose per 64 steps x 64 pixels) and masked
    popcounts (:func:`cfsr._words.count_between`). Other entries are left as they are."""
    k_count, hh, ww = out.shape
    nw = (hi - lo + 63) >> 6
    for i in range(hh):
        a_x = xa[i]
        b_x = xb[i]
        if a_x >= b_x:
            continue
        words = np.empty((b_x - a_x + ROW_PAD, nw), np.uint64)
        base, step = row_words(packed, geo, lo, hi, y0 + i, a_x, b_x, words)
        for x in range(a_x, b_x):
            r = base + step * (x - a_x)
            for k in range(k_count):
                a = starts[k]
                out[k, i, x - x0] = count_between(words, r, lo, a, a + length)
    return out
