"""CFSR's parameter table: every parameter's default, unit, range and meaning (the one source
of them, :class:`~cfsr.methods.registry.Param`) and its presets. The quality tiers are in
:mod:`cfsr.methods.cfsr.tiers`, the typed settings the pipeline reads in
:mod:`cfsr.methods.cfsr.settings`.
"""

from __future__ import annotations

from dataclasses import replace
from enum import StrEnum

from cfsr.methods.cfsr.coarse import (
    CSR_ONLY_PARAMS,
    CSR_PARAMS,
    CSR_PRESETS,
)
from cfsr.methods.cfsr.slow_motion_windows import SLOW_PARAMS
from cfsr.methods.registry import MAX_WINDOW_STEPS, Param, Params, choices_of
from cfsr.methods.tfp import STATIC_ESTIMATORS


class MogSides(StrEnum):
    """Eq. 9's test (``mog_sides``)."""

    PAST = "past"  #: the MOG frame at t against the history before t (the paper's)
    BOTH = "both"  #: the sharp rate at t against the history before t and after it


class Quality(StrEnum):
    """CFSR's quality tier (``quality``; :mod:`cfsr.methods.cfsr.tiers`)."""

    FULL = "full"  #: every default
    FAST = "fast"  #: the cheaper point of the measured Pareto front


#: Ranges: a window-like parameter (steps) reaches at most half the ring's limit
#: (MAX_WINDOW_STEPS) on its side of t, the static gate's two spans a quarter each; frame
#: counts stay within what one frame can afford (each history or PatchMatch frame is a
#: full-frame pass); pixel sizes within a sensor's extent. Products (mog_frames * mog_stride,
#: pm_count * pm_step) are checked as a whole by resolve_params.
#: PatchMatch frames on each side of t (``pm_count``; ``pm_far_count`` is the same range)
FRAMES_A_SIDE = Param(24, "frames", "PatchMatch frames on each side of t", minimum=0, maximum=64)

FINE_PARAMS: dict[str, Param] = {
    # the static estimate's 160 steps centred on t, as CSR's span (CSR_ONLY_PARAMS): a slow
    # drift or vibration biases a trailing span by its 80-step lag (drift 0.001 px/step, motion
    # region +0.12 dB, lowlight +0.14, pan +0.09, no scene or REDS file lower by 0.07); the
    # frame's window after t (PatchMatch and TFI reach, 248 steps) already covers the 80 steps
    "tfp_mode": replace(CSR_PARAMS["tfp_mode"], default="centred"),
    "mog_frames": Param(
        12, "frames", "CSR frames K fed to MOG, ending at t", minimum=1, maximum=256
    ),
    "mog_stride": Param.steps(32, "steps between consecutive MOG frames"),
    "mog_window": Param.steps(64, "TFP window w of the CSR frames fed to MOG"),
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
        choices=choices_of(MogSides),
    ),
    # the steady span rule, as CSR's dynamic_span reads it (CfsrSettings.sharp)
    "mog_span": replace(
        CSR_ONLY_PARAMS["dynamic_span"],
        help="both: centred span of the rate at t compared with the backgrounds (steady span "
        "rule)",
    ),
    # half the frames of the history before t over about the same reach: the second MOG
    # costs in proportion to its frames, and 12 x 32 steps gave the same masks within 0.003
    "mog_future_frames": Param(
        6, "frames", "both: TFP frames of the mirrored history after t", minimum=1, maximum=256
    ),
    "mog_future_stride": Param.steps(64, "both: steps between the mirrored history's frames"),
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
    "still_reach": Param.steps(
        380,
        "steps searched each side of t for the still-pixel proof (0: no proof, the paper's "
        "fine mask)",
        minimum=0,
    ),
    "still_run": Param.steps(
        64,
        "still pixels: shortest stretch of exact constant rate, at t and where the rate returns",
        minimum=2,
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
    "daisi_span": Param.steps(
        5,
        "DAISI evaluated within t +- span (0: at t)",
        minimum=0,
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
    # 24 targets 2 steps apart (the same 48-step reach as 16 x 3, half again the samples):
    # REDS +0.23 (every file up), disk +0.26, fan +0.28, car +0.44, no scene lower than -0.02,
    # about 1.2x the CPU of a full frame; the fast tier takes 15 x 2 + 2 x 9 (QUALITY_TIERS)
    "pm_step": Param.steps(2, "spacing of PatchMatch frames t +- step*i"),
    "pm_count": FRAMES_A_SIDE,
    # a sparser tail keeps the reach of the slow movers (the pan) with fewer frames: the fast
    # tier's 15 x 2 + 2 x 9 (QUALITY_TIERS)
    "pm_far_count": replace(
        FRAMES_A_SIDE, default=0, help="PatchMatch frames on each side beyond the pm_count "
        "ones, pm_far_step apart"
    ),
    "pm_far_step": Param.steps(8, "spacing of the far PatchMatch frames"),
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
        "8, 17 PatchMatch targets a side (15 two steps apart, 2 nine apart): about 0.7x the "
        "CPU of full, within 0.5 dB of it on the simulator scenes); "
        "parameters set to other values than their defaults keep them",
        choices=choices_of(Quality),
    ),
    # outputs close together continue from the previous one (_Carry): its history frames are
    # reused instead of recomputed; the result moves by under 0.1 dB (docs/methods.md,
    # "Carried work")
    "carry_span": Param.steps(
        512,
        "outputs within one span of this many steps (spans start at multiples of it) reuse "
        "the previous output's work when at most carry_gap steps after it (0: every output "
        "from nothing, as an isolated one)",
        minimum=0,
        maximum=MAX_WINDOW_STEPS,
    ),
    "carry_gap": Param.steps(
        128,
        "largest step from the previous output that still reuses its work",
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
    "static_window": Param.steps(
        160,
        "length of each span the static gate compares",
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    # windows as long as the motion allows, per pixel (cfsr.methods.cfsr.slow_motion_windows)
    **SLOW_PARAMS,
}

FINE_PRESETS: dict[str, Params] = {
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

