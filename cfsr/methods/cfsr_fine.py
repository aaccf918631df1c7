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
   ``i = 1..pm_count`` (clipped to the window), computed only on the 8 x 8 tiles within reach
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
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Mapping, MutableMapping
from typing import Any, NamedTuple

import numpy as np
from numba import njit, prange

from cfsr._isi import search_range
from cfsr._words import (
    ROW_PAD,
    PackedWindow,
    Stored,
    Words,
    count_between,
    count_range,
    isi_in_words,
    n_words,
    next_spike,
    prefix_counts,
    prev_spike,
    range_times,
    row_or_stored,
    row_words,
)
from cfsr.methods.atsr import atsr_fuse, atsr_fuse_isi
from cfsr.methods.csr import (
    CSR_PARAMS,
    CSR_PRESETS,
    csr_window,
    span_estimator,
    static_checked,
    static_length,
    steady_parts,
    uses_steady,
)
from cfsr.methods.daisi import daisi_from_times, log_table
from cfsr.methods.distinction import distinct_in_words, long_isi_buffer
from cfsr.methods.masks import fine_mask
from cfsr.methods.mog import mog_background, mog_objects, to_u8
from cfsr.methods.patchmatch import finish_padding, padded_guides, patchmatch_fuse
from cfsr.methods.pmframes import TILE, match_reach, pm_frames, pm_tiles
from cfsr.methods.registry import MAX_WINDOW_STEPS, Method, Output, Param, register
from cfsr.methods.slowmotion import SLOW_PARAMS, slow_fuse, slow_reach
from cfsr.methods.staticgate import active_tiles, span_counts, span_isi_rate, static_gate
from cfsr.methods.steady import steady_range
from cfsr.methods.still import still_pixels
from cfsr.methods.tfp import STATIC_ESTIMATORS, span_rate, tfp_span

__all__ = [
    "QUALITY_TIERS",
    "carry_groups",
    "cfsr_window",
    "effective_params",
    "fast_config",
    "fine_mask",
    "fine_stage",
]

