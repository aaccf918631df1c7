"""The coarse stage's whole-frame scan (CFSR paper Eq. 3-6, with DAISI's Eq. 10-14 at t): the
CSR history frames that MOG learns, the coarse mask, TFI, TFP and DAISI at t, from one walk of
every pixel's spike words.

Every per-pixel quantity of the coarse stage is a function of the pixel's spike times, so the
scan reads them once per pixel straight from the packed frames (:mod:`cfsr._words`) and
computes them together, with the same numbers as the stand-alone rules
(:func:`cfsr.methods.cfsr.coarse.csr_frames`, :func:`cfsr.methods.cfsr.daisi.daisi_strength`,
:func:`cfsr.methods.tfi.tfi_rate`, :func:`cfsr.methods.tfp.tfp_rate`). DAISI is a fine-stage cue
(:mod:`cfsr.methods.cfsr.daisi`), read here because it reads the same spikes. The compiled scans
are in :mod:`cfsr.methods.cfsr._history_kernels`.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from cfsr._isi import search_range
from cfsr._words import ROW_PAD, PackedWindow, Stored, Words, n_words
from cfsr.methods.cfsr._history_kernels import (
    NO_COARSE,
    Daisi,
    HistUnion,
    Spans,
    Windows,
    dynamic_kernel,
    static_kernel,
)
from cfsr.methods.cfsr.atsr import atsr_fuse_isi
from cfsr.methods.cfsr.coarse import span_estimator, static_length, uses_steady
from cfsr.methods.cfsr.daisi import log_table
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.cfsr.steady_distinction import steady_range
from cfsr.methods.tfp import RateRule, TfpMode, tfp_span

__all__ = ["History", "history_scan", "tfi_at"]


_SCRATCH = threading.local()


def _scratch(shape: tuple[int, ...]) -> np.ndarray:
    """The history scan's word store, kept per thread between calls: a fresh 13 MB array
    costs its page faults on every frame (several ms, more than the transposes it saves)."""
    buf = getattr(_SCRATCH, "words", None)
    if buf is None or buf.shape != shape:
        buf = _SCRATCH.words = np.empty(shape, np.uint64)
    return buf


class History(NamedTuple):
    """The whole-frame scan's results (:func:`history_scan`); rates in spikes per step."""

    words: tuple[np.ndarray, np.ndarray, int, int]  #: stored words ``(store, bases, lo, hi)``
    rates: np.ndarray  #: float32 (K, H, W): the CSR history, oldest first
    ends: np.ndarray  #: int64 (K,): the history frames' last steps as used (carried ones too)
    coarse: np.ndarray  #: bool (H, W): the coarse mask at t (Eq. 5-6)
    tfi: np.ndarray | None  #: float32 (H, W): TFI at t when the scan had it (None: not yet)
    tfp: np.ndarray  #: float32 (H, W): the static estimate at t (Eq. 4 or isi)
    daisi: np.ndarray  #: float32 (H, W): DAISI at t (Eq. 10-14)


class _Reach(NamedTuple):
    """What the history scan reads, in window steps; spans are ``[start, end)``."""

    ends: np.ndarray  #: int64 (K,): the scanned history frames' last steps
    tfp_starts: np.ndarray  #: int64 (K,): the history frames' TFP spans
    tfp_ends: np.ndarray
    static_start: int  #: the static estimate's span at t
    static_end: int
    daisi_start: int  #: DAISI's range around t
    daisi_end: int
    union_start: int  #: the union of the history frames' distinction windows (Eq. 5)
    union_end: int
    words_start: int  #: the spike words read, covering all of the above
    words_end: int


