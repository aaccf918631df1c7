"""CSR: coarse region-adaptive reconstruction (CFSR paper Eq. 5-7).

1. Coarse distinction (Eq. 5-6, :mod:`cfsr.methods.cfsr.distinction`): a pixel is dynamic when the
   ISIs inside the ``T`` steps before t take at least ``theta`` distinct values.
2. TFI (Eq. 3) on dynamic pixels, a static estimate on static ones: the paper's TFP (Eq. 4,
   window ``tfp_window``) with ``static_estimator=tfp``, or with ``isi`` the span's spike count
   less one over its first-to-last spike distance (:func:`cfsr.methods.tfp.span_rate`, exact
   for a steady pixel where the window count is off by up to one spike), over ``static_span``
   steps (0: ``tfp_window``) placed like the TFP window; a pixel with fewer than two spikes
   in the span takes the TFI (:func:`cfsr.methods.tfp.static_rate`).
3. ATSR (Eq. 7, :mod:`cfsr.methods.cfsr.atsr`): the static estimate is scaled by mean TFI / mean
   static estimate over the static region and pasted with the dynamic TFI.

A window with no dynamic pixel needs only TFP: the TFI stage is skipped and the scale is 1
(there is no dynamic region whose brightness the static one must match).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any

import numpy as np

from cfsr._words import PackedWindow
from cfsr.methods.cfsr.atsr import atsr_fuse
from cfsr.methods.cfsr.distinction import coarse_masks, distinct_isi_counts_packed
from cfsr.methods.cfsr.steady_distinction import (
    DISTINCTIONS,
    Distinction,
    check_static,
    noise_level,
    steadiness,
    steady_mask,
)
from cfsr.methods.registry import (
    MAX_WINDOW_STEPS,
    Method,
    MethodSettings,
    Output,
    Param,
    Params,
    choices_of,
    register,
)
from cfsr.methods.tfi import tfi_rate_packed, tfi_rates
from cfsr.methods.tfp import (
    RateRule,
    TfpMode,
    static_rate,
    static_rate_packed,
    tfp_extent,
    tfp_rate,
    tfp_rate_packed,
    tfp_span,
)


class StaticEstimator(StrEnum):
    """The static region's rate at t (:func:`static_checked`)."""

    STEADY = "steady"  #: ``isi`` where the interval at t agrees with it, the TFI elsewhere
    ISI = "isi"  #: ``(spikes - 1) / (last - first)`` over the span, the TFI below two spikes
    TFP = "tfp"  #: window count / w (Eq. 4, the paper's)


class DynamicEstimator(StrEnum):
    """``csr``'s dynamic-region rate."""

    STEADY = "steady"  #: the checked span rule over ``dynamic_span`` centred steps
    TFI = "tfi"  #: the interval at t (Eq. 7, the paper's)


#: Static-region estimators of CSR and CFSR at t (:func:`static_checked`).
STATIC_CHOICES = choices_of(StaticEstimator)

__all__ = ["csr_frames", "csr_frame_packed", "CSR_PARAMS", "csr_window", "static_length"]

