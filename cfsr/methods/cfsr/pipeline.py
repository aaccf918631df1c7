"""CFSR: coarse-to-fine reconstruction (CFSR paper Eq. 3-14), registered as ``cfsr``.

Pipeline for output step t (every stage a pure function of the spike window; the readings and
the calibration of every default are in docs/methods.md):

1. **CSR history** (:mod:`cfsr.methods.cfsr.coarse`): CSR frames at ``t - k * mog_stride`` for
   ``k = mog_frames - 1 .. 0`` (oldest first, the last one is t), their static region a TFP of
   ``mog_window`` steps (the paper's CSR, Eq. 5-7). The ``coarse`` output is the coarse mask
   at t: the steady-interval mask (:mod:`cfsr.methods.cfsr.steady_distinction`, default) or Eq. 6's
   (``distinction = isi_set``); with ``static_estimator = steady`` the static estimate at t
   is kept only where t's own interval agrees with it (the TFI elsewhere).
2. **MOG** (:mod:`cfsr.methods.cfsr.mog`, Eq. 8-9): a fresh ``bgsegm`` MOG model learns the history
   on the 8-bit scale (``mog_gain``: rate shown as 255, 0 = the 99.5th percentile of the CSR
   frame at t), gives the background B, and ``|f_t - B| >= phi0`` marks moving objects (phi0
   kept at least two count quanta of the MOG frames, so dark scenes do not mark noise).
   ``mog_sides = past`` is the paper's test (f: the MOG frame at t, a ``mog_window``-step
   TFP). ``both`` (default): f is the span rule over ``mog_span`` centred steps (the MOG
   frame where t's interval is longer than that span), and an object must also lie further
   than ``mog_match * phi0`` from the background of the **mirrored history** (TFP frames
   after t, fed to a second MOG farthest first): a *ghost*, background a mover uncovered
   within the history, matches it and leaves the fine mask (it stays in PatchMatch's region).
3. **DAISI** (:mod:`cfsr.methods.cfsr.daisi`, Eq. 10-14): adjacent-ISI log ratios ``>= phi`` within
   ``daisi_span`` steps of t mark the edges of moving objects.
4. **Fine mask**: the union of the coarse mask, the MOG objects and the DAISI edges, closed with
   a ``close_size`` square, holes filled, components under ``min_area`` pixels dropped, grown
   by ``dilate`` pixels ("the edges refine the object mask"). Then the **still pixels** among it
   (:mod:`cfsr.methods.cfsr.still_pixels`, ``still_reach`` > 0): pixels whose spikes hold one exact
   rate around t and either kept it to an end of ``t +- still_reach`` or come back to it
   after a change. They leave the mask (before and after the closing; holes a mover encloses
   are filled again) and the dilation does not grow into them; this is the ``fine`` output.
   PatchMatch still works on the mask before this step, and the still pixels left out take
   their run's rate.
5. **Fine reconstruction** (:mod:`cfsr.methods.cfsr.patchmatch`): TFI at t and at
   ``t +- pm_step*i``, ``i = 1..pm_count``, and ``pm_far_count`` more ``pm_far_step`` apart
   (clipped to the window), computed only on the 8 x 8 tiles within reach of a fine-mask
   pixel's own patch and one tile more (the rest hold NaN: never matched);
   PatchMatch on a guide (TFA over ``pm_guide`` intervals, Gaussian ``pm_sigma``) matches the
   6 x 6 patch of every fine-mask pixel in each frame, and the raw TFI rates at the matches
   are averaged with the reference.
6. **ATSR** (:mod:`cfsr.methods.cfsr.atsr`, Eq. 7): the refined dynamic region is fused with the
   static TFP (``tfp_window``) scaled by mean TFI / mean TFP over the static region.

"Skip what the scene does not need" (``adaptive``, default True): a window whose spike counts did
not change over the last two ``static_window`` spans (:mod:`cfsr.methods.cfsr.static_gate`) is
output as the TFP at once, with empty masks; otherwise the same test per ``static_tile`` tile leaves
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
(:class:`CfsrSettings`, built once per frame) are in :mod:`cfsr.methods.cfsr.params`, the
compiled whole-frame scans in :mod:`cfsr.methods.cfsr._history_kernels`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from cfsr._words import PackedWindow
from cfsr.methods.cfsr.carry import carry_groups, carry_in, carry_out
from cfsr.methods.cfsr.coarse import (
    CSR_PARAMS,
    csr_window,
    static_checked,
    static_length,
    steady_parts,
    uses_steady,
)
from cfsr.methods.cfsr.fine_mask import fine_region, moving_objects
from cfsr.methods.cfsr.fusion import refine_stage
from cfsr.methods.cfsr.history import History, history_scan
from cfsr.methods.cfsr.mog_two_sided import SharpRate
from cfsr.methods.cfsr.params import FINE_PARAMS, FINE_PRESETS
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.cfsr.slow_motion_windows import slow_fuse, slow_reach
from cfsr.methods.cfsr.static_gate import gated_rate, static_gate, tile_gates
from cfsr.methods.registry import Memo, Method, Output, register
from cfsr.methods.tfp import TfpMode, tfp_extent, tfp_span

__all__ = ["Coarse", "Masks", "cfsr_window", "fine_stage", "future_reach", "sharp_span"]


def cfsr_window(s: CfsrSettings) -> tuple[int, int]:
    """Steps before/after t that one CFSR frame needs (under its tier's settings)."""
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
        before = max(before, s.still_reach)
        after = max(after, s.still_reach)
    before, after = max(before, slow_reach(s)), max(after, slow_reach(s))  # slow-motion windows
    if s.adaptive and s.static_tol >= 0:  # the static gate's two spans end with the TFP's
        tfp_after = tfp_extent(static_length(s), s.tfp_mode)[1]
        before = max(before, 2 * s.static_window - tfp_after - 1)
    return before, after


def sharp_span(s: CfsrSettings) -> tuple[int, int]:
    """Steps before/after t that the sharp rate at t reads (``mog_span`` centred, the TFI's
    ``max_isi`` range for a pixel with fewer than two spikes in it)."""
    before, after = tfp_extent(s.mog_span, TfpMode.CENTRED)
    reach = s.max_isi
    return max(before, reach), max(after, reach)


def future_reach(s: CfsrSettings) -> int:
    """Steps after t that the mirrored history reads: frames ``[t + k * s, t + k * s +
    mog_window)``, ``s = mog_future_stride``, ``k = 0 .. mog_future_frames - 1``."""
    k, stride = s.mog_future_frames, s.mog_future_stride
    return (k - 1) * stride + s.mog_window - 1


class Coarse(NamedTuple):
    """Step 1, the coarse stage (:func:`_coarse_stage`); rates in spikes per step, (H, W)."""

    history: History  #: the whole-frame scan
    coarse: np.ndarray  #: bool: the coarse mask at t (steady rule or Eq. 5-6)
    tfp: np.ndarray  #: float32: the static estimate at t (steady-checked when asked)
    tfi: np.ndarray | None  #: float32: TFI at t when already read (None: not yet)
    sharp: SharpRate | None  #: Eq. 9's f under ``mog_sides = both`` (None: past)
    noise: float | None  #: the frame's temporal-noise level (None: not measured)


class Masks(NamedTuple):
    """Steps 2-4, the fine masks (:func:`_mask_stage`), bool (H, W) but ``tfp``."""

    coarse: np.ndarray  #: the ``coarse`` output
    fine: np.ndarray  #: the ``fine`` output (still pixels left out)
    region: np.ndarray  #: what PatchMatch reconstructs (the mask before the still pixels)
    left: np.ndarray | None  #: still pixels the fine mask leaves out (None: none)
    tfp: np.ndarray  #: float32: the static estimate, the still pixels' run rate there


def fine_stage(
    window: np.ndarray | PackedWindow,
    center: int,
    seed: int,
    s: CfsrSettings,
    memo: Memo | None = None,
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
    ``carry_gap`` after it): its CSR history frames stand in for this output's within half a stride
    (:func:`_carried_ends`), and the PatchMatch frames of the group's last output at the same steps
    are taken as computed (:func:`cfsr.methods.cfsr.patchmatch_frames.pm_frames`' bank: the
    same numbers). Without it, or for the first output of a group, the frame is the isolated
    one.
    """
    src = window if isinstance(window, PackedWindow) else PackedWindow.from_frames(window)
    carried, bank = carry_in(memo, int(seed), center, s)
    # 0. static gate: counts unchanged over the last two spans -> the TFP, nothing else to do
    pa, pb = tfp_span(center, src.n, static_length(s), s.tfp_mode)
    gate = static_gate(src, pb, s.static_window, s.static_tol) if s.adaptive else None
    if gate is not None:
        none = np.zeros((src.h, src.w), bool)
        carry_out(memo, int(seed), center, s, None, bank)
        return gated_rate(src, gate, pa, pb, center, s), {"coarse": none, "fine": none.copy()}
    active, slow_cand = tile_gates(src, pb, s)
    # 1. CSR history (oldest first; frames before the window start dropped), DAISI, TFI, TFP
    coarse = _coarse_stage(src, center, s, active, carried)
    frames = dict(zip(coarse.history.ends.tolist(), coarse.history.rates, strict=True))
    carry_out(memo, int(seed), center, s, frames, bank)
    # 2-4. MOG objects, DAISI edges, the fine mask and PatchMatch's region
    masks = _mask_stage(src, center, coarse, s)
    # 5-6. PatchMatch on the fine region, ATSR
    ref = refine_stage(src, center, seed, coarse, masks, s, bank)
    # 7. windows as long as the motion allows where the pixel moves slowly (slow_motion_windows)
    rate = slow_fuse(src, center, ref.rate, ref.used, s, slow_cand, coarse.noise)
    return rate, {"coarse": masks.coarse, "fine": masks.fine}


def _coarse_stage(
    src: PackedWindow,
    center: int,
    s: CfsrSettings,
    active: np.ndarray | None,
    carried: Mapping[int, np.ndarray] | None,
) -> Coarse:
    """Step 1: the history scan (:func:`history_scan`) and, when a steady rule or the two-sided
    test is on, the intervals around t: steady coarse mask, static check, sharp rate; read
    from the history scan's words, before anything else reuses its scratch store."""
    hs = history_scan(src, center, s, active, carried)
    if not (uses_steady(s.coarse) or s.two_sided):
        return Coarse(hs, hs.coarse, hs.tfp, hs.tfi, None, None)
    # CFSR has no dynamic estimator of its own: two-sided, the span rule at t is the sharp rate
    q = s.sharp if s.two_sided else s.coarse
    st = steady_parts(src, center, q, words=hs.words, static=False, active=active)
    sharp = SharpRate(st.dynamic, st.isi, hs.rates[-1], s.mog_span) if s.two_sided else None
    return Coarse(
        hs,
        hs.coarse if st.mask is None else st.mask,
        static_checked(hs.tfp, st.isi, st.noise, s.coarse),
        (1.0 / st.isi).astype(np.float32),  # the same numbers as tfi_at
        sharp,
        st.noise,
    )


def _mask_stage(
    src: PackedWindow, center: int, coarse: Coarse, s: CfsrSettings
) -> Masks:
    """Steps 2-4: MOG objects (Eq. 8-9, ghosts told by the mirrored history), DAISI edges
    (Eq. 10-14), the fine mask, its still pixels (left out, with their run's rate) and
    PatchMatch's region."""
    hist = coarse.history
    objects, ghosts = moving_objects(src, center, hist.rates, coarse.coarse, coarse.sharp, s)
    edges = hist.daisi >= s.phi
    fine, region, left, tfp = fine_region(
        src, center, coarse.coarse, objects, edges, ghosts, coarse.tfp, hist.words, s
    )
    return Masks(coarse.coarse, fine, region, left, tfp)


def _compute(
    window: np.ndarray | PackedWindow,
    center: int,
    start: int,
    s: CfsrSettings,
    memo: Memo | None = None,
) -> Output:
    rate, masks = fine_stage(window, center, int(start) + int(center), s, memo)
    return Output(rate, masks)


def _compute_packed(
    packed,
    layout,
    center: int,
    start: int,
    s: CfsrSettings,
    memo: Memo | None = None,
) -> Output:
    return _compute(PackedWindow.from_packed(packed, layout), center, start, s, memo)


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
        borrowed_mask="coarse",  # its dynamic pixels come from spikes along the motion
    )
)
