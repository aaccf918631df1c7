"""CSR: coarse region-adaptive reconstruction (CFSR paper Eq. 5-7).

1. Coarse distinction (Eq. 5-6, :mod:`cfsr.methods.distinction`): a pixel is dynamic when the
   ISIs inside the ``T`` steps before t take at least ``theta`` distinct values.
2. TFI (Eq. 3) on dynamic pixels, a static estimate on static ones: the paper's TFP (Eq. 4,
   window ``tfp_window``) with ``static_estimator=tfp``, or with ``isi`` the span's spike count
   less one over its first-to-last spike distance (:func:`cfsr.methods.tfp.span_rate`, exact
   for a steady pixel where the window count is off by up to one spike), over ``static_span``
   steps (0: ``tfp_window``) placed like the TFP window; a pixel with fewer than two spikes
   in the span takes the TFI (:func:`cfsr.methods.tfp.static_rate`).
3. ATSR (Eq. 7, :mod:`cfsr.methods.atsr`): the static estimate is scaled by mean TFI / mean
   static estimate over the static region and pasted with the dynamic TFI.

A window with no dynamic pixel needs only TFP: the TFI stage is skipped and the scale is 1
(there is no dynamic region whose brightness the static one must match).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cfsr.methods.atsr import atsr_fuse
from cfsr.methods.distinction import coarse_masks, distinct_isi_counts_packed
from cfsr.methods.registry import MAX_WINDOW_STEPS, Method, Output, Param, register
from cfsr.methods.tfi import tfi_rate_packed, tfi_rates
from cfsr.methods.tfp import STATIC_ESTIMATORS, static_rate, static_rate_packed

__all__ = ["csr_frames", "csr_frame_packed", "CSR_PARAMS", "csr_window", "static_length"]

#: Parameters shared by ``csr`` and ``cfsr`` (defaults calibrated on the simulator, see
#: docs/methods.md; the paper's values are in the ``paper`` preset). Window-like parameters
#: reach at most half the ring's limit each, so that any combination fits (before + after).
CSR_PARAMS: dict[str, Param] = {
    "T": Param(
        300,
        "steps",
        "coarse distinction window T before t (Eq. 5)",
        minimum=2,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    # distinct ISIs in T steps sum to at most T, so there are fewer than sqrt(2 T) <= 283
    "theta": Param(
        8,
        "ISI values",
        "distinct ISI values in T that make a pixel dynamic (Eq. 6)",
        minimum=1,
        maximum=1000,
    ),
    "tfp_window": Param(
        160,
        "steps",
        "TFP window w for the static region (Eq. 4)",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "tfp_mode": Param(
        "trailing", "", "TFP window: trailing (Eq. 4) or centred", choices=("trailing", "centred")
    ),
    "max_isi": Param(
        200,
        "steps",
        "TFI search range each side of t (Eq. 3)",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    # isi by default: on the simulator and REDS it is at least as good as TFP on every scene,
    # whole frame and motion region (docs/methods.md); the paper's TFP stays in the presets
    "static_estimator": Param(
        "isi",
        "",
        "static-region rate: tfp (Eq. 4, window count / w) or isi ((spikes - 1) / first-to-last "
        "spike steps over static_span; the TFI below two spikes)",
        choices=STATIC_ESTIMATORS,
    ),
    # 0 keeps the TFP window; a longer span sees more intervals (more precise for dark static
    # pixels, more smear on a mover the distinction misses)
    "static_span": Param(
        0,
        "steps",
        "isi: span of the static estimate, placed as tfp_mode (0: tfp_window)",
        minimum=0,
        maximum=MAX_WINDOW_STEPS // 2,
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
    },
    "simulated": {
        "T": 300,
        "theta": 10,
        "tfp_window": 30,
        "tfp_mode": "trailing",
        "static_estimator": "tfp",
        "static_span": 0,
    },
}

#: ``csr`` alone has no fine stage to catch the moving pixels the coarse test misses (bright
#: moving texture has too few distinct ISIs), so its static TFP defaults to a shorter, centred
#: window that smears a missed mover less (docs/methods.md, calibration).
CSR_ONLY_PARAMS: dict[str, Param] = {
    **CSR_PARAMS,
    "tfp_window": Param(
        32,
        "steps",
        "TFP window w for the static region (Eq. 4)",
        minimum=1,
        maximum=MAX_WINDOW_STEPS // 2,
    ),
    "tfp_mode": Param(
        "centred", "", "TFP window: trailing (Eq. 4) or centred", choices=("trailing", "centred")
    ),
}


def static_length(p: Mapping[str, Any]) -> int:
    """Steps of the static estimate's span: ``static_span`` for ``isi`` when set, else
    ``tfp_window`` (parameter sets without the keys read as the paper's TFP)."""
    if p.get("static_estimator", "tfp") == "isi" and int(p.get("static_span", 0)) > 0:
        return int(p["static_span"])
    return int(p["tfp_window"])


def csr_window(p: Mapping[str, Any]) -> tuple[int, int]:
    """Steps before/after t that one CSR frame needs."""
    w = static_length(p)
    if p["tfp_mode"] == "trailing":
        tb, ta = w - 1, 0
    else:
        tb, ta = w // 2, w - w // 2 - 1
    return max(p["T"] - 1, tb, p["max_isi"]), max(ta, p["max_isi"])


def csr_frames(
    spikes: np.ndarray, centers: Sequence[int], p: Mapping[str, Any]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR frames at several indices of one window.

    Parameters
    ----------
    spikes : ndarray (n, H, W) uint8 0/1
        Upright spike frames.
    centers : sequence of int
        Indices into ``spikes`` of the output steps.
    p : mapping
        ``T``, ``theta``, ``tfp_window``, ``tfp_mode``, ``max_isi`` (see :data:`CSR_PARAMS`).

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
    masks = coarse_masks(spikes, cs, p["T"], p["theta"])
    rates = np.empty(masks.shape, np.float32)
    tfps = np.empty(masks.shape, np.float32)
    # TFI only where a frame has dynamic pixels, all of them from one scan per pixel
    need = [k for k in range(len(cs)) if masks[k].any()]
    tfis = tfi_rates(spikes, [cs[k] for k in need], max_isi=p["max_isi"])
    tfi_of = dict(zip(need, tfis, strict=True))
    for k, c in enumerate(cs):
        tfp = static_rate(
            spikes,
            c,
            window=static_length(p),
            mode=p["tfp_mode"],
            estimator=p.get("static_estimator", "tfp"),
            max_isi=p["max_isi"],
            tfi=tfi_of.get(k),
        )
        tfps[k] = tfp
        if k in tfi_of:
            rates[k] = atsr_fuse(tfi_of[k], tfp, masks[k])[0]
        else:
            rates[k] = np.clip(tfp, 0.0, 1.0)
    return rates, masks, tfps


def _compute(window: np.ndarray, center: int, start: int, p: Mapping[str, Any]) -> Output:
    rates, masks, _ = csr_frames(window, [center], p)
    return Output(rates[0], {"coarse": masks[0]})


def csr_frame_packed(
    packed: np.ndarray, layout: Any, center: int, p: Mapping[str, Any]
) -> tuple[np.ndarray, np.ndarray]:
    """One CSR frame and its coarse mask from packed frames: the same numbers as
    :func:`csr_frames`, without unpacking the window (the live path's budget)."""
    mask = distinct_isi_counts_packed(packed, layout, center, p["T"]) >= int(p["theta"])
    tfi = tfi_rate_packed(packed, layout, center, max_isi=p["max_isi"]) if mask.any() else None
    tfp = static_rate_packed(
        packed,
        layout,
        center,
        window=static_length(p),
        mode=p["tfp_mode"],
        estimator=p.get("static_estimator", "tfp"),
        max_isi=p["max_isi"],
        tfi=tfi,
    )
    if tfi is None:
        return np.clip(tfp, 0.0, 1.0), mask
    return atsr_fuse(tfi, tfp, mask)[0], mask


def _compute_packed(packed, layout, center: int, start: int, p: Mapping[str, Any]) -> Output:
    rate, mask = csr_frame_packed(packed, layout, center, p)
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
        presets=CSR_PRESETS,
        reference="CFSR paper Eq. 3-7 (coarse stage)",
    )
)