#: Parameters shared by ``csr`` and ``cfsr`` (defaults calibrated on the simulator, see
#: docs/methods.md; the paper's values are in the ``paper`` preset). Window-like parameters
#: reach at most half the ring's limit each, so that any combination fits (before + after).
CSR_PARAMS: dict[str, Param] = {
    "T": Param.steps(
        300,
        "coarse distinction window T before t (Eq. 5)",
        minimum=2,
    ),
    # distinct ISIs in T steps sum to at most T, so there are fewer than sqrt(2 T) <= 283
    "theta": Param(
        8,
        "ISI values",
        "distinct ISI values in T that make a pixel dynamic (Eq. 6)",
        minimum=1,
        maximum=1000,
    ),
    "tfp_window": Param.steps(160, "TFP window w for the static region (Eq. 4)"),
    "tfp_mode": Param(
        "trailing", "", "TFP window: trailing (Eq. 4) or centred", choices=choices_of(TfpMode)
    ),
    "max_isi": Param.steps(200, "TFI search range each side of t (Eq. 3)"),
    # steady by default: the isi rule where t's own interval agrees with it, the TFI where it
    # does not (a mover the masks miss is not smeared); isi and the paper's tfp are choices
    "static_estimator": Param(
        "steady",
        "",
        "static-region rate: tfp (Eq. 4, window count / w), isi ((spikes - 1) / first-to-last "
        "spike steps over static_span; the TFI below two spikes) or steady (isi where the "
        "interval at t agrees with it within steady_match, the TFI elsewhere)",
        choices=STATIC_CHOICES,
    ),
    "steady_match": Param(
        0.05,
        "",
        "steady: relative tolerance of |ISI(t) - 1/rate| (plus one step; at least "
        "steady_noise times the frame's noise level)",
        minimum=0.0,
        maximum=100.0,
    ),
    "distinction": Param(
        "steady",
        "",
        "coarse distinction: steady (interval spread around t, regularised) or isi_set "
        "(distinct ISIs in T >= theta, Eq. 5-6)",
        choices=DISTINCTIONS,
    ),
    "steady_radius": Param.steps(
        24,
        "steady: intervals containing a step within this many steps of t are compared",
        maximum=MAX_WINDOW_STEPS // 4,
    ),
    "steady_tol": Param(
        0.2,
        "",
        "steady: relative interval spread (max - min - 1) / mean above which a pixel is "
        "dynamic",
        minimum=0.0,
        maximum=100.0,
    ),
    "steady_noise": Param(
        3.5,
        "",
        "steady: the spread tolerance is at least this many times the frame's median spread "
        "(its temporal-noise level)",
        minimum=0.0,
        maximum=100.0,
    ),
    "coarse_close": Param(
        15,
        "pixels",
        "steady: closing square of the coarse mask (holes filled; <= 1: none)",
        minimum=0,
        maximum=255,
    ),
    # 0 keeps the TFP window; a longer span sees more intervals (more precise for dark static
    # pixels, more smear on a mover the distinction misses)
    "static_span": Param.steps(
        0,
        "isi: span of the static estimate, placed as tfp_mode (0: tfp_window)",
        minimum=0,
    ),
}

CSR_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        "T": 400,
        "theta": 6,
        "tfp_window": 160,
        "tfp_mode": "trailing",
        "static_estimator": "tfp",
        "static_span": 0,
        "distinction": "isi_set",
    },
    "simulated": {
        "T": 300,
        "theta": 10,
        "tfp_window": 30,
        "tfp_mode": "trailing",
        "static_estimator": "tfp",
        "static_span": 0,
        "distinction": "isi_set",
    },
}

#: ``csr`` alone has no fine stage: its dynamic region is the whole answer there. The paper
#: gives it the TFI (Eq. 7), whose one interval is the noisiest estimate of a moving pixel; by
#: default it gets the steady-checked span rule over a short centred span (``dynamic_span``),
#: so the two regions differ in span length only (docs/methods.md, CSR). The paper's TFP
#: window, if chosen, stays short and centred (it smears a missed mover less); the steady
#: static span is long (static_span = 160, centred), its check catching missed movers.
#: Shared parameters keep CSR_PARAMS' unit and range; only their defaults (and a help text
#: that names the steady rule) differ here.
CSR_ONLY_PARAMS: dict[str, Param] = {
    **CSR_PARAMS,
    "static_span": replace(
        CSR_PARAMS["static_span"],
        default=160,
        help="isi/steady: span of the static estimate, placed as tfp_mode (0: tfp_window)",
    ),
    "dynamic_estimator": Param(
        "steady",
        "",
        "dynamic-region rate: tfi (Eq. 7, the interval at t) or steady (the steady static "
        "rule over dynamic_span centred steps)",
        choices=choices_of(DynamicEstimator),
    ),
    "dynamic_span": Param.steps(
        16,
        "steady: centred span of the dynamic region's estimate",
        minimum=2,
    ),
    "tfp_window": replace(CSR_PARAMS["tfp_window"], default=32),
    "tfp_mode": replace(CSR_PARAMS["tfp_mode"], default="centred"),
}