def _reach(src: PackedWindow, center: int, ends: np.ndarray, s: CfsrSettings) -> _Reach:
    """:class:`_Reach` of the scan of the history frames ending at ``ends``."""
    n = src.n
    span, m, dspan = s.T, s.max_isi, s.daisi_span
    spans = [tfp_span(int(e), n, s.mog_window, s.tfp_mode) for e in ends]
    tfp_starts = np.array([a for a, _ in spans], np.int64)
    tfp_ends = np.array([b for _, b in spans], np.int64)
    static_start, static_end = tfp_span(center, n, static_length(s), s.tfp_mode)
    daisi_start, daisi_end = max(0, center - dspan - m), min(n, center + dspan + m + 1)
    union_start, union_end = max(0, int(ends[0]) - span + 1), int(ends[-1]) + 1
    # the words cover both passes (the second reads TFI intervals up to max_isi around ends)
    first, last = int(ends[0]), int(ends[-1])
    lo = max(0, min(union_start, int(tfp_starts.min()), static_start, daisi_start, first - m))
    hi = min(n, max(union_end, int(tfp_ends.max()), static_end, daisi_end, last + m + 1))
    if uses_steady(s.coarse) or s.two_sided:  # the steady rules read the same words
        s_lo, s_hi = steady_range(n, center, m)
        lo, hi = min(lo, s_lo), max(hi, s_hi)
        if s.two_sided:  # and the sharp rate at t
            s_lo, s_hi = tfp_span(center, n, s.mog_span, TfpMode.CENTRED)
            lo, hi = max(0, min(lo, s_lo)), min(n, max(hi, s_hi))
    return _Reach(
        ends,
        tfp_starts,
        tfp_ends,
        static_start,
        static_end,
        daisi_start,
        daisi_end,
        union_start,
        union_end,
        lo,
        hi,
    )


def history_scan(
    src: PackedWindow,
    center: int,
    s: CfsrSettings,
    active: np.ndarray | None = None,
    carried: Mapping[int, np.ndarray] | None = None,
) -> History:
    """The whole-frame scan: the CSR history of MOG, DAISI at t, TFI and TFP at t.

    The same numbers as ``csr_frames`` (history frames' static TFP over ``mog_window`` steps),
    ``daisi_strength``, ``tfi_rate`` and ``tfp_rate`` on the window. A first pass proves the
    static pixels static and gathers what a static window needs; the second (TFI at every
    history step, coarse masks) runs only when some pixel is not proven static.

    Outside ``active`` (bool ``(H, W)``; None: every pixel), tiles the static gate passes
    (:func:`cfsr.methods.cfsr.static_gate.active_tiles`), a pixel is static without a proof: its
    history frames are its MOG frame at t, its DAISI is 0, and the ATSR scale of each history
    frame before t is summed over the active pixels' static region (the frame at t's over the
    whole static region, as without tiles: its rates set MOG's gain).

    ``carried`` (window index of a frame's last step -> a CSR history frame of an earlier
    output, :func:`_carried_ends`) stands in for the history frames within half a stride of
    their ends; only the others, and the frame at t, are scanned. ``ends`` gives the
    history's ends as used.
    """
    h, w = src.h, src.w
    ks = range(s.mog_frames - 1, -1, -1)
    ends = np.array(
        [center - k * s.mog_stride for k in ks if center - k * s.mog_stride >= 0], np.int64
    )
    all_ends, reused = ends, dict[int, np.ndarray]()
    if carried:
        all_ends, reused = _carried_ends(ends, carried, s.mog_stride)
        ends = np.array([e for e in all_ends if e not in reused], np.int64)
    r = _reach(src, center, ends, s)
    theta, m = s.theta, s.max_isi
    k = ends.size
    # the K history TFP windows and the one at t, as indices into their sorted distinct edges
    wins = np.concatenate(
        [np.stack([r.tfp_starts, r.tfp_ends], 1), [[r.static_start, r.static_end]]]
    ).astype(np.int64)
    bounds, inv = np.unique(wins, return_inverse=True)
    inv = inv.reshape(wins.shape)
    # which windows take the isi rule: the history frames' (MOG's input) and the one at t
    isi_win = np.array(
        [s.mog_estimator == RateRule.ISI] * k + [span_estimator(s) == RateRule.ISI], np.bool_
    )
    # the kernels take an empty mask for "no tile gate": every pixel active
    act = np.empty((0, 0), np.bool_) if active is None else active
    ub = np.empty((h, w), np.int32)
    tfps = np.empty((k + 1, h, w), np.float32)
    daisi = np.empty((h, w), np.float32)
    store = _scratch((h, w + ROW_PAD, n_words(r.words_start, r.words_end)))
    bases = np.empty((h, 2), np.int64)
    static_kernel(
        Words(src.packed, src.geo, r.words_start, r.words_end),
        HistUnion(r.union_start, r.union_end, s.T, theta),
        Spans(
            bounds.astype(np.int64),
            np.ascontiguousarray(inv[:, 0]),
            np.ascontiguousarray(inv[:, 1]),
            isi_win,
            np.append(ends, center).astype(np.int64),
            m,
        ),
        Daisi(
            int(center),
            s.daisi_span,
            r.daisi_start,
            r.daisi_end,
            log_table(r.daisi_end - r.daisi_start),
        ),
        ub,
        tfps,
        daisi,
        Stored(store, bases),
        act,
    )
    words = (store, bases, r.words_start, r.words_end)
    if not (ub >= theta).any():  # every pixel proven static in every history frame
        rates, coarse = tfps[:k], np.zeros((h, w), bool)  # static rates, in [0, 1] already
        tfi = None
    else:
        rates, coarse, tfi = _second_pass(src, ends, words, ub, tfps[:k], act, active, s)
    rates = _with_carried(rates, ends, all_ends, reused, active)
    return History(words, rates, all_ends, coarse, tfi, tfps[k], daisi)


