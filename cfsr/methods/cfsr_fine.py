"""CFSR: coarse-to-fine reconstruction (CFSR paper Eq. 3-14), registered as ``cfsr``.

Pipeline for output step t (every stage a pure function of the spike window; the readings and
the calibration of every default are in docs/methods.md):

1. **CSR history** (:mod:`cfsr.methods.csr`): CSR frames at ``t - k * mog_stride`` for
   ``k = mog_frames - 1 .. 0`` (oldest first, the last one is t), their static region a TFP of
   ``mog_window`` steps (the paper's CSR, Eq. 5-7). The ``coarse`` output is the coarse mask
   at t: the steady-interval mask (:mod:`cfsr.methods.steady`, default) or Eq. 6's
   (``distinction = isi_set``); with ``static_estimator = steady`` the static estimate at t
   is kept only where t's own interval agrees with it (the TFI elsewhere).
2. **MOG** (:mod:`cfsr.methods.mog`, Eq. 8-9): a fresh ``bgsegm`` MOG model learns the history
   on the 8-bit scale (``mog_gain``: rate shown as 255, 0 = the 99.5th percentile of the CSR
   frame at t), gives the background B, and ``|f_t - B| >= phi0`` marks moving objects (phi0
   kept at least two count quanta of the MOG frames, so dark scenes do not mark noise).
   ``mog_sides = past`` is the paper's test (f: the MOG frame at t, a ``mog_window``-step
   TFP). ``both`` (default): f is the span rule over ``mog_span`` centred steps (the MOG
   frame where t's interval is longer than that span), and an object must also lie further
   than ``mog_match * phi0`` from the background of the **mirrored history** (TFP frames
   after t, fed to a second MOG farthest first): a *ghost*, background a mover uncovered
   within the history, matches it and leaves the fine mask (it stays in PatchMatch's region).
3. **DAISI** (:mod:`cfsr.methods.daisi`, Eq. 10-14): adjacent-ISI log ratios ``>= phi`` within
   ``daisi_span`` steps of t mark the edges of moving objects.
4. **Fine mask**: the union of the coarse mask, the MOG objects and the DAISI edges, closed with
   a ``close_size`` square, holes filled, components under ``min_area`` pixels dropped, grown
   by ``dilate`` pixels ("the edges refine the object mask"). Then the **still pixels** among
   it (:mod:`cfsr.methods.still`, ``still_reach`` > 0): pixels whose spikes hold one exact
   rate around t and either kept it to an end of ``t +- still_reach`` or come back to it
   after a change. They leave the mask (before and after the closing; holes a mover encloses
   are filled again) and the dilation does not grow into them; this is the ``fine`` output.
   PatchMatch still works on the mask before this step, and the still pixels left out take
   their run's rate.
5. **Fine reconstruction** (:mod:`cfsr.methods.patchmatch`): TFI at t and at ``t +- pm_step*i``,
   ``i = 1..pm_count``, and ``pm_far_count`` more ``pm_far_step`` apart (clipped to the
   window), computed only on the 8 x 8 tiles within reach
   of a fine-mask pixel's own patch and one tile more (the rest hold NaN: never matched);
   PatchMatch on a guide (TFA over ``pm_guide`` intervals, Gaussian ``pm_sigma``) matches the
   6 x 6 patch of every fine-mask pixel in each frame, and the raw TFI rates at the matches
   are averaged with the reference.
6. **ATSR** (:mod:`cfsr.methods.atsr`, Eq. 7): the refined dynamic region is fused with the
   static TFP (``tfp_window``) scaled by mean TFI / mean TFP over the static region.

"Skip what the scene does not need" (``adaptive``, default True): a window whose spike counts did
not change over the last two ``static_window`` spans (:mod:`cfsr.methods.staticgate`) is output
as the TFP at once, with empty masks; otherwise the same test per ``static_tile`` tile leaves
the tiles that pass it, with their neighbours, static without the proofs below (no
distinct-ISI walk, DAISI or interval spread there; their MOG history is their frame at t);
the history scan proves most
pixels static in one walk of their spikes, and runs its second pass (TFI at every history step,
coarse masks) only when some pixel is not proven static; an empty fine mask skips the TFI frames
and PatchMatch entirely (the output is then the plain TFP); MOG runs only where the 8-bit
history varies by phi0 or more; tiles without a fine-mask pixel within its patch's reach get no
TFI frames and no guides, and PatchMatch works only on the fine mask's pixels.
``adaptive=False`` is the always-full pipeline (every stage on the whole frame, same output
rule) that the benchmark compares with.

Speed: every per-pixel quantity above is a function of the pixel's spike times, so fused scans
read them once per pixel straight from the packed frames as spike words (:mod:`cfsr._words`;
``compute_packed``, no unpacking) and compute, with the same numbers as the stand-alone
kernels: the whole-frame history scan (steps 1 and 3, the TFP and TFI at t) and the
PatchMatch-region scan (step 5).

Layout: this module is the pipeline (:func:`fine_stage` and its stages, each returning a named
tuple); the parameter table, presets, quality tiers and the typed settings every stage reads
(:class:`CfsrSettings`, built once per frame) are in :mod:`cfsr.methods._cfsr_params`, the
compiled whole-frame scans in :mod:`cfsr.methods._cfsr_kernels`.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Mapping, MutableMapping
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np

from cfsr._isi import search_range
from cfsr._words import ROW_PAD, PackedWindow, Stored, Words, n_words
from cfsr.methods._cfsr_kernels import (
    NO_COARSE,
    Daisi,
    HistUnion,
    Spans,
    Windows,
    crop_counts,
    dynamic_kernel,
    static_kernel,
)
from cfsr.methods._cfsr_params import (
    FINE_PARAMS,
    FINE_PRESETS,
    QUALITY_TIERS,
    CfsrSettings,
    effective_params,
    pm_offsets,
)
from cfsr.methods.atsr import atsr_fuse, atsr_fuse_isi
from cfsr.methods.csr import (
    CSR_PARAMS,
    csr_window,
    span_estimator,
    static_checked,
    static_length,
    steady_parts,
    uses_steady,
)
from cfsr.methods.daisi import log_table
from cfsr.methods.masks import fine_mask
from cfsr.methods.mog import mog_background, mog_objects, to_u8
from cfsr.methods.patchmatch import finish_padding, padded_guides, patchmatch_fuse
from cfsr.methods.pmframes import TILE, match_reach, pm_frames, pm_tiles
from cfsr.methods.registry import Method, Output, register
from cfsr.methods.slowmotion import slow_fuse, slow_reach
from cfsr.methods.staticgate import active_tiles, span_counts, span_isi_rate, static_gate
from cfsr.methods.steady import steady_range
from cfsr.methods.still import still_pixels
from cfsr.methods.tfp import tfp_extent, tfp_span

__all__ = [
    "FINE_PARAMS",
    "FINE_PRESETS",
    "QUALITY_TIERS",
    "CfsrSettings",
    "carry_groups",
    "cfsr_window",
    "effective_params",
    "fast_config",
    "fine_mask",
    "fine_stage",
    "pm_offsets",
]


def fast_config(cfg: Any) -> Any:
    """The ``fast`` tier of a CFSR :class:`~cfsr.config.MethodConfig` (its other parameters
    kept); a config of another method is returned as it is."""
    if cfg.method != "cfsr":
        return cfg
    return cfg.replace(params={"quality": "fast"})


def carry_groups(times: Iterable[int], p: Mapping[str, Any] | CfsrSettings) -> list[list[int]]:
    """Split output steps into the groups within which outputs carry work forward.

    The steps are sorted and deduplicated; a group ends where the next step lies in another
    span of ``carry_span`` steps (spans start at multiples of it, from step 0) or more than
    ``carry_gap`` steps after the previous one (``carry_span = 0``: every step alone). The
    groups depend only on the steps and these two parameters: the first output of a group is
    computed from nothing (as an isolated output) and the others continue from the one before
    them, so a group run in order with one memo gives the same frames in any process, and
    the frames do not depend on how the groups are shared between processes.
    """
    s = CfsrSettings.of(p)
    ts = sorted({int(t) for t in times})
    groups: list[list[int]] = []
    for t in ts:
        if groups and _continues(groups[-1][-1], t, s):
            groups[-1].append(t)
        else:
            groups.append([t])
    return groups


def _continues(prev: int, t: int, s: CfsrSettings) -> bool:
    """Whether output step ``t`` continues from ``prev`` (:func:`carry_groups`' rule)."""
    span = int(s.carry_span)
    return span > 0 and prev // span == t // span and 0 < t - prev <= int(s.carry_gap)


def cfsr_window(p: Mapping[str, Any] | CfsrSettings) -> tuple[int, int]:
    """Steps before/after t that one CFSR frame needs (under its tier's settings)."""
    s = CfsrSettings.of(p)
    cb, ca = csr_window(s.coarse)  # the static TFP at t
    # the MOG history's frames: TFP over mog_window steps
    hb, ha = csr_window(replace(s.coarse, tfp_window=s.mog_window, static_span=0))
    pm = s.pm_offsets[-1] if s.pm_offsets else 0  # the farthest PatchMatch frame
    reach = s.max_isi
    before = max(cb, hb + (s.mog_frames - 1) * s.mog_stride, pm + reach, s.daisi_span + reach)
    after = max(ca, ha, pm + reach, s.daisi_span + reach)
    if s.two_sided:  # the mirrored history after t and the sharp rate at t
        before = max(before, sharp_span(s)[0])
        after = max(after, future_reach(s), sharp_span(s)[1])
    if s.still_reach > 0:  # the still-pixel proof's range
        before = max(before, int(s.still_reach))
        after = max(after, int(s.still_reach))
    before, after = max(before, slow_reach(s)), max(after, slow_reach(s))  # slow-motion windows
    if s.adaptive and s.static_tol >= 0:  # the static gate's two spans end with the TFP's
        tfp_after = tfp_extent(static_length(s), s.tfp_mode)[1]
        before = max(before, 2 * s.static_window - tfp_after - 1)
    return before, after


def sharp_span(s: CfsrSettings) -> tuple[int, int]:
    """Steps before/after t that the sharp rate at t reads (``mog_span`` centred, the TFI's
    ``max_isi`` range for a pixel with fewer than two spikes in it)."""
    before, after = tfp_extent(int(s.mog_span), "centred")
    reach = int(s.max_isi)
    return max(before, reach), max(after, reach)


def future_reach(s: CfsrSettings) -> int:
    """Steps after t that the mirrored history reads: frames ``[t + k * s, t + k * s +
    mog_window)``, ``s = mog_future_stride``, ``k = 0 .. mog_future_frames - 1``."""
    k, stride = int(s.mog_future_frames), int(s.mog_future_stride)
    return (k - 1) * stride + int(s.mog_window) - 1


_SCRATCH = threading.local()


def _scratch(shape: tuple[int, ...]) -> np.ndarray:
    """The history scan's word store, kept per thread between calls: a fresh 13 MB array
    costs its page faults on every frame (several ms, more than the transposes it saves)."""
    buf = getattr(_SCRATCH, "words", None)
    if buf is None or buf.shape != shape:
        buf = _SCRATCH.words = np.empty(shape, np.uint64)
    return buf


class History(NamedTuple):
    """The whole-frame scan's results (:func:`_history`); rates in spikes per step."""

    words: tuple[np.ndarray, np.ndarray, int, int]  #: stored words ``(store, bases, lo, hi)``
    rates: np.ndarray  #: float32 (K, H, W): the CSR history, oldest first
    ends: np.ndarray  #: int64 (K,): the history frames' last steps as used (carried ones too)
    coarse: np.ndarray  #: bool (H, W): the coarse mask at t (Eq. 5-6)
    tfi: np.ndarray | None  #: float32 (H, W): TFI at t when the scan had it (None: not yet)
    tfp: np.ndarray  #: float32 (H, W): the static estimate at t (Eq. 4 or isi)
    daisi: np.ndarray  #: float32 (H, W): DAISI at t (Eq. 10-14)


class _Reach(NamedTuple):
    """What the history scan reads: the K history frames' ends and TFP spans, t's TFP span,
    DAISI's range, the distinction windows' union and the words' steps (all window steps)."""

    ends: np.ndarray  #: int64 (K,): the scanned frames' last steps
    ta: np.ndarray  #: int64 (K,): TFP span starts
    tb: np.ndarray  #: int64 (K,): TFP span ends
    pa: int
    pb: int
    d_lo: int
    d_hi: int
    u_lo: int
    u_hi: int
    lo: int
    hi: int


def _reach(src: PackedWindow, center: int, ends: np.ndarray, s: CfsrSettings) -> _Reach:
    """:class:`_Reach` of the scan of the history frames ending at ``ends``."""
    n = src.n
    span, m, dspan = int(s.T), int(s.max_isi), int(s.daisi_span)
    spans = [tfp_span(int(e), n, s.mog_window, s.tfp_mode) for e in ends]
    ta = np.array([a for a, _ in spans], np.int64)
    tb = np.array([b for _, b in spans], np.int64)
    pa, pb = tfp_span(center, n, static_length(s), s.tfp_mode)
    d_lo, d_hi = max(0, center - dspan - m), min(n, center + dspan + m + 1)
    u_lo, u_hi = max(0, int(ends[0]) - span + 1), int(ends[-1]) + 1
    # the words cover both passes (the second reads TFI intervals up to max_isi around ends)
    lo = max(0, min(u_lo, int(ta.min()), pa, d_lo, int(ends[0]) - m))
    hi = min(n, max(u_hi, int(tb.max()), pb, d_hi, int(ends[-1]) + m + 1))
    if uses_steady(s.coarse) or s.two_sided:  # the steady rules read the same words
        s_lo, s_hi = steady_range(n, center, m)
        lo, hi = min(lo, s_lo), max(hi, s_hi)
        if s.two_sided:  # and the sharp rate at t
            s_lo, s_hi = tfp_span(center, n, int(s.mog_span), "centred")
            lo, hi = max(0, min(lo, s_lo)), min(n, max(hi, s_hi))
    return _Reach(ends, ta, tb, pa, pb, d_lo, d_hi, u_lo, u_hi, lo, hi)


def _history(
    src: PackedWindow,
    center: int,
    p: Mapping[str, Any] | CfsrSettings,
    active: np.ndarray | None = None,
    carried: Mapping[int, np.ndarray] | None = None,
) -> History:
    """The whole-frame scan: the CSR history of MOG, DAISI at t, TFI and TFP at t.

    The same numbers as ``csr_frames`` (history frames' static TFP over ``mog_window`` steps),
    ``daisi_strength``, ``tfi_rate`` and ``tfp_rate`` on the window. A first pass proves the
    static pixels static and gathers what a static window needs; the second (TFI at every
    history step, coarse masks) runs only when some pixel is not proven static.

    Outside ``active`` (bool ``(H, W)``; None: every pixel), tiles the static gate passes
    (:func:`cfsr.methods.staticgate.active_tiles`), a pixel is static without a proof: its
    history frames are its MOG frame at t, its DAISI is 0, and the ATSR scale of each history
    frame before t is summed over the active pixels' static region (the frame at t's over the
    whole static region, as without tiles: its rates set MOG's gain).

    ``carried`` (window index of a frame's last step -> a CSR history frame of an earlier
    output, :func:`_carried_ends`) stands in for the history frames within half a stride of
    their ends; only the others, and the frame at t, are scanned. ``ends`` gives the
    history's ends as used.
    """
    s = CfsrSettings.of(p)
    h, w = src.h, src.w
    ks = range(s.mog_frames - 1, -1, -1)
    ends = np.array(
        [center - k * s.mog_stride for k in ks if center - k * s.mog_stride >= 0], np.int64
    )
    all_ends, reused = ends, dict[int, np.ndarray]()
    if carried:
        all_ends, reused = _carried_ends(ends, carried, int(s.mog_stride))
        ends = np.array([e for e in all_ends if e not in reused], np.int64)
    r = _reach(src, center, ends, s)
    theta, m = int(s.theta), int(s.max_isi)
    k = ends.size
    # the K history TFP windows and the one at t, as indices into their sorted distinct edges
    wins = np.concatenate([np.stack([r.ta, r.tb], 1), [[r.pa, r.pb]]]).astype(np.int64)
    bounds, inv = np.unique(wins, return_inverse=True)
    inv = inv.reshape(wins.shape)
    # which windows take the isi rule: the history frames' (MOG's input) and the one at t
    isi_win = np.array([s.mog_estimator == "isi"] * k + [span_estimator(s) == "isi"], np.bool_)
    # the kernels take an empty mask for "no tile gate": every pixel active
    act = np.empty((0, 0), np.bool_) if active is None else active
    ub = np.empty((h, w), np.int32)
    tfps = np.empty((k + 1, h, w), np.float32)
    daisi = np.empty((h, w), np.float32)
    store = _scratch((h, w + ROW_PAD, n_words(r.lo, r.hi)))
    bases = np.empty((h, 2), np.int64)
    static_kernel(
        Words(src.packed, src.geo, r.lo, r.hi),
        HistUnion(r.u_lo, r.u_hi, int(s.T), theta),
        Spans(
            bounds.astype(np.int64),
            np.ascontiguousarray(inv[:, 0]),
            np.ascontiguousarray(inv[:, 1]),
            isi_win,
            np.append(ends, center).astype(np.int64),
            m,
        ),
        Daisi(int(center), int(s.daisi_span), r.d_lo, r.d_hi, log_table(r.d_hi - r.d_lo)),
        ub,
        tfps,
        daisi,
        Stored(store, bases),
        act,
    )
    words = (store, bases, r.lo, r.hi)
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
    theta = int(s.theta)
    counts = np.empty((k, h, w), np.int32)
    isi = np.empty((k, h, w), np.int32)
    dynamic_kernel(
        Words(src.packed, src.geo, lo, hi),
        Windows(ends, int(s.T), theta, int(s.max_isi)),
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
    a scanned one does there (:func:`_history`)."""
    if not reused:
        return rates
    at = {int(e): i for i, e in enumerate(ends.tolist())}
    out = np.stack([reused[e] if e in reused else rates[at[e]] for e in all_ends.tolist()])
    if active is not None:
        np.copyto(out[:-1], out[-1], where=~active)
    return out


def _tfi_at(src: PackedWindow, center: int, m: int) -> np.ndarray:
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


class Coarse(NamedTuple):
    """Step 1, the coarse stage (:func:`_coarse_stage`); rates in spikes per step, (H, W)."""

    history: History  #: the whole-frame scan
    coarse: np.ndarray  #: bool: the coarse mask at t (steady rule or Eq. 5-6)
    tfp: np.ndarray  #: float32: the static estimate at t (steady-checked when asked)
    tfi: np.ndarray | None  #: float32: TFI at t when already read (None: not yet)
    sharp: _Sharp | None  #: Eq. 9's f under ``mog_sides = both`` (None: past)
    noise: float | None  #: the frame's temporal-noise level (None: not measured)


class Masks(NamedTuple):
    """Steps 2-4, the fine masks (:func:`_mask_stage`), bool (H, W) but ``tfp``."""

    coarse: np.ndarray  #: the ``coarse`` output
    fine: np.ndarray  #: the ``fine`` output (still pixels left out)
    region: np.ndarray  #: what PatchMatch reconstructs (the mask before the still pixels)
    left: np.ndarray | None  #: still pixels the fine mask leaves out (None: none)
    tfp: np.ndarray  #: float32: the static estimate, the still pixels' run rate there


class Refined(NamedTuple):
    """Steps 5-6, the fine reconstruction (:func:`_refine_stage`)."""

    rate: np.ndarray  #: float32 (H, W): spikes per step in [0, 1]
    used: np.ndarray | None  #: bool (H, W): where the refined rates were taken (None: none)


def fine_stage(
    window: np.ndarray | PackedWindow,
    center: int,
    seed: int,
    p: Mapping[str, Any] | CfsrSettings,
    memo: MutableMapping[str, Any] | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The whole CFSR pipeline on one window; returns ``(rate, {"coarse", "fine"})``.

    ``adaptive`` (default True) skips what the scene does not need: counts unchanged
    over the last two ``static_window`` spans (the static gate) or no fine-mask pixel ->
    the plain TFP; otherwise TFI frames and guides only on the tiles within a patch's reach
    of a fine-mask pixel (:func:`pm_tiles`) and PatchMatch only on the fine-mask pixels.
    ``adaptive=False`` is the always-full pipeline: MOG on the whole frame, TFI frames and
    guides on the whole frame, PatchMatch on the same region, then the same output rule (TFP
    where the fine mask is empty, ATSR with the fine mask otherwise), so the two differ only
    where a match would reach beyond the tiles the adaptive pipeline computes.

    ``p`` runs under its ``quality`` tier (:class:`CfsrSettings`, :func:`effective_params`).
    ``seed`` is the absolute step of t (PatchMatch's draws are keyed by it). ``memo`` (a dict
    kept for one stream) carries work from the previous output to this one when
    :func:`carry_groups`' rule joins them (the same span of ``carry_span`` steps, at most
    ``carry_gap`` after it): its CSR history frames stand in for this output's within half a
    stride (:func:`_carried_ends`), and the PatchMatch frames of the group's last output at
    the same steps are taken as computed (:func:`cfsr.methods.pmframes.pm_frames`' bank: the
    same numbers). Without it, or for the first output of a group, the frame is the isolated
    one.
    """
    s = CfsrSettings.of(p)
    src = window if isinstance(window, PackedWindow) else PackedWindow.from_frames(window)
    carried, bank = _carry_in(memo, int(seed), center, s)
    # 0. static gate: counts unchanged over the last two spans -> the TFP, nothing else to do
    pa, pb = tfp_span(center, src.n, static_length(s), s.tfp_mode)
    gate = static_gate(src, pb, s.static_window, s.static_tol) if s.adaptive else None
    if gate is not None:
        none = np.zeros((src.h, src.w), bool)
        _carry_out(memo, int(seed), center, s, None, bank)
        return _gated_rate(src, gate, pa, pb, center, s), {"coarse": none, "fine": none.copy()}
    active, slow_cand = _tile_gates(src, pb, s)
    # 1. CSR history (oldest first; frames before the window start dropped), DAISI, TFI, TFP
    co = _coarse_stage(src, center, s, active, carried)
    frames = dict(zip(co.history.ends.tolist(), co.history.rates, strict=True))
    _carry_out(memo, int(seed), center, s, frames, bank)
    # 2-4. MOG objects, DAISI edges, the fine mask and PatchMatch's region
    mk = _mask_stage(src, center, co, s)
    # 5-6. PatchMatch on the fine region, ATSR
    ref = _refine_stage(src, center, seed, co, mk, s, bank)
    # 7. windows as long as the motion allows where the pixel moves slowly (slowmotion)
    rate = slow_fuse(src, center, ref.rate, ref.used, s, slow_cand, co.noise)
    return rate, {"coarse": mk.coarse, "fine": mk.fine}


def _coarse_stage(
    src: PackedWindow,
    center: int,
    s: CfsrSettings,
    active: np.ndarray | None,
    carried: Mapping[int, np.ndarray] | None,
) -> Coarse:
    """Step 1: the history scan (:func:`_history`) and, when a steady rule or the two-sided
    test is on, the intervals around t: steady coarse mask, static check, sharp rate; read
    from the history scan's words, before anything else reuses its scratch store."""
    hs = _history(src, center, s, active, carried)
    if not (uses_steady(s.coarse) or s.two_sided):
        return Coarse(hs, hs.coarse, hs.tfp, hs.tfi, None, None)
    # CFSR has no dynamic estimator of its own: two-sided, the span rule at t is the sharp rate
    q = s.sharp if s.two_sided else s.coarse
    st = steady_parts(src, center, q, words=hs.words, static=False, active=active)
    sharp = _Sharp(st.dynamic, st.isi, hs.rates[-1], int(s.mog_span)) if s.two_sided else None
    return Coarse(
        hs,
        hs.coarse if st.mask is None else st.mask,
        static_checked(hs.tfp, st.isi, st.noise, s.coarse),
        (1.0 / st.isi).astype(np.float32),  # the same numbers as _tfi_at
        sharp,
        st.noise,
    )


def _mask_stage(src: PackedWindow, center: int, co: Coarse, s: CfsrSettings) -> Masks:
    """Steps 2-4: MOG objects (Eq. 8-9, ghosts told by the mirrored history), DAISI edges
    (Eq. 10-14), the fine mask, its still pixels (left out, with their run's rate) and
    PatchMatch's region."""
    objects, ghosts = _objects(src, center, co.history.rates, co.coarse, co.sharp, s)
    edges = co.history.daisi >= s.phi
    fine, region, left, tfp = _fine_region(
        src, center, co.coarse, objects, edges, ghosts, co.tfp, co.history.words, s
    )
    return Masks(co.coarse, fine, region, left, tfp)


def _refine_stage(
    src: PackedWindow,
    center: int,
    seed: int,
    co: Coarse,
    mk: Masks,
    s: CfsrSettings,
    bank: dict[str, Any] | None,
) -> Refined:
    """Steps 5-6: the TFI at t refined by PatchMatch on the fine region (adaptive: only on
    the tiles within a patch's reach of a fine-mask pixel), fused with the static estimate
    by ATSR (Eq. 7); the plain static estimate where the region is empty. The ATSR reads the
    refined rates on region & ~left only: the still pixels left out (and, always-full, the
    pixels outside the region) are matched but not averaged."""
    if s.adaptive and not mk.region.any():
        return Refined(np.clip(mk.tfp, 0.0, 1.0).astype(np.float32), None)
    used = mk.region if mk.left is None else mk.region & ~mk.left
    refined, (y0, x0), domain = _refine(src, center, seed, mk.region, used, s, bank)
    if not mk.region.any():  # always-full pipeline on a static window: the same TFP output
        return Refined(np.clip(mk.tfp, 0.0, 1.0).astype(np.float32), None)
    # TFI at t (computed here when the history did not need it)
    tfi_full = co.tfi if co.tfi is not None else _tfi_at(src, center, int(s.max_isi))
    dyn = tfi_full.copy()
    crop = dyn[y0 : y0 + domain.shape[0], x0 : x0 + domain.shape[1]]
    crop[domain] = refined[domain]
    rate, _ = atsr_fuse(dyn, mk.tfp, used, tfi=tfi_full)
    return Refined(rate, used)


def _gated_rate(
    src: PackedWindow, gate: np.ndarray, pa: int, pb: int, center: int, s: CfsrSettings
) -> np.ndarray:
    """The output of a window the static gate passes (``gate``: its counts over the last
    span): the static estimate over ``[pa, pb)``, spikes per step in [0, 1]. Such a window
    has no mover for the steady check to catch, so the isi rule applies as is."""
    if span_estimator(s) == "isi":  # below two spikes: the TFI at t
        tfp = span_isi_rate(src, pa, pb, center=center, max_isi=int(s.max_isi))
    else:
        counts = gate if pb - pa == s.static_window else span_counts(src, pa, pb)
        tfp = counts / np.float32(max(1, pb - pa))
    return np.clip(tfp, 0.0, 1.0).astype(np.float32)


def _tile_gates(
    src: PackedWindow, pb: int, s: CfsrSettings
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(active, slow_cand)``: the pixels of the tiles the static gate per tile does not
    pass (None: all), for the adaptive stages and for the slow-motion windows.

    The slow-motion windows look only where the gate per tile finds a change (its tiles are
    still: their rate is a long window's already) whatever ``adaptive`` and the gate
    settings, so that every pipeline gives a still window the same output."""
    tile, tol, adaptive = int(s.static_tile), int(s.static_tol), s.adaptive

    def tiles(tol: int, tile: int) -> np.ndarray | None:
        a = active_tiles(src, pb, s.static_window, tol, tile)
        return None if a is not None and a.all() else a

    active = tiles(tol, tile) if adaptive and tile > 0 else None
    if adaptive and tile > 0 and tol >= 0:
        return active, active
    return active, tiles(tol if tol >= 0 else 1, tile or 16)  # tol -1: the default's


def _objects(
    src: PackedWindow,
    center: int,
    rates: np.ndarray,
    coarse: np.ndarray,
    sharp: _Sharp | None,
    s: CfsrSettings,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Eq. 8-9 on the CSR history ``rates`` (oldest first): the moving objects, and the
    ghosts (None: not tested) that the mirrored history after t tells apart
    (``mog_sides = both``)."""
    gain = s.mog_gain
    if gain <= 0:
        gain = float(np.percentile(rates[-1], 99.5)) if rates[-1].size else 1.0
        if not np.isfinite(gain) or gain <= 0:
            gain = 1.0
    u8 = to_u8(rates, gain)
    # one spike more or less in the MOG frames' window moves the 8-bit value by `quantum`
    # levels; in dark scenes that exceeds phi0 and Eq. 9 would mark noise, so phi0 is kept
    # at least two quanta (no effect at ordinary brightness: 16 levels at rate_scale 0.5)
    quantum = 255.0 / (s.mog_window * gain)
    phi0 = max(s.phi0, 2.0 * quantum)
    hist = s.mog_history or s.mog_frames
    objects = _mog_objects(u8, phi0, s.adaptive, s, hist, sharp, gain)
    match = phi0 * float(s.mog_match)
    ghosts = None
    if sharp is not None and match > 0:  # a ghost matches the background after t
        # only objects outside the coarse mask can change the fine mask (the union is what
        # is regularised), so only they are tested
        cand = objects & ~coarse
        if cand.any():
            keep = _future_objects(src, center, cand, sharp, gain, match, s.adaptive, s, hist)
            ghosts = cand & ~keep
            objects = (objects & coarse) | keep
    return objects, ghosts


def _fine_region(
    src: PackedWindow,
    center: int,
    coarse: np.ndarray,
    objects: np.ndarray,
    edges: np.ndarray,
    ghosts: np.ndarray | None,
    tfp: np.ndarray,
    words: Any,
    s: CfsrSettings,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Step 4: ``(fine, region, left, tfp)``: the fine mask (the cues' union regularised,
    its still pixels left out), the region PatchMatch reconstructs (the mask before the still
    pixels, and the ghosts), the still pixels left out (None: none) and the static estimate
    with their run's rate there."""

    def cues(still: np.ndarray | None = None) -> np.ndarray:
        return fine_mask(
            coarse,
            objects,
            edges,
            close_size=s.close_size,
            min_area=s.min_area,
            dilate=s.dilate,
            still=still,
        )

    fine = cues()
    region = fine  # what PatchMatch reconstructs
    left = None  # still pixels the reported fine mask leaves out: their run's rate
    if int(s.still_reach) > 0 and fine.any():
        # the still pixels among the mask's: background at t, proven by their own spikes
        still, still_rate = still_pixels(
            src,
            center,
            fine,
            reach=int(s.still_reach),
            min_run=int(s.still_run),
            jump=float(s.still_jump),
            words=words,
        )
        if still.any():
            fine = cues(still)
            # the still pixels it leaves out take their run's rate (exact over 64-760
            # steps); PatchMatch keeps its region (what it matches there is unchanged:
            # a region without them cost the fan's moving pixels 3.7 % more squared error)
            left = still & ~fine
            tfp = np.where(left, still_rate, tfp)
    if ghosts is not None:
        # the ghosts are background and leave the fine mask, but stay in the region
        # PatchMatch reconstructs (at zero motion it averages 33 TFI frames there): left to
        # the static estimate, the car lost 1.1 dB (docs/methods.md, "Two-sided objects")
        region = region | ghosts
    return fine, region, left, tfp


def _refine(
    src: PackedWindow,
    center: int,
    seed: int,
    region: np.ndarray,
    used: np.ndarray,
    s: CfsrSettings,
    bank: dict[str, Any] | None = None,
) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """Step 5: the TFI at t refined by PatchMatch (Eq. 3 + the paper's patch averaging) on
    ``region`` (adaptive: TFI frames and guides only on the tiles within a patch's reach of
    it), averaged on ``used``. Returns ``(refined, (y0, x0), domain)``: the refined rates of
    the crop at ``(y0, x0)`` and the crop's pixels they hold. ``bank``: the PatchMatch frames
    carried within a group of outputs (:func:`cfsr.methods.pmframes.pm_frames`)."""
    h, w, n = src.h, src.w, src.n
    if s.adaptive:
        # a match reaching beyond the computed tiles reads NaN and is never taken (pm_frames);
        # one tile more than a pixel's own patch reads at zero motion leaves room for the
        # motion (with none, the blades' moving pixels lost 0.11 dB; docs/methods.md)
        reach = match_reach(int(s.pm_patch), float(s.pm_sigma)) + TILE
        tiles = pm_tiles(region, reach)
        ty, tx = np.nonzero(tiles)
        y0, y1 = ty.min() * TILE, min(h, (ty.max() + 1) * TILE)
        x0, x1 = tx.min() * TILE, min(w, (tx.max() + 1) * TILE)
        domain = region[y0:y1, x0:x1]
    else:
        # frames and guides on the whole frame, but PatchMatch on the region alone, as the
        # adaptive pipeline: the temporal schedule searches blocks of the matched pixels of a
        # row (their end pixels' predictions, their distinct bests, their neighbours'
        # offsets), so matching the pixels outside the region too changed the candidates of
        # the region's edge pixels, and with them the ghosts' rates outside the fine mask
        # (0.6 % at one pixel with pm_count 24 x pm_step 2); their matches were never used
        y0, y1, x0, x1 = 0, h, 0, w
        tiles = None
        domain = region
    # the reference t first, then t -+ each offset inside the window
    tcs = [center] + [c for d in s.pm_offsets for c in (center - d, center + d) if 0 <= c < n]
    # the guides go straight into the buffer the search reads (no padded copy of every frame)
    padded, view = padded_guides(len(tcs), int(y1 - y0), int(x1 - x0), int(s.pm_patch))
    raw, guides = pm_frames(
        src,
        tcs,
        (int(y0), int(y1), int(x0), int(x1)),
        s,
        tiles,
        guide_out=view,
        bank=bank,
        shift=seed - center,
    )
    finish_padding(padded, int(s.pm_patch))
    refined = patchmatch_fuse(
        raw[0],
        guides[0],
        raw[1:],
        guides[1:],
        domain,
        wanted=used[y0:y1, x0:x1],
        patch=s.pm_patch,
        iters=s.pm_iters,
        max_radius=s.pm_radius,
        h=s.pm_h,
        seed=seed,
        origin=(int(y0), int(x0)),
        # temporal schedule: each target starts from the motion predicted by the nearer ones
        offsets_steps=[c - center for c in tcs[1:]],
        padded=padded,
    )
    return refined, (int(y0), int(x0)), domain


class _Carry(NamedTuple):
    """What an output leaves in the memo for the next one (:func:`fine_stage`)."""

    t: int  #: absolute step of the output
    key: CfsrSettings  #: its settings but the carry rule's: another set carries nothing
    frames: dict[int, np.ndarray]  #: absolute last step -> CSR history frame (H, W) float32
    #: the PatchMatch frames of the group's last output that ran PatchMatch, by absolute
    #: step (:func:`cfsr.methods.pmframes.pm_frames`)
    bank: dict[str, Any]


def _carry_in(
    memo: MutableMapping[str, Any] | None, t: int, center: int, s: CfsrSettings
) -> tuple[dict[int, np.ndarray] | None, dict[str, Any] | None]:
    """The previous output's history frames (window indices -> frame; None: none) when output
    step ``t`` continues from it (:func:`_continues`), and the group's PatchMatch frames (an
    empty bank for the first output of a group; None without a memo or with
    ``carry_span = 0``)."""
    if memo is None or int(s.carry_span) <= 0:
        return None, None
    old = memo.get("cfsr")
    if not isinstance(old, _Carry) or not _continues(old.t, t, s) or old.key != s.carry_key:
        return None, {}
    shift = t - center  # absolute step of window index 0
    return {a - shift: f for a, f in old.frames.items()}, old.bank


def _carry_out(
    memo: MutableMapping[str, Any] | None,
    t: int,
    center: int,
    s: CfsrSettings,
    frames: Mapping[int, np.ndarray] | None,
    bank: dict[str, Any] | None = None,
) -> None:
    """Leave this output's history frames (window index -> frame; None: none) and the
    group's PatchMatch frames (``bank``, which :func:`_refine` fills in place) in ``memo``."""
    if memo is None or int(s.carry_span) <= 0:
        return
    shift = t - center
    kept = {} if frames is None else {e + shift: f for e, f in frames.items()}
    memo["cfsr"] = _Carry(t, s.carry_key, kept, {} if bank is None else bank)


class _Sharp(NamedTuple):
    """Eq. 9's f under ``mog_sides = both``: the span rule over ``span`` centred steps at t
    (``rate``), where t's interval (``isi``, steps) is shorter than the span; the MOG frame
    at t (``frame``) elsewhere, where the span holds fewer than two spikes (its TFI cost the
    dim scene's fine IoU 0.05). Rates in spikes per step, (H, W)."""

    rate: np.ndarray
    isi: np.ndarray
    frame: np.ndarray
    span: int

    def u8(self, box: tuple[int, int, int, int], gain: float) -> np.ndarray:
        """f on the crop ``box = (y0, y1, x0, x1)`` on MOG's 8-bit scale (:func:`to_u8`)."""
        y0, y1, x0, x1 = box
        r = np.where(
            self.isi[y0:y1, x0:x1] < self.span,
            self.rate[y0:y1, x0:x1],
            self.frame[y0:y1, x0:x1],
        )
        return to_u8(r, gain)


def _mog_settings(s: CfsrSettings, hist: int) -> dict[str, Any]:
    """:func:`cfsr.methods.mog.mog_background`'s keywords from the settings (both MOGs)."""
    return {
        "history": hist,
        "nmixtures": s.mog_mixtures,
        "background_ratio": s.mog_ratio,
        "noise_sigma": s.mog_noise,
    }


def _mog_objects(
    u8: np.ndarray,
    phi0: float,
    adaptive: bool,
    p: Mapping[str, Any] | CfsrSettings,
    hist: int,
    sharp: _Sharp | None = None,
    gain: float = 1.0,
):
    """Eq. 8-9 on the history ``u8`` (oldest first): ``|f - B| >= phi0`` with f the last
    history frame, or the sharp rate at t (``sharp``, put on the 8-bit scale with ``gain``).

    MOG models every pixel on its own, and its background B lies between the pixel's smallest
    and largest history value, so ``|f - B| >= phi0`` with f in the history is impossible where
    the history's range is below phi0. A sharp f outside the history could pass there, but
    such a pixel has not seen a mover in its history (its light changed only within the last
    few steps) and is left out too: f's noise would otherwise scatter objects, and the
    pixels MOG must run on, over the frame. The adaptive pipeline therefore runs MOG only on
    the pixels whose range reaches phi0 (none: no objects, MOG skipped), gathered into one
    row (as :func:`_future_objects` does): the same objects, at a cost that follows their
    number rather than their bounding box's.
    """
    h, w = u8.shape[1:]
    varies = None
    if adaptive or sharp is not None:
        varies = (u8.max(axis=0).astype(np.int16) - u8.min(axis=0)) >= phi0
    settings = _mog_settings(CfsrSettings.of(p), hist)
    if not adaptive:
        _, background = mog_background(u8, **settings)
        f = u8[-1] if sharp is None else sharp.u8((0, h, 0, w), gain)
        found = mog_objects(f, background, phi0)
        return found if sharp is None else found & varies
    if not varies.any():
        return np.zeros((h, w), bool)
    box = _box(varies, True)
    y0, y1, x0, x1 = box
    sel = varies[y0:y1, x0:x1]
    # the history of the varying pixels alone, as one row (MOG models each pixel on its own)
    row = np.ascontiguousarray(u8[:, y0:y1, x0:x1][:, sel][:, None, :])
    _, background = mog_background(row, **settings)
    f = row[-1, 0] if sharp is None else sharp.u8(box, gain)[sel]
    objects = np.zeros((h, w), bool)
    objects[y0:y1, x0:x1][sel] = mog_objects(f, background[0], phi0)
    return objects


def _box(mask: np.ndarray, adaptive: bool) -> tuple[int, int, int, int]:
    """The bounding box ``(y0, y1, x0, x1)`` of a non-empty ``mask`` (adaptive), or the frame."""
    if not adaptive:
        return 0, mask.shape[0], 0, mask.shape[1]
    ys, xs = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    return int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1


def _future_objects(
    src: PackedWindow,
    center: int,
    cand: np.ndarray,
    sharp: _Sharp,
    gain: float,
    match: float,
    adaptive: bool,
    s: CfsrSettings,
    hist: int,
) -> np.ndarray:
    """The candidate objects ``cand`` that are not ghosts by the **mirrored history**.

    The mirrored history: TFP frames (Eq. 4) over ``[t + k * s, t + k * s + mog_window)``, ``s =
    mog_future_stride``, ``k = mog_future_frames - 1 .. 0``, fed to a fresh MOG farthest first
    (time reversed, so the last frame is the one at t; frames past the window's end dropped),
    its background B as :func:`cfsr.methods.mog.mog_background`'s. A ghost -- background that a
    mover uncovered within the history before t, which that history's B still holds as the
    mover -- is background for the whole history after t: where the sharp rate at t lies
    within ``match`` levels (half of phi0 by default) of this B the pixel is a ghost. A pixel
    the mover covers at t lies near neither background, except by chance on a moving texture,
    hence the tighter ``match``.

    The frames are counted on the packed bytes of the candidates' bounding box (the whole
    frame when not ``adaptive``), and MOG, which models every pixel on its own, runs on the
    candidates alone, gathered into one row: its cost follows their number.
    """
    n = src.n
    win, stride = int(s.mog_window), int(s.mog_future_stride)
    starts = [
        center + k * stride
        for k in range(int(s.mog_future_frames) - 1, -1, -1)
        if center + k * stride + win <= n
    ]
    if not starts:  # no frame after t in the window: no ghost can be told
        return cand.copy()
    box = _box(cand, adaptive)
    y0, y1, x0, x1 = box
    sel = cand[y0:y1, x0:x1]
    # per row, the columns from its first to its last candidate (none: the row is skipped)
    rows = sel.any(axis=1)
    xa = np.where(rows, x0 + sel.argmax(axis=1), x0).astype(np.int64)
    xb = np.where(rows, x1 - sel[:, ::-1].argmax(axis=1), x0).astype(np.int64)
    counts = crop_counts(
        src.packed,
        src.geo,
        min(starts),
        max(starts) + win,
        np.asarray(starts, np.int64),
        win,
        y0,
        x0,
        xa,
        xb,
        np.zeros((len(starts), y1 - y0, x1 - x0), np.int32),
    )
    frames = to_u8(counts[:, sel].astype(np.float32) / np.float32(win), gain)
    _, background = mog_background(frames[:, None, :], **_mog_settings(s, hist))
    keep = np.zeros_like(cand)
    keep[y0:y1, x0:x1][sel] = mog_objects(sharp.u8(box, gain)[sel], background[0], match)
    return keep


def _compute(
    window: np.ndarray | PackedWindow,
    center: int,
    start: int,
    p: Mapping[str, Any],
    memo: MutableMapping[str, Any] | None = None,
) -> Output:
    rate, masks = fine_stage(window, center, int(start) + int(center), p, memo)
    return Output(rate, masks)


def _compute_packed(
    packed,
    layout,
    center: int,
    start: int,
    p: Mapping[str, Any],
    memo: MutableMapping[str, Any] | None = None,
) -> Output:
    return _compute(PackedWindow.from_packed(packed, layout), center, start, p, memo)


register(
    Method(
        name="cfsr",
        summary="Coarse-to-fine CFSR: CSR + MOG/DAISI fine mask + PatchMatch-refined TFI, ATSR",
        params={**CSR_PARAMS, **FINE_PARAMS},
        window=cfsr_window,
        compute=_compute,
        compute_packed=_compute_packed,
        masks=("coarse", "fine"),
        presets=FINE_PRESETS,
        reference="CFSR paper Eq. 3-14 (coarse and fine stages)",
        settings=CfsrSettings,
        recurrent=True,
        groups=carry_groups,
    )
)