@dataclass(frozen=True)
class CoarseSettings(MethodSettings):
    """The coarse stage's parameters (:data:`CSR_PARAMS`: meaning, unit and range), shared by
    ``csr`` (:class:`CsrSettings`) and ``cfsr``."""

    T: int  #: distinction window before t (Eq. 5), steps
    theta: int  #: distinct ISI values that make a pixel dynamic (Eq. 6)
    tfp_window: int  #: TFP window w (Eq. 4), steps
    tfp_mode: TfpMode
    max_isi: int  #: TFI search range each side of t (Eq. 3), steps
    static_estimator: StaticEstimator
    steady_match: float
    distinction: Distinction
    steady_radius: int  #: steps
    steady_tol: float
    steady_noise: float
    coarse_close: int  #: pixels
    static_span: int  #: steps (0: tfp_window)


@dataclass(frozen=True)
class CsrSettings(CoarseSettings):
    """``csr``'s parameters (:data:`CSR_ONLY_PARAMS`): the coarse ones and the dynamic
    region's estimate."""

    dynamic_estimator: DynamicEstimator
    dynamic_span: int  #: steps

    @classmethod
    def of(cls, p: Params | MethodSettings) -> CsrSettings:
        """As :meth:`MethodSettings.of`; a parameter set without a dynamic estimator of its own
        (CFSR's, whose fine stage reconstructs the dynamic region) takes the paper's TFI."""
        if isinstance(p, cls):
            return p
        if isinstance(p, MethodSettings) or "dynamic_estimator" not in p:
            return tfi_dynamic(CoarseSettings.of(p))
        return super().of(p)


def tfi_dynamic(c: CoarseSettings) -> CsrSettings:
    """``c``'s coarse parameters with the TFI (Eq. 7) as the dynamic region's estimate."""
    return CsrSettings(
        **c.pick(*CoarseSettings.names()),
        dynamic_estimator=DynamicEstimator.TFI,
        dynamic_span=_TFI_SPAN,
    )


#: ``dynamic_span`` of :func:`tfi_dynamic` (not read under the TFI)
_TFI_SPAN = CSR_ONLY_PARAMS["dynamic_span"].default


def static_length(s: CoarseSettings) -> int:
    """Steps of the static estimate's span: ``static_span`` for ``isi`` when set, else
    ``tfp_window``."""
    if s.static_estimator is not StaticEstimator.TFP and s.static_span > 0:
        return s.static_span
    return s.tfp_window