def _second_pass(
    src: PackedWindow,
    ends: np.ndarray,
    words: tuple[np.ndarray, np.ndarray, int, int],
    ub: np.ndarray,
    tfps: np.ndarray,
    act: np.ndarray,
    active: np.ndarray | None,
    s: CfsrSettings,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The history scan's second pass, when some pixel is not proven static: TFI at every
    history end (Eq. 3) and the coarse masks (Eq. 5-6) from the stored words; returns the
    CSR history (TFI where a frame has dynamic pixels, its TFP ``tfps`` elsewhere, as
    ``csr_frames``), the coarse mask at t and the TFI at t (spikes per step)."""
    store, bases, lo, hi = words
    k, h, w = tfps.shape
    theta = s.theta
    counts = np.empty((k, h, w), np.int32)
    isi = np.empty((k, h, w), np.int32)
    dynamic_kernel(
        Words(src.packed, src.geo, lo, hi),
        Windows(ends, s.T, theta, s.max_isi),
        Stored(store, bases),
        ub,
        counts,
        isi,
        act,
    )
    masks = counts >= theta
    rates = atsr_fuse_isi(isi, tfps, masks, counted=active)
    if active is not None:  # static tiles: their (exact) MOG frame at t throughout
        np.copyto(rates[:-1], rates[-1], where=~active)
    return rates, masks[-1], (1.0 / isi[-1]).astype(np.float32)


def _carried_ends(
    ends: np.ndarray, carried: Mapping[int, np.ndarray], stride: int
) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The history's ends with carried frames in place: each end before t (``ends[:-1]``)
    takes the unused carried frame whose end is nearest to it, within ``stride // 2`` steps
    (ties: the earlier one); ``(ends as used, {end: carried frame})``. The frame at t is never
    carried (its coarse mask, TFI and TFP at t come from the same scan)."""
    out = ends.copy()
    reused: dict[int, np.ndarray] = {}
    have = sorted(c for c in carried if 0 <= c < int(ends[-1]))
    for i, e in enumerate(ends[:-1].tolist()):
        near = [c for c in have if abs(c - e) <= stride // 2 and c not in reused]
        if near:
            c = min(near, key=lambda c: (abs(c - e), c))
            reused[c] = carried[c]
            out[i] = c
    return out, reused


def _with_carried(
    rates: np.ndarray,
    ends: np.ndarray,
    all_ends: np.ndarray,
    reused: Mapping[int, np.ndarray],
    active: np.ndarray | None,
) -> np.ndarray:
    """The history frames at ``all_ends``: the scanned ``rates`` (one per ``ends``) and the
    ``reused`` ones, oldest first. Outside ``active`` a carried frame takes the frame at t, as
    a scanned one does there (:func:`history_scan`)."""
    if not reused:
        return rates
    at = {int(e): i for i, e in enumerate(ends.tolist())}
    out = np.stack([reused[e] if e in reused else rates[at[e]] for e in all_ends.tolist()])
    if active is not None:
        np.copyto(out[:-1], out[-1], where=~active)
    return out


def tfi_at(src: PackedWindow, center: int, m: int) -> np.ndarray:
    """TFI rate (Eq. 3) at ``center`` on the whole frame, from the packed window."""
    n = src.n
    a, b = search_range(center, m, n)
    isi = np.empty((1, src.h, src.w), np.int32)
    dynamic_kernel(
        Words(src.packed, src.geo, a, b),
        Windows(np.array([center], np.int64), 1, NO_COARSE, m),
        Stored(np.empty((0, 0, 0), np.uint64), np.empty((0, 2), np.int64)),  # gather words
        np.zeros((src.h, src.w), np.int32),
        np.empty_like(isi),
        isi,
        np.empty((0, 0), np.bool_),
    )
    return (1.0 / isi[0]).astype(np.float32)