#: Ranges: a window-like parameter (steps) reaches at most half the ring's limit
#: (MAX_WINDOW_STEPS) on its side of t, the static gate's two spans a quarter each; frame
#: counts stay within what one frame can afford (each history or PatchMatch frame is a
#: full-frame pass); pixel sizes within a sensor's extent. Products (mog_frames * mog_stride,
#: pm_count * pm_step) are checked as a whole by resolve_params.
FINE_PARAMS: dict[str, Param] = {
    "mog_frames": Param(
        12, "frames", "CSR frames K fed to MOG, ending at t", minimum=1, maximum=256
    ),
    "mog_stride": Param(
        32,
        "steps",
        "steps between consecutive MOG frames",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "mog_window": Param(
        64,
        "steps",
        "TFP window w of the CSR frames fed to MOG",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    # MOG compares each pixel with its own history, so the frames' quantisation noise is
    # stationary and phi0 is sized for it (the quantum below); the isi rule makes the frames
    # sharper but moves a mover's edge pixels (first-to-last spike spans straddle it), which
    # cost fine-mask IoU and motion PSNR on the simulator (docs/methods.md)
    "mog_estimator": Param(
        "tfp",
        "",
        "rate rule of the CSR frames fed to MOG: tfp (Eq. 4) or isi (as static_estimator)",
        choices=STATIC_ESTIMATORS,
    ),
    "mog_history": Param(
        0, "frames", "MOG history length (0: mog_frames)", minimum=0, maximum=10_000
    ),
    "mog_mixtures": Param(3, "", "Gaussians per pixel in MOG", minimum=1, maximum=8),
    "mog_ratio": Param(0.7, "", "MOG background ratio", minimum=0.0, maximum=1.0),
    "mog_noise": Param(
        0.0, "8-bit levels", "MOG noise sigma (0: OpenCV default 15)", minimum=0, maximum=255.0
    ),
    "mog_gain": Param(
        0.0, "spikes/step", "rate shown as 255 for MOG (0: auto)", minimum=0, maximum=1.0
    ),
    # Eq. 9 against the past alone marks the background a mover left within the history (a
    # ghost: B is the mover) and, on the frame at t, the mover's 64-step trail; "both" asks
    # the sharp rate at t to differ from the background before t and from the background
    # of the mirrored history after t (docs/methods.md, "Two-sided objects")
    "mog_sides": Param(
        "both",
        "",
        "Eq. 9's test: past (the paper: the MOG frame at t against the background of the "
        "history before t) or both (the rate over mog_span centred steps at t against the "
        "background of the history before t and of its mirror after t)",
        choices=("past", "both"),
    ),
    "mog_span": Param(
        16,
        "steps",
        "both: centred span of the rate at t compared with the backgrounds (steady span rule)",
        minimum=2,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    # half the frames of the history before t over about the same reach: the second MOG
    # costs in proportion to its frames, and 12 x 32 steps gave the same masks within 0.003
    "mog_future_frames": Param(
        6, "frames", "both: TFP frames of the mirrored history after t", minimum=1, maximum=256
    ),
    "mog_future_stride": Param(
        64,
        "steps",
        "both: steps between the mirrored history's frames",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "mog_match": Param(
        0.5,
        "",
        "both: a pixel within mog_match * phi0 of the background after t is background (a "
        "ghost the past's background still holds as the mover); 0: no test after t",
        minimum=0,
        maximum=1.0,
    ),
    # a pixel whose spikes keep one exact rate around t, and which either kept it to an end
    # of the searched range or comes back to it after a change, is background at t: the fine
    # mask leaves it out and does not grow into it (docs/methods.md, "Still pixels")
    "still_reach": Param(
        380,
        "steps",
        "steps searched each side of t for the still-pixel proof (0: no proof, the paper's "
        "fine mask)",
        minimum=0,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "still_run": Param(
        64,
        "steps",
        "still pixels: shortest stretch of exact constant rate, at t and where the rate returns",
        minimum=2,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "still_jump": Param(
        0.2,
        "",
        "still pixels: an interval at least max(2 steps, still_jump * period) off the run's "
        "period is the change the rate must return across",
        minimum=0,
        maximum=10.0,
    ),
    "phi0": Param(
        20.0,
        "8-bit levels",
        "|f - B| threshold for moving objects (Eq. 9)",
        minimum=0,
        maximum=255.0,
    ),
    # |log ISI ratio| <= log(40,000) ~ 10.6 for any two intervals within 1 s
    "phi": Param(
        0.75, "log ratio", "DAISI edge threshold, natural log (Eq. 14)", minimum=0, maximum=20.0
    ),
    "daisi_span": Param(
        5,
        "steps",
        "DAISI evaluated within t +- span (0: at t)",
        minimum=0,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "close_size": Param(
        9, "pixels", "square closing of the fine mask (0/1: none)", minimum=0, maximum=64
    ),
    "min_area": Param(
        16, "pixels", "drop fine-mask components smaller than this", minimum=0, maximum=1 << 20
    ),
    "dilate": Param(
        2, "pixels", "grow the fine mask by this radius (safety margin)", minimum=0, maximum=64
    ),
    "pm_step": Param(
        3,
        "steps",
        "spacing of PatchMatch frames t +- step*i",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "pm_count": Param(16, "frames", "PatchMatch frames on each side of t", minimum=0, maximum=64),
    "pm_patch": Param(6, "pixels", "patch side", minimum=1, maximum=16),
    "pm_iters": Param(2, "", "PatchMatch scans", minimum=0, maximum=16),
    "pm_radius": Param(16, "pixels", "largest random-search radius", minimum=0, maximum=4096),
    "pm_guide": Param(
        3, "intervals", "guide = TFA over this many intervals (0: the TFI)", minimum=0, maximum=64
    ),
    "pm_sigma": Param(
        1.0, "pixels", "Gaussian sigma applied to the guide (0: none)", minimum=0, maximum=16.0
    ),
    # non-local-means weights instead of the paper's plain average: a match whose guide
    # differs by 0.015 spikes/step per pixel counts e^-1 as much; wrong matches of fast or
    # deforming content weigh less (REDS +0.24 dB, blades +0.8, car +0.2; noisy -0.05 in
    # the motion region; 0.01 and 0.02 gave REDS 0.07 and 0.04 dB less)
    "pm_h": Param(
        0.015,
        "spikes/step",
        "match weight scale exp(-SSD/(P^2 h^2)); 0: average",
        minimum=0,
        maximum=10.0,
    ),
    # the tier's settings replace only parameters left at their defaults (QUALITY_TIERS;
    # its measured cost and PSNR are in docs/methods.md, "Quality tiers")
    "quality": Param(
        "full",
        "",
        "quality tier: full (every default) or fast (4 MOG frames 96 steps apart on the past "
        "alone, a 200-step distinction window, 300-step still reach, PatchMatch search radius "
        "8: about 0.8x the CPU of full, within 0.15 dB of it on the simulator scenes); "
        "parameters set to other values than their defaults keep them",
        choices=("full", "fast"),
    ),
    # outputs close together continue from the previous one (_Carry): its history frames are
    # reused instead of recomputed; the result moves by under 0.1 dB (docs/methods.md,
    # "Carried work")
    "carry_span": Param(
        512,
        "steps",
        "outputs within one span of this many steps (spans start at multiples of it) reuse "
        "the previous output's work when at most carry_gap steps after it (0: every output "
        "from nothing, as an isolated one)",
        minimum=0,
        maximum=MAX_WINDOW_STEPS,
    ),
    "carry_gap": Param(
        128,
        "steps",
        "largest step from the previous output that still reuses its work",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "adaptive": Param(
        True,
        "",
        "skip what the scene does not need (False: every stage on the whole frame)",
    ),
    "static_tol": Param(
        1,
        "spikes",
        "adaptive: a window whose counts over two static_window spans differ by at most this "
        "at every pixel is output as TFP at once (-1: gate off)",
        minimum=-1,
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    # the gate per tile: tiles that pass it, and whose neighbours pass it, skip the proofs
    # the whole-frame stages would spend on them (docs/methods.md, "A gate per tile")
    "static_tile": Param(
        16,
        "pixels",
        "adaptive: side of the tiles the static gate also tests one by one; a tile whose "
        "counts and whose neighbours' counts pass is static without a proof (0: whole frame "
        "only)",
        minimum=0,
        maximum=4096,
    ),
    # the gate's two spans lie back to back before t
    "static_window": Param(
        160,
        "steps",
        "length of each span the static gate compares",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    # windows as long as the motion allows, per pixel (cfsr.methods.slowmotion)
    **SLOW_PARAMS,
}

FINE_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        **CSR_PRESETS["paper"],
        "mog_estimator": "tfp",
        "mog_sides": "past",
        "still_reach": 0,
        "phi0": 50.0,
        "phi": 4.0,
        "daisi_span": 0,
        "pm_step": 5,
        "pm_count": 10,
        "pm_guide": 0,
        "pm_sigma": 0.0,
        "pm_h": 0.0,
        "slow_reach": 0,
    },
    "simulated": {
        **CSR_PRESETS["simulated"],
        "mog_estimator": "tfp",
        "mog_sides": "past",
        "still_reach": 0,
        "slow_reach": 0,
    },
}


#: What each ``quality`` tier changes (docs/methods.md, "Quality tiers"). ``fast`` is the
#: cheapest point measured by ``cfsr bench --tiers`` that stays within 0.5 dB (whole frame) and
#: 1.0 dB (motion region) of ``full`` on every simulator scene.
QUALITY_TIERS: dict[str, dict[str, Any]] = {
    "full": {},
    "fast": {
        # the same reach of history (~380 steps) in 4 frames instead of 12, and the paper's
        # Eq. 9 on the past alone (no mirrored history after t): no scene moved by 0.1 dB
        "mog_frames": 4,
        "mog_stride": 96,
        "mog_sides": "past",
        # a 200-step distinction window and a 300-step still-pixel reach: within 0.05 dB
        "T": 200,
        "still_reach": 300,
        # the first PatchMatch target's full search from 8 pixels instead of 16 (no scene
        # moved). The PatchMatch targets stay: they are the largest cost, but 14 a side cost
        # the pan 0.63 dB and 12 the car 0.48-0.67 (the slow movers average noise over them)
        "pm_radius": 8,
    },
}

_DEFAULTS = {k: prm.default for k, prm in {**CSR_PARAMS, **FINE_PARAMS}.items()}


def effective_params(p: Mapping[str, Any]) -> Mapping[str, Any]:
    """The parameters one frame runs with: ``p`` with its ``quality`` tier's settings
    (:data:`QUALITY_TIERS`) in place of the values left at their defaults. A parameter set to
    any other value keeps it (a value equal to the default cannot be told from an unset one:
    the tier replaces it). ``full`` returns ``p`` itself."""
    tier = QUALITY_TIERS[p.get("quality", "full")]
    if not tier:
        return p
    return {**p, **{k: v for k, v in tier.items() if p.get(k, _DEFAULTS[k]) == _DEFAULTS[k]}}


def fast_config(cfg: Any) -> Any:
    """The ``fast`` tier of a CFSR :class:`~cfsr.config.MethodConfig` (its other parameters
    kept); a config of another method is returned as it is."""
    if cfg.method != "cfsr":
        return cfg
    return cfg.replace(params={"quality": "fast"})


def carry_groups(times: Iterable[int], p: Mapping[str, Any]) -> list[list[int]]:
    """Split output steps into the groups within which outputs carry work forward.

    The steps are sorted and deduplicated; a group ends where the next step lies in another
    span of ``carry_span`` steps (spans start at multiples of it, from step 0) or more than
    ``carry_gap`` steps after the previous one (``carry_span = 0``: every step alone). The
    groups depend only on the steps and these two parameters: the first output of a group is
    computed from nothing (as an isolated output) and the others continue from the one before
    them, so a group run in order with one memo gives the same frames in any process, and
    the frames do not depend on how the groups are shared between processes.
    """
    ts = sorted({int(t) for t in times})
    groups: list[list[int]] = []
    for t in ts:
        if groups and _continues(groups[-1][-1], t, p):
            groups[-1].append(t)
        else:
            groups.append([t])
    return groups


def _continues(prev: int, t: int, p: Mapping[str, Any]) -> bool:
    """Whether output step ``t`` continues from ``prev`` (:func:`carry_groups`' rule)."""
    span = int(p.get("carry_span", 0))
    return span > 0 and prev // span == t // span and 0 < t - prev <= int(p["carry_gap"])


def cfsr_window(p: Mapping[str, Any]) -> tuple[int, int]:
    """Steps before/after t that one CFSR frame needs (under its tier's settings)."""
    p = effective_params(p)
    cb, ca = csr_window(p)  # the static TFP at t
    hb, ha = csr_window({**p, "tfp_window": p["mog_window"], "static_span": 0})  # MOG history
    pm = p["pm_step"] * p["pm_count"]
    reach = p["max_isi"]
    before = max(
        cb, hb + (p["mog_frames"] - 1) * p["mog_stride"], pm + reach, p["daisi_span"] + reach
    )
    after = max(ca, ha, pm + reach, p["daisi_span"] + reach)
    if two_sided(p):  # the mirrored history after t and the sharp rate at t
        before = max(before, sharp_span(p)[0])
        after = max(after, future_reach(p), sharp_span(p)[1])
    if p.get("still_reach", 0) > 0:  # the still-pixel proof's range
        before = max(before, int(p["still_reach"]))
        after = max(after, int(p["still_reach"]))
    before, after = max(before, slow_reach(p)), max(after, slow_reach(p))  # slow-motion windows
    if p["adaptive"] and p["static_tol"] >= 0:  # the static gate's two spans end with the TFP's
        _, tfp_end = tfp_span(0, 1 << 62, static_length(p), p["tfp_mode"])  # steps after 0, +1
        before = max(before, 2 * p["static_window"] - tfp_end)
    return before, after


def two_sided(p: Mapping[str, Any]) -> bool:
    """Whether Eq. 9 tests the sharp rate at t against both backgrounds (``mog_sides``)."""
    return p.get("mog_sides", "past") == "both"


def sharp_span(p: Mapping[str, Any]) -> tuple[int, int]:
    """Steps before/after t that the sharp rate at t reads (``mog_span`` centred, the TFI's
    ``max_isi`` range for a pixel with fewer than two spikes in it)."""
    span = int(p["mog_span"])
    reach = int(p["max_isi"])
    return max(span // 2, reach), max(span - span // 2 - 1, reach)


def future_reach(p: Mapping[str, Any]) -> int:
    """Steps after t that the mirrored history reads: frames ``[t + k * s, t + k * s +
    mog_window)``, ``s = mog_future_stride``, ``k = 0 .. mog_future_frames - 1``."""
    k, s = int(p["mog_future_frames"]), int(p["mog_future_stride"])
    return (k - 1) * s + int(p["mog_window"]) - 1


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
# * :func:`_static_kernel` (whole frame): proves pixels static in every history frame (one
#   walk of their spikes), the TFP counts of the history and at t, DAISI at t -- all that a
#   static window needs;
# * :func:`_dynamic_kernel` (whole frame, only when some pixel is not proven static): TFI at
#   the K history steps and the coarse masks of the unproven pixels;
# * :mod:`cfsr.methods.pmframes` (only the tiles PatchMatch can read): TFI and TFA at the
#   PatchMatch steps.


@njit(cache=True, inline="always")
def _daisi_words(words, r, lo, c, dspan, d_lo, d_hi, loc, logs):  # pragma: no cover - numba
    """:func:`daisi_from_times` at ``c +- dspan`` from the only spikes it reads: those in
    ``[c - dspan - 1, c + dspan]`` and two on each side, all inside ``[d_lo, d_hi)``."""
    a_lo = c - dspan
    a_hi = c + dspan
    nl = 0
    p1 = prev_spike(words, r, lo, a_lo - 2, d_lo)
    if p1 >= 0:
        p2 = prev_spike(words, r, lo, p1 - 1, d_lo)
        if p2 >= 0:
            loc[nl] = p2
            nl += 1
        loc[nl] = p1
        nl += 1
    nl += range_times(words, r, lo, max(d_lo, a_lo - 1), min(d_hi, a_hi + 1), loc[nl:])
    n1 = next_spike(words, r, lo, a_hi + 1, d_hi)
    if n1 >= 0:
        loc[nl] = n1
        nl += 1
        n2 = next_spike(words, r, lo, n1 + 1, d_hi)
        if n2 >= 0:
            loc[nl] = n2
            nl += 1
    return daisi_from_times(loc[:nl], a_lo, a_hi, logs)


class _Union(NamedTuple):
    """The union ``[u_lo, u_hi)`` of the K distinction windows, their length ``span`` (T)
    and ``theta`` (Eq. 5-6)."""

    u_lo: int
    u_hi: int
    span: int
    theta: int


class _Spans(NamedTuple):
    """The static-rate spans of the K history frames and of t: span j is ``[bounds[ia[j]],
    bounds[ib[j]])`` (shared edges counted once), ``isi_est[j]`` its rule, ``cents[j]`` the
    step whose TFI (``m`` steps each side) a sparse pixel takes."""

    bounds: np.ndarray  #: int64 (nb,): sorted distinct span edges
    ia: np.ndarray  #: int64 (K + 1,)
    ib: np.ndarray  #: int64 (K + 1,)
    isi_est: np.ndarray  #: bool (K + 1,)
    cents: np.ndarray  #: int64 (K + 1,)
    m: int


class _Windows(NamedTuple):
    """The K history distinction windows of ``span`` (T) steps ending at ``ends``, ``theta``
    (Eq. 5-6), and the TFI search (``m`` steps each side of each end, Eq. 3)."""

    ends: np.ndarray  #: int64 (K,): sorted last steps of the windows
    span: int
    theta: int
    m: int


# a theta no distinct-ISI count reaches (T <= MAX_WINDOW_STEPS): the second pass then walks
# no coarse window and gives the TFI intervals alone (:func:`_tfi_at`)
_NO_COARSE = 1 << 30


class _Daisi(NamedTuple):
    """DAISI at ``c`` over ``c +- dspan`` (Eq. 10-14), spikes read in ``[d_lo, d_hi)``."""

    c: int
    dspan: int
    d_lo: int
    d_hi: int
    logs: np.ndarray  #: float64: :func:`cfsr.methods.daisi.log_table`


@njit(parallel=True, cache=True)
def _static_kernel(src, union, spans, dai, ub, tfp, daisi, kept, active):
    # pragma: no cover - numba
    """First pass of the history scan: what a static window needs, nothing more.

    Per pixel, on the words of ``src`` (:class:`~cfsr._words.Words`): ``ub``, the distinct
    ISIs of the union ``[u_lo, u_hi)`` of the K distinction windows (walk stopped at
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
    u_lo, u_hi, span, theta = union
    bounds, ia, ib, isi_est, cents, m = spans
    c, dspan, d_lo, d_hi, logs = dai
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
    for y in prange(h):
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
                ub[y, x] = distinct_in_words(words, r, nw, lo, u_lo, u_hi, span, big, theta)
                daisi[y, x] = _daisi_words(words, r, lo, c, dspan, d_lo, d_hi, loc, logs)
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


@njit(parallel=True, cache=True)
def _dynamic_kernel(src, wins, kept, ub, counts, isi, active):  # pragma: no cover - numba
    """Second pass, run only when some pixel was not proven static: the TFI interval at
    every history step (the ATSR scale of Eq. 7 needs it on the static region too) and,
    where ``ub >= theta``, each history window's distinct-ISI count (Eq. 5) by a walk that
    stops at ``theta`` (only ``count >= theta``, the coarse mask, is used: a moving pixel
    reaches it within a few words); elsewhere ``counts`` is ``ub``, below ``theta`` like
    every window's own count. ``src`` (:class:`~cfsr._words.Words`) gives the steps, ``wins``
    (:class:`_Windows`) the windows. Reads the first pass's words (``kept``,
    :class:`~cfsr._words.Stored`) when it holds one row per image row; otherwise gathers them.
    Where ``active`` (bool ``(H, W)``, or empty: every pixel) is False, only the TFI interval at
    the last step (t) is computed (``ub`` is 0 there)."""
    packed, geo, lo, hi = src
    ends, span, theta, m = wins
    store, bases = kept
    n = packed.shape[0]
    h, w = ub.shape
    k_count = ends.shape[0]
    every = active.shape[0] == 0
    nw = n_words(lo, hi)
    for y in prange(h):
        big = long_isi_buffer(lo, hi)
        words, base, step = row_or_stored(packed, geo, lo, hi, y, w, store, bases)
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


_SCRATCH = threading.local()


def _scratch(shape: tuple[int, ...]) -> np.ndarray:
    """The history scan's word store, kept per thread between calls: a fresh 13 MB array
    costs its page faults on every frame (several ms, more than the transposes it saves)."""
    buf = getattr(_SCRATCH, "words", None)
    if buf is None or buf.shape != shape:
        buf = _SCRATCH.words = np.empty(shape, np.uint64)
    return buf


def _history(
    src: PackedWindow,
    center: int,
    p: Mapping[str, Any],
    active: np.ndarray | None = None,
    carried: Mapping[int, np.ndarray] | None = None,
) -> dict[str, Any]:
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
    their ends; only the others, and the frame at t, are scanned. ``"ends"`` gives the
    history's ends as used.
    """
    n, h, w = src.n, src.h, src.w
    ks = range(p["mog_frames"] - 1, -1, -1)
    ends = np.array(
        [center - k * p["mog_stride"] for k in ks if center - k * p["mog_stride"] >= 0], np.int64
    )
    all_ends, reused = ends, dict[int, np.ndarray]()
    if carried:
        all_ends, reused = _carried_ends(ends, carried, int(p["mog_stride"]))
        ends = np.array([e for e in all_ends if e not in reused], np.int64)
    span, m, dspan, theta = (int(p[key]) for key in ("T", "max_isi", "daisi_span", "theta"))
    spans = [tfp_span(int(e), n, p["mog_window"], p["tfp_mode"]) for e in ends]
    ta = np.array([a for a, _ in spans], np.int64)
    tb = np.array([b for _, b in spans], np.int64)
    pa, pb = tfp_span(center, n, static_length(p), p["tfp_mode"])
    d_lo, d_hi = max(0, center - dspan - m), min(n, center + dspan + m + 1)
    u_lo, u_hi = max(0, int(ends[0]) - span + 1), int(ends[-1]) + 1
    # the words cover both passes (the second reads TFI intervals up to max_isi around ends)
    lo = max(0, min(u_lo, int(ta.min()), pa, d_lo, int(ends[0]) - m))
    hi = min(n, max(u_hi, int(tb.max()), pb, d_hi, int(ends[-1]) + m + 1))
    if uses_steady(p) or two_sided(p):  # the steady rules read the same words (fine_stage)
        s_lo, s_hi = steady_range(n, center, m)
        lo, hi = min(lo, s_lo), max(hi, s_hi)
        if two_sided(p):  # and the sharp rate at t
            s_lo, s_hi = tfp_span(center, n, int(p["mog_span"]), "centred")
            lo, hi = max(0, min(lo, s_lo)), min(n, max(hi, s_hi))
    k = ends.size
    # the K history TFP windows and the one at t, as indices into their sorted distinct edges
    wins = np.concatenate([np.stack([ta, tb], 1), [[pa, pb]]]).astype(np.int64)
    bounds, inv = np.unique(wins, return_inverse=True)
    inv = inv.reshape(wins.shape)
    # which windows take the isi rule: the history frames' (MOG's input) and the one at t
    isi_win = np.array(
        [p.get("mog_estimator", "tfp") == "isi"] * k + [span_estimator(p) == "isi"], np.bool_
    )
    # the kernels take an empty mask for "no tile gate": every pixel active
    act = np.empty((0, 0), np.bool_) if active is None else active
    ub = np.empty((h, w), np.int32)
    tfps = np.empty((k + 1, h, w), np.float32)
    daisi = np.empty((h, w), np.float32)
    store = _scratch((h, w + ROW_PAD, n_words(lo, hi)))
    bases = np.empty((h, 2), np.int64)
    _static_kernel(
        Words(src.packed, src.geo, lo, hi),
        _Union(u_lo, u_hi, span, theta),
        _Spans(
            bounds.astype(np.int64),
            np.ascontiguousarray(inv[:, 0]),
            np.ascontiguousarray(inv[:, 1]),
            isi_win,
            np.append(ends, center).astype(np.int64),
            m,
        ),
        _Daisi(int(center), dspan, d_lo, d_hi, log_table(d_hi - d_lo)),
        ub,
        tfps,
        daisi,
        Stored(store, bases),
        act,
    )
    words = (store, bases, lo, hi)
    if not (ub >= theta).any():  # every pixel proven static in every history frame
        rates, coarse = tfps[:k], np.zeros((h, w), bool)  # static rates, in [0, 1] already
        tfi = None
    else:
        rates, coarse, tfi = _second_pass(src, ends, words, ub, tfps[:k], act, active, p)
    return {
        "words": words,
        "rates": _with_carried(rates, ends, all_ends, reused, active),
        "ends": all_ends,
        "coarse": coarse,
        "tfi": (lambda: _tfi_at(src, center, m)) if tfi is None else (lambda: tfi),
        "tfp": tfps[k],
        "daisi": daisi,
    }


def _second_pass(
    src: PackedWindow,
    ends: np.ndarray,
    words: tuple[np.ndarray, np.ndarray, int, int],
    ub: np.ndarray,
    tfps: np.ndarray,
    act: np.ndarray,
    active: np.ndarray | None,
    p: Mapping[str, Any],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The history scan's second pass, when some pixel is not proven static: TFI at every
    history end (Eq. 3) and the coarse masks (Eq. 5-6) from the stored words; returns the
    CSR history (TFI where a frame has dynamic pixels, its TFP ``tfps`` elsewhere, as
    ``csr_frames``), the coarse mask at t and the TFI at t (spikes per step)."""
    store, bases, lo, hi = words
    k, h, w = tfps.shape
    theta = int(p["theta"])
    counts = np.empty((k, h, w), np.int32)
    isi = np.empty((k, h, w), np.int32)
    _dynamic_kernel(
        Words(src.packed, src.geo, lo, hi),
        _Windows(ends, int(p["T"]), theta, int(p["max_isi"])),
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
    _dynamic_kernel(
        Words(src.packed, src.geo, a, b),
        _Windows(np.array([center], np.int64), 1, _NO_COARSE, m),
        Stored(np.empty((0, 0, 0), np.uint64), np.empty((0, 2), np.int64)),  # gather words
        np.zeros((src.h, src.w), np.int32),
        np.empty_like(isi),
        isi,
        np.empty((0, 0), np.bool_),
    )
    return (1.0 / isi[0]).astype(np.float32)


def fine_stage(
    window: np.ndarray | PackedWindow,
    center: int,
    seed: int,
    p: Mapping[str, Any],
    memo: MutableMapping[str, Any] | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The whole CFSR pipeline on one window; returns ``(rate, {"coarse", "fine"})``.

    ``p["adaptive"]`` (default True) skips what the scene does not need: counts unchanged
    over the last two ``static_window`` spans (the static gate) or no fine-mask pixel ->
    the plain TFP; otherwise TFI frames and guides only on the tiles within a patch's reach
    of a fine-mask pixel (:func:`pm_tiles`) and PatchMatch only on the fine-mask pixels.
    ``adaptive=False`` is the always-full pipeline: MOG on the whole frame, TFI frames, guides
    and PatchMatch on every pixel, then the same output rule (TFP where the fine mask is empty,
    ATSR with the fine mask otherwise), so the two differ only where PatchMatch's propagation
    from pixels outside the mask changes a match.

    ``p`` runs under its ``quality`` tier (:func:`effective_params`). ``seed`` is the absolute
    step of t (PatchMatch's draws are keyed by it). ``memo`` (a dict kept for one stream) carries
    work from the previous output to this one when :func:`carry_groups`' rule joins them (the
    same span of ``carry_span`` steps, at most ``carry_gap`` after it): its CSR history frames
    stand in for this output's within half a stride (:func:`_carried_ends`), and the
    PatchMatch frames of the group's last output at the same steps are taken as computed
    (:func:`cfsr.methods.pmframes.pm_frames`' bank: the same numbers). Without it, or for the
    first output of a group, the frame is the isolated one.
    """
    p = effective_params(p)
    src = window if isinstance(window, PackedWindow) else PackedWindow.from_frames(window)
    n, h, w = src.n, src.h, src.w
    carried, bank = _carry_in(memo, int(seed), center, p)
    adaptive = bool(p.get("adaptive", True))
    # 0. static gate: counts unchanged over the last two spans -> the TFP, nothing else to do
    pa, pb = tfp_span(center, n, static_length(p), p["tfp_mode"])
    gate = static_gate(src, pb, p["static_window"], p["static_tol"]) if adaptive else None
    if gate is not None:
        none = np.zeros((h, w), bool)
        _carry_out(memo, int(seed), center, p, None, bank)
        return _gated_rate(src, gate, pa, pb, center, p), {"coarse": none, "fine": none.copy()}
    active, slow_cand = _tile_gates(src, pb, adaptive, p)
    # 1. CSR history (oldest first; frames before the window start dropped), DAISI, TFI, TFP
    hs = _history(src, center, p, active, carried)
    rates, coarse, tfp = hs["rates"], hs["coarse"], hs["tfp"]
    frames = dict(zip(hs["ends"].tolist(), rates, strict=True))
    _carry_out(memo, int(seed), center, p, frames, bank)
    tfi_at_t = hs["tfi"]
    sharp = None  # Eq. 9's f under mog_sides = both (_Sharp)
    noise = None  # the frame's temporal-noise level (steady rules; the slow-motion stage's gate)
    if uses_steady(p) or two_sided(p):  # the intervals around t: steady coarse mask, static
        # check, sharp rate; from the history scan's words, before anything else reuses its
        # scratch store
        q = p
        if two_sided(p):  # CFSR has no dynamic estimator of its own: the span rule at t
            q = {**p, "dynamic_estimator": "steady", "dynamic_span": int(p["mog_span"])}
        st = steady_parts(src, center, q, words=hs["words"], static=False, active=active)
        noise = st.noise
        coarse = coarse if st.mask is None else st.mask
        tfp = static_checked(tfp, st.isi, st.noise, p)
        tfi_t = (1.0 / st.isi).astype(np.float32)  # the same numbers as _tfi_at
        if two_sided(p):
            sharp = _Sharp(st.dynamic, st.isi, rates[-1], int(p["mog_span"]))

        def tfi_at_t():
            return tfi_t

    # 2. MOG background and moving objects (Eq. 8-9), ghosts told by the mirrored history
    objects, ghosts = _objects(src, center, rates, coarse, sharp, adaptive, p)
    # 3. DAISI edges (Eq. 10-14)
    edges = hs["daisi"] >= p["phi"]

    # 4. fine mask, its still pixels (left out, with their run's rate) and PatchMatch's region
    fine, region, left, tfp = _fine_region(
        src, center, coarse, objects, edges, ghosts, tfp, hs["words"], p
    )
    masks = {"coarse": coarse, "fine": fine}
    if adaptive and not region.any():
        rate = np.clip(tfp, 0.0, 1.0).astype(np.float32)
        return slow_fuse(src, center, rate, None, p, slow_cand, noise), masks
    # 5. TFI refined by PatchMatch on the fine region (adaptive: only on the tiles within a
    # patch's reach of a fine-mask pixel); the ATSR below reads the refined rates on region &
    # ~left only: the still pixels left out (and, always-full, the pixels outside the region)
    # are matched but not averaged
    used = region if left is None else region & ~left
    refined, (y0, x0), domain = _refine(src, center, seed, region, used, adaptive, p, bank)
    if not region.any():  # always-full pipeline on a static window: the same TFP output
        rate = np.clip(tfp, 0.0, 1.0).astype(np.float32)
        return slow_fuse(src, center, rate, None, p, slow_cand, noise), masks
    tfi_full = tfi_at_t()  # TFI at t (computed here when the history did not need it)
    dyn = tfi_full.copy()
    crop = dyn[y0 : y0 + domain.shape[0], x0 : x0 + domain.shape[1]]
    crop[domain] = refined[domain]
    # 6. ATSR (Eq. 7)
    rate, _ = atsr_fuse(dyn, tfp, used, tfi=tfi_full)
    # 7. windows as long as the motion allows where the pixel moves slowly (slowmotion)
    return slow_fuse(src, center, rate, used, p, slow_cand, noise), masks


def _gated_rate(src: PackedWindow, gate: np.ndarray, pa: int, pb: int, center: int,
                p: Mapping[str, Any]) -> np.ndarray:
    """The output of a window the static gate passes (``gate``: its counts over the last
    span): the static estimate over ``[pa, pb)``, spikes per step in [0, 1]. Such a window
    has no mover for the steady check to catch, so the isi rule applies as is."""
    if span_estimator(p) == "isi":  # below two spikes: the TFI at t
        tfp = span_isi_rate(src, pa, pb, center=center, max_isi=int(p["max_isi"]))
    else:
        counts = gate if pb - pa == p["static_window"] else span_counts(src, pa, pb)
        tfp = counts / np.float32(max(1, pb - pa))
    return np.clip(tfp, 0.0, 1.0).astype(np.float32)


def _tile_gates(
    src: PackedWindow, pb: int, adaptive: bool, p: Mapping[str, Any]
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(active, slow_cand)``: the pixels of the tiles the static gate per tile does not
    pass (None: all), for the adaptive stages and for the slow-motion windows.

    The slow-motion windows look only where the gate per tile finds a change (its tiles are
    still: their rate is a long window's already) whatever ``adaptive`` and the gate
    settings, so that every pipeline gives a still window the same output."""
    tile, tol = int(p.get("static_tile", 0)), int(p["static_tol"])

    def tiles(tol: int, tile: int) -> np.ndarray | None:
        a = active_tiles(src, pb, p["static_window"], tol, tile)
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
    adaptive: bool,
    p: Mapping[str, Any],
) -> tuple[np.ndarray, np.ndarray | None]:
    """Eq. 8-9 on the CSR history ``rates`` (oldest first): the moving objects, and the
    ghosts (None: not tested) that the mirrored history after t tells apart
    (``mog_sides = both``)."""
    gain = p["mog_gain"]
    if gain <= 0:
        gain = float(np.percentile(rates[-1], 99.5)) if rates[-1].size else 1.0
        if not np.isfinite(gain) or gain <= 0:
            gain = 1.0
    u8 = to_u8(rates, gain)
    # one spike more or less in the MOG frames' window moves the 8-bit value by `quantum`
    # levels; in dark scenes that exceeds phi0 and Eq. 9 would mark noise, so phi0 is kept
    # at least two quanta (no effect at ordinary brightness: 16 levels at rate_scale 0.5)
    quantum = 255.0 / (p["mog_window"] * gain)
    phi0 = max(p["phi0"], 2.0 * quantum)
    hist = p["mog_history"] or p["mog_frames"]
    objects = _mog_objects(u8, phi0, adaptive, p, hist, sharp, gain)
    match = phi0 * float(p["mog_match"])
    ghosts = None
    if sharp is not None and match > 0:  # a ghost matches the background after t
        # only objects outside the coarse mask can change the fine mask (the union is what
        # is regularised), so only they are tested
        cand = objects & ~coarse
        if cand.any():
            keep = _future_objects(src, center, cand, sharp, gain, match, adaptive, p, hist)
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
    p: Mapping[str, Any],
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
            close_size=p["close_size"],
            min_area=p["min_area"],
            dilate=p["dilate"],
            still=still,
        )

    fine = cues()
    region = fine  # what PatchMatch reconstructs
    left = None  # still pixels the reported fine mask leaves out: their run's rate
    if int(p.get("still_reach", 0)) > 0 and fine.any():
        # the still pixels among the mask's: background at t, proven by their own spikes
        still, still_rate = still_pixels(
            src,
            center,
            fine,
            reach=int(p["still_reach"]),
            min_run=int(p["still_run"]),
            jump=float(p["still_jump"]),
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
    adaptive: bool,
    p: Mapping[str, Any],
    bank: dict[str, Any] | None = None,
) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """Step 5: the TFI at t refined by PatchMatch (Eq. 3 + the paper's patch averaging) on
    ``region`` (adaptive: TFI frames and guides only on the tiles within a patch's reach of
    it), averaged on ``used``. Returns ``(refined, (y0, x0), domain)``: the refined rates of
    the crop at ``(y0, x0)`` and the crop's pixels they hold. ``bank``: the PatchMatch frames
    carried within a group of outputs (:func:`cfsr.methods.pmframes.pm_frames`)."""
    h, w, n = src.h, src.w, src.n
    if adaptive:
        # a match reaching beyond the computed tiles reads NaN and is never taken (pm_frames);
        # one tile more than a pixel's own patch reads at zero motion leaves room for the
        # motion (with none, the blades' moving pixels lost 0.11 dB; docs/methods.md)
        reach = match_reach(int(p["pm_patch"]), float(p["pm_sigma"])) + TILE
        tiles = pm_tiles(region, reach)
        ty, tx = np.nonzero(tiles)
        y0, y1 = ty.min() * TILE, min(h, (ty.max() + 1) * TILE)
        x0, x1 = tx.min() * TILE, min(w, (tx.max() + 1) * TILE)
        domain = region[y0:y1, x0:x1]
    else:
        y0, y1, x0, x1 = 0, h, 0, w
        tiles = None
        domain = np.ones((h, w), bool)
    offs = [p["pm_step"] * i for i in range(1, p["pm_count"] + 1)]
    # the reference t first, then t -+ step*i inside the window
    tcs = [center] + [c for s in offs for c in (center - s, center + s) if 0 <= c < n]
    # the guides go straight into the buffer the search reads (no padded copy of 33 frames)
    padded, view = padded_guides(len(tcs), int(y1 - y0), int(x1 - x0), int(p["pm_patch"]))
    raw, guides = pm_frames(
        src,
        tcs,
        (int(y0), int(y1), int(x0), int(x1)),
        p,
        tiles,
        guide_out=view,
        bank=bank,
        shift=seed - center,
    )
    finish_padding(padded, int(p["pm_patch"]))
    refined = patchmatch_fuse(
        raw[0],
        guides[0],
        raw[1:],
        guides[1:],
        domain,
        wanted=used[y0:y1, x0:x1],
        patch=p["pm_patch"],
        iters=p["pm_iters"],
        max_radius=p["pm_radius"],
        h=p["pm_h"],
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
    key: tuple  #: its effective parameters: another set carries nothing
    frames: dict[int, np.ndarray]  #: absolute last step -> CSR history frame (H, W) float32
    #: the PatchMatch frames of the group's last output that ran PatchMatch, by absolute
    #: step (:func:`cfsr.methods.pmframes.pm_frames`)
    bank: dict[str, Any]


def _carry_key(p: Mapping[str, Any]) -> tuple:
    return tuple(sorted((k, v) for k, v in p.items() if not k.startswith("carry_")))


def _carry_in(
    memo: MutableMapping[str, Any] | None, t: int, center: int, p: Mapping[str, Any]
) -> tuple[dict[int, np.ndarray] | None, dict[str, Any] | None]:
    """The previous output's history frames (window indices -> frame; None: none) when output
    step ``t`` continues from it (:func:`_continues`), and the group's PatchMatch frames (an
    empty bank for the first output of a group; None without a memo or with
    ``carry_span = 0``)."""
    if memo is None or int(p.get("carry_span", 0)) <= 0:
        return None, None
    old = memo.get("cfsr")
    if not isinstance(old, _Carry) or not _continues(old.t, t, p) or old.key != _carry_key(p):
        return None, {}
    shift = t - center  # absolute step of window index 0
    return {a - shift: f for a, f in old.frames.items()}, old.bank


def _carry_out(
    memo: MutableMapping[str, Any] | None,
    t: int,
    center: int,
    p: Mapping[str, Any],
    frames: Mapping[int, np.ndarray] | None,
    bank: dict[str, Any] | None = None,
) -> None:
    """Leave this output's history frames (window index -> frame; None: none) and the
    group's PatchMatch frames (``bank``, which :func:`_refine` fills in place) in ``memo``."""
    if memo is None or int(p.get("carry_span", 0)) <= 0:
        return
    shift = t - center
    kept = {} if frames is None else {e + shift: f for e, f in frames.items()}
    memo["cfsr"] = _Carry(t, _carry_key(p), kept, {} if bank is None else bank)


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


def _mog_settings(p: Mapping[str, Any], hist: int) -> dict[str, Any]:
    """:func:`cfsr.methods.mog.mog_background`'s settings from the parameters (both MOGs)."""
    return {
        "history": hist,
        "nmixtures": p["mog_mixtures"],
        "background_ratio": p["mog_ratio"],
        "noise_sigma": p["mog_noise"],
    }


def _mog_objects(
    u8: np.ndarray,
    phi0: float,
    adaptive: bool,
    p: Mapping[str, Any],
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
    settings = _mog_settings(p, hist)
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


@njit(parallel=True, cache=True)
def _crop_counts(packed, geo, lo, hi, starts, length, y0, x0, xa, xb, out):
    # pragma: no cover - numba
    """``out[k, i, x - x0]``: spikes of image pixel ``(y0 + i, x)``, ``xa[i] <= x <
    xb[i]`` (a row with ``xa[i] >= xb[i]`` is skipped), in steps ``[starts[k], starts[k] +
    length)`` (all inside ``[lo, hi)``), from the packed frames: those pixels' words
    (:func:`cfsr._words.row_words`, one transpose per 64 steps x 64 pixels) and masked
    popcounts (:func:`cfsr._words.count_between`). Other entries are left as they are."""
    k_count, hh, ww = out.shape
    nw = (hi - lo + 63) >> 6
    for i in prange(hh):
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
    p: Mapping[str, Any],
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
    win, stride = int(p["mog_window"]), int(p["mog_future_stride"])
    starts = [
        center + k * stride
        for k in range(int(p["mog_future_frames"]) - 1, -1, -1)
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
    counts = _crop_counts(
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
    _, background = mog_background(frames[:, None, :], **_mog_settings(p, hist))
    keep = np.zeros_like(cand)
    keep[y0:y1, x0:x1][sel] = mog_objects(sharp.u8(box, gain)[sel], background[0], match)
    return keep


def _compute(
    window: np.ndarray,
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
    src = PackedWindow.from_packed(packed, layout)
    rate, masks = fine_stage(src, center, int(start) + int(center), p, memo)
    return Output(rate, masks)


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
        recurrent=True,
        groups=carry_groups,
    )
)