def csr_window(s: CsrSettings) -> tuple[int, int]:
    """Steps before/after t that one CSR frame needs."""
    tb, ta = tfp_extent(static_length(s), s.tfp_mode)
    reach = s.max_isi  # TFI at t; the steady rules read inside the same range
    if s.dynamic_estimator is DynamicEstimator.STEADY:
        reach = max(reach, s.dynamic_span // 2 + 1)
    return max(s.T - 1, tb, reach), max(ta, reach)


def uses_steady(s: CsrSettings) -> bool:
    """Whether a parameter set reads the intervals around t
    (:mod:`cfsr.methods.cfsr.steady_distinction`)."""
    return (
        s.distinction is Distinction.STEADY
        or s.static_estimator is StaticEstimator.STEADY
        or s.dynamic_estimator is DynamicEstimator.STEADY
    )


def span_estimator(s: CoarseSettings) -> RateRule:
    """The span rule under ``static_estimator`` (``steady`` is ``isi`` plus a check)."""
    if s.static_estimator is StaticEstimator.STEADY:
        return RateRule.ISI
    return RateRule(s.static_estimator.value)


def csr_frames(
    spikes: np.ndarray, centers: Sequence[int], s: CsrSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR frames at several indices of one window.

    Parameters
    ----------
    spikes : ndarray (n, H, W) uint8 0/1
        Upright spike frames.
    centers : sequence of int
        Indices into ``spikes`` of the output steps.
    s : CsrSettings
        The coarse parameters (:data:`CSR_PARAMS`; CFSR's: :func:`tfi_dynamic`).

    Returns
    -------
    rates : ndarray (K, H, W) float32
        CSR rate, spikes per step in [0, 1].
    masks : ndarray (K, H, W) bool
        Coarse dynamic masks (Eq. 6).
    tfp : ndarray (K, H, W) float32
        The static estimates (TFP, Eq. 4, or ``isi``) the static region used, before the
        ATSR scale.
    """
    cs = [int(c) for c in centers]
    if uses_steady(s):
        return _steady_frames(spikes, cs, s)
    masks = coarse_masks(spikes, cs, s.T, s.theta)
    rates = np.empty(masks.shape, np.float32)
    tfps = np.empty(masks.shape, np.float32)
    # TFI only where a frame has dynamic pixels, all of them from one scan per pixel
    need = [k for k in range(len(cs)) if masks[k].any()]
    tfis = tfi_rates(spikes, [cs[k] for k in need], max_isi=s.max_isi)
    tfi_of = dict(zip(need, tfis, strict=True))
    for k, c in enumerate(cs):
        tfp = static_rate(
            spikes,
            c,
            window=static_length(s),
            mode=s.tfp_mode,
            estimator=span_estimator(s),
            max_isi=s.max_isi,
            tfi=tfi_of.get(k),
        )
        tfps[k] = tfp
        if k in tfi_of:
            rates[k] = atsr_fuse(tfi_of[k], tfp, masks[k])[0]
        else:
            rates[k] = np.clip(tfp, 0.0, 1.0)
    return rates, masks, tfps


def _steady_frames(
    spikes: np.ndarray, cs: Sequence[int], s: CsrSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`csr_frames` when a steady rule is on (:func:`csr_steady`)."""
    src = PackedWindow.from_frames(spikes)
    h, w = spikes.shape[1:]
    rates = np.empty((len(cs), h, w), np.float32)
    masks = np.empty((len(cs), h, w), bool)
    tfps = np.empty((len(cs), h, w), np.float32)
    for k, c in enumerate(cs):
        rates[k], masks[k], tfps[k] = csr_steady(
            src,
            c,
            s,
            coarse=lambda c=c: coarse_masks(spikes, [c], s.T, s.theta)[0],
            tfp=lambda c=c: tfp_rate(spikes, c, window=static_length(s), mode=s.tfp_mode),
        )
    return rates, masks, tfps


@dataclass(frozen=True)
class Steady:
    """What the steady rules read around t (:func:`steady_parts`)."""

    mask: np.ndarray | None  #: steady coarse mask, None under ``distinction = isi_set``
    isi: np.ndarray  #: TFI interval at t, steps, int32 (H, W)
    noise: float  #: the frame's noise level (median interval spread)
    static: np.ndarray | None  #: span rule over the static span (``isi``/``steady`` only)
    dynamic: np.ndarray | None  #: span rule over ``dynamic_span`` (``dynamic_estimator = steady``)


def steady_parts(
    src: PackedWindow,
    center: int,
    s: CsrSettings,
    *,
    words=None,
    static: bool = True,
    active: np.ndarray | None = None,
) -> Steady:
    """One read of every pixel's words around t
    (:func:`cfsr.methods.cfsr.steady_distinction.steadiness`): the steady coarse mask, the TFI
    interval at t, the noise level and the span rules the parameters ask for
    (``static=False``: the caller has the static span rule already;
    ``active``: the pixels outside static tiles, the others' spread taken as 0)."""
    n = src.n
    spans = []
    want_static = static and span_estimator(s) is RateRule.ISI
    want_dyn = s.dynamic_estimator is DynamicEstimator.STEADY
    if want_static:
        spans.append(tfp_span(center, n, static_length(s), s.tfp_mode))
    if want_dyn:
        spans.append(tfp_span(center, n, s.dynamic_span, TfpMode.CENTRED))
    spread, isi, rates = steadiness(
        src,
        center,
        radius=s.steady_radius,
        max_isi=s.max_isi,
        spans=tuple(spans),
        words=words,
        active=active,
    )
    noise = noise_level(spread)
    mask = None
    if s.distinction is Distinction.STEADY:
        mask = steady_mask(
            spread,
            tol=s.steady_tol,
            noise=noise,
            noise_factor=s.steady_noise,
            close_size=s.coarse_close,
        )
    return Steady(
        mask,
        isi,
        noise,
        rates[0] if want_static else None,
        rates[-1] if want_dyn else None,
    )


def static_checked(
    tfp: np.ndarray, isi: np.ndarray, noise: float, s: CoarseSettings
) -> np.ndarray:
    """The static estimate under ``static_estimator``: ``steady`` keeps it only where the interval
    at t agrees (:func:`cfsr.methods.cfsr.steady_distinction.check_static`, tolerance raised to the
    noise level); ``isi`` and ``tfp`` as they are."""
    if s.static_estimator is not StaticEstimator.STEADY:
        return tfp
    return check_static(tfp, isi, match=steady_match(s, noise))


def steady_match(s: CoarseSettings, noise: float) -> float:
    """The check's relative tolerance: ``steady_match``, raised to ``steady_noise`` times the
    frame's noise level (as the coarse mask's tolerance: a noisy steady pixel's interval at t
    strays from its mean by the same relative amount as its intervals spread)."""
    return max(s.steady_match, s.steady_noise * noise)


def csr_steady(
    src: PackedWindow,
    center: int,
    s: CsrSettings,
    *,
    coarse: Callable[[], np.ndarray],
    tfp: Callable[[], np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One CSR frame when a steady rule is on: Eq. 7 with the checked static estimate and,
    on the dynamic region, the TFI or (``dynamic_estimator = steady``) the checked span rule
    over ``dynamic_span`` centred steps. ``coarse()`` gives the Eq. 5-6 mask (used under
    ``distinction = isi_set``), ``tfp()`` the window count (``static_estimator = tfp``).
    Returns the rate, the coarse mask and the static estimate."""
    st = steady_parts(src, center, s)
    mask = coarse() if st.mask is None else st.mask
    tfi = (1.0 / st.isi).astype(np.float32)
    static = static_checked(tfp() if st.static is None else st.static, st.isi, st.noise, s)
    if not mask.any():
        return np.clip(static, 0.0, 1.0), mask, static
    dyn = tfi
    if st.dynamic is not None:
        dyn = check_static(st.dynamic, st.isi, match=steady_match(s, st.noise))
    return atsr_fuse(dyn, static, mask, tfi=tfi)[0], mask, static


def _compute(window: np.ndarray, center: int, start: int, s: CsrSettings) -> Output:
    rates, masks, _ = csr_frames(window, [center], s)
    return Output(rates[0], {"coarse": masks[0]})


def csr_frame_packed(
    packed: np.ndarray, layout: Any, center: int, s: CsrSettings
) -> tuple[np.ndarray, np.ndarray]:
    """One CSR frame and its coarse mask from packed frames: the same numbers as
    :func:`csr_frames`, without unpacking the window (the live path's budget)."""
    if uses_steady(s):
        rate, mask, _ = csr_steady(
            PackedWindow.from_packed(packed, layout),
            center,
            s,
            coarse=lambda: distinct_isi_counts_packed(packed, layout, center, s.T)
            >= s.theta,
            tfp=lambda: tfp_rate_packed(
                packed, layout, center, window=static_length(s), mode=s.tfp_mode
            ),
        )
        return rate, mask
    mask = distinct_isi_counts_packed(packed, layout, center, s.T) >= s.theta
    tfi = tfi_rate_packed(packed, layout, center, max_isi=s.max_isi) if mask.any() else None
    tfp = static_rate_packed(
        packed,
        layout,
        center,
        window=static_length(s),
        mode=s.tfp_mode,
        estimator=span_estimator(s),
        max_isi=s.max_isi,
        tfi=tfi,
    )
    if tfi is None:
        return np.clip(tfp, 0.0, 1.0), mask
    return atsr_fuse(tfi, tfp, mask)[0], mask


def _compute_packed(packed, layout, center: int, start: int, s: CsrSettings) -> Output:
    rate, mask = csr_frame_packed(packed, layout, center, s)
    return Output(rate, {"coarse": mask})


register(
    Method(
        name="csr",
        summary="Coarse CFSR: ISI-set distinction, TFI on dynamic / TFP on static, ATSR fusion",
        params=dict(CSR_ONLY_PARAMS),
        window=csr_window,
        compute=_compute,
        compute_packed=_compute_packed,
        masks=("coarse",),
        presets={k: {**v, "dynamic_estimator": "tfi"} for k, v in CSR_PRESETS.items()},
        reference="CFSR paper Eq. 3-7 (coarse stage)",
        settings=CsrSettings,
    )
)
