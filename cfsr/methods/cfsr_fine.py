"""CFSR: coarse-to-fine reconstruction (CFSR paper Eq. 3-14), registered as ``cfsr``.

Pipeline for output step t (every stage a pure function of the spike window; the readings and
the calibration of every default are in docs/methods.md):

1. **CSR history** (:mod:`cfsr.methods.csr`): CSR frames at ``t - k * mog_stride`` for
   ``k = mog_frames - 1 .. 0`` (oldest first, the last one is t), their static region a TFP of
   ``mog_window`` steps. The coarse mask at t (Eq. 6) is the ``coarse`` output.
2. **MOG** (:mod:`cfsr.methods.mog`, Eq. 8-9): a fresh ``bgsegm`` MOG model learns the history
   on the 8-bit scale (``mog_gain``: rate shown as 255, 0 = the 99.5th percentile of the CSR
   frame at t), gives the background B, and ``|f_t - B| >= phi0`` marks moving objects (phi0
   kept at least two count quanta of the MOG frames, so dark scenes do not mark noise).
3. **DAISI** (:mod:`cfsr.methods.daisi`, Eq. 10-14): adjacent-ISI log ratios ``>= phi`` within
   ``daisi_span`` steps of t mark the edges of moving objects.
4. **Fine mask**: the union of the coarse mask, the MOG objects and the DAISI edges, closed with
   a ``close_size`` square, holes filled, components under ``min_area`` pixels dropped, grown
   by ``dilate`` pixels. This is the ``fine`` output ("the edges refine the object mask").
5. **Fine reconstruction** (:mod:`cfsr.methods.patchmatch`): TFI at t and at ``t +- pm_step*i``,
   ``i = 1..pm_count`` (clipped to the window), computed only on the bounding box of the fine
   mask (plus search margin); PatchMatch on a guide (TFA over ``pm_guide`` intervals, Gaussian
   ``pm_sigma``) matches the 6 x 6 patch of every fine-mask pixel in each frame, and the raw
   TFI rates at the matches are averaged with the reference.
6. **ATSR** (:mod:`cfsr.methods.atsr`, Eq. 7): the refined dynamic region is fused with the
   static TFP (``tfp_window``) scaled by mean TFI / mean TFP over the static region.

"Skip what the scene does not need": an empty fine mask skips the TFI frames and PatchMatch
entirely (the output is then the plain TFP), and PatchMatch works only on the fine mask's
pixels, with TFI frames computed on its bounding box.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from cfsr.methods.atsr import atsr_fuse
from cfsr.methods.csr import CSR_PARAMS, CSR_PRESETS, csr_frames, csr_window
from cfsr.methods.daisi import daisi_strength
from cfsr.methods.mog import mog_background, mog_objects, to_u8
from cfsr.methods.patchmatch import patchmatch_fuse
from cfsr.methods.registry import Method, Output, Param, register
from cfsr.methods.tfa import adaptive_rates
from cfsr.methods.tfi import tfi_rate, tfi_rates
from cfsr.methods.tfp import tfp_rate

__all__ = ["fine_mask", "fine_stage", "cfsr_window"]

FINE_PARAMS: dict[str, Param] = {
    "mog_frames": Param(12, "frames", "CSR frames K fed to MOG, ending at t", minimum=1),
    "mog_stride": Param(32, "steps", "steps between consecutive MOG frames", minimum=1),
    "mog_window": Param(64, "steps", "TFP window w of the CSR frames fed to MOG", minimum=1),
    "mog_history": Param(0, "frames", "MOG history length (0: mog_frames)", minimum=0),
    "mog_mixtures": Param(3, "", "Gaussians per pixel in MOG", minimum=1, maximum=8),
    "mog_ratio": Param(0.7, "", "MOG background ratio", minimum=0.0, maximum=1.0),
    "mog_noise": Param(0.0, "8-bit levels", "MOG noise sigma (0: OpenCV default 15)", minimum=0),
    "mog_gain": Param(0.0, "spikes/step", "rate shown as 255 for MOG (0: auto)", minimum=0),
    "phi0": Param(20.0, "8-bit levels", "|f - B| threshold for moving objects (Eq. 9)", minimum=0),
    "phi": Param(0.75, "log ratio", "DAISI edge threshold, natural log (Eq. 14)", minimum=0),
    "daisi_span": Param(5, "steps", "DAISI evaluated within t +- span (0: at t)", minimum=0),
    "close_size": Param(9, "pixels", "square closing of the fine mask (0/1: none)", minimum=0),
    "min_area": Param(16, "pixels", "drop fine-mask components smaller than this", minimum=0),
    "dilate": Param(2, "pixels", "grow the fine mask by this radius (safety margin)", minimum=0),
    "pm_step": Param(3, "steps", "spacing of PatchMatch frames t +- step*i", minimum=1),
    "pm_count": Param(16, "frames", "PatchMatch frames on each side of t", minimum=0),
    "pm_patch": Param(6, "pixels", "patch side", minimum=1, maximum=16),
    "pm_iters": Param(2, "", "PatchMatch scans", minimum=0, maximum=16),
    "pm_radius": Param(16, "pixels", "largest random-search radius", minimum=0),
    "pm_guide": Param(
        3, "intervals", "guide = TFA over this many intervals (0: the TFI)", minimum=0, maximum=64
    ),
    "pm_sigma": Param(1.0, "pixels", "Gaussian sigma applied to the guide (0: none)", minimum=0),
    "pm_h": Param(
        0.0, "spikes/step", "match weight scale exp(-SSD/(P^2 h^2)); 0: average", minimum=0
    ),
}

FINE_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        **CSR_PRESETS["paper"],
        "phi0": 50.0,
        "phi": 4.0,
        "daisi_span": 0,
        "pm_step": 5,
        "pm_count": 10,
        "pm_guide": 0,
        "pm_sigma": 0.0,
    },
    "simulated": {**CSR_PRESETS["simulated"]},
}


def cfsr_window(p: Mapping[str, Any]) -> tuple[int, int]:
    """Steps before/after t that one CFSR frame needs."""
    cb, ca = csr_window(p)  # the static TFP at t
    hb, ha = csr_window({**p, "tfp_window": p["mog_window"]})  # each MOG history frame
    pm = p["pm_step"] * p["pm_count"]
    reach = p["max_isi"]
    before = max(
        cb, hb + (p["mog_frames"] - 1) * p["mog_stride"], pm + reach, p["daisi_span"] + reach
    )
    after = max(ca, ha, pm + reach, p["daisi_span"] + reach)
    return before, after


def fine_mask(
    coarse: np.ndarray,
    objects: np.ndarray,
    edges: np.ndarray,
    *,
    close_size: int = 9,
    min_area: int = 16,
    dilate: int = 0,
) -> np.ndarray:
    """Fine dynamic mask: union of the cues, closed, holes filled, small components dropped."""
    from scipy import ndimage as ndi

    m = np.asarray(coarse, bool) | np.asarray(objects, bool) | np.asarray(edges, bool)
    if not m.any():
        return m
    if close_size > 1:
        import cv2

        k = np.ones((int(close_size), int(close_size)), np.uint8)
        m = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_CLOSE, k) > 0
    m = ndi.binary_fill_holes(m)
    if min_area > 1:
        lab, n = ndi.label(m)
        if n:
            sizes = np.bincount(lab.ravel())
            keep = sizes >= int(min_area)
            keep[0] = False
            m = keep[lab]
    if dilate > 0 and m.any():
        import cv2

        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(dilate) + 1,) * 2)
        m = cv2.dilate(m.astype(np.uint8), k) > 0
    return m


def _guides(spikes: np.ndarray, centers, tfi: np.ndarray, p: Mapping[str, Any]) -> np.ndarray:
    """Matching guides: TFA over ``pm_guide`` intervals (or the TFI), Gaussian-smoothed.

    TFA adapts its integration to the pixel's own firing, so the guide is equally clean in
    bright and dark scenes (a fixed-window TFP guide is mostly 0 or 1/w in low light).
    """
    if p["pm_guide"] <= 0:
        g = np.array(tfi, np.float32)
    else:
        g = adaptive_rates(spikes, centers, threshold=p["pm_guide"], max_window=p["max_isi"])
    if p["pm_sigma"] > 0:
        import cv2

        for k in range(g.shape[0]):
            g[k] = cv2.GaussianBlur(g[k], (0, 0), float(p["pm_sigma"]))
    return g


def fine_stage(
    window: np.ndarray, center: int, seed: int, p: Mapping[str, Any]
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The whole CFSR pipeline on one window; returns ``(rate, {"coarse", "fine"})``."""
    n, h, w = window.shape
    # 1. CSR history, oldest first; frames before the window start are dropped
    ks = range(p["mog_frames"] - 1, -1, -1)
    centers = [center - k * p["mog_stride"] for k in ks if center - k * p["mog_stride"] >= 0]
    rates, coarse_all, _ = csr_frames(window, centers, {**p, "tfp_window": p["mog_window"]})
    coarse = coarse_all[-1]
    # 2. MOG background and moving objects (Eq. 8-9)
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
    _, background = mog_background(
        u8,
        history=hist,
        nmixtures=p["mog_mixtures"],
        background_ratio=p["mog_ratio"],
        noise_sigma=p["mog_noise"],
    )
    objects = mog_objects(u8[-1], background, phi0)
    # 3. DAISI edges (Eq. 10-14)
    edges = daisi_strength(window, center, span=p["daisi_span"], max_isi=p["max_isi"]) >= p["phi"]
    # 4. fine mask
    fine = fine_mask(
        coarse,
        objects,
        edges,
        close_size=p["close_size"],
        min_area=p["min_area"],
        dilate=p["dilate"],
    )
    tfp = tfp_rate(window, center, window=p["tfp_window"], mode=p["tfp_mode"])
    masks = {"coarse": coarse, "fine": fine}
    if not fine.any():
        return np.clip(tfp, 0.0, 1.0).astype(np.float32), masks
    # 5. TFI refined by PatchMatch on the fine region, on its bounding box only
    ys, xs = np.nonzero(fine)
    margin = p["pm_radius"] + p["pm_patch"] + int(3 * p["pm_sigma"]) + 1
    y0, y1 = max(0, ys.min() - margin), min(h, ys.max() + margin + 1)
    x0, x1 = max(0, xs.min() - margin), min(w, xs.max() + margin + 1)
    crop = np.ascontiguousarray(window[:, y0:y1, x0:x1])
    tfi_full = tfi_rate(window, center, max_isi=p["max_isi"])
    offs = [p["pm_step"] * i for i in range(1, p["pm_count"] + 1)]
    # the reference t first, then t -+ step*i inside the window
    tcs = [center] + [c for s in offs for c in (center - s, center + s) if 0 <= c < n]
    raw = tfi_rates(crop, tcs, max_isi=p["max_isi"])
    guides = _guides(crop, tcs, raw, p)
    refined = patchmatch_fuse(
        raw[0],
        guides[0],
        raw[1:],
        guides[1:],
        fine[y0:y1, x0:x1],
        patch=p["pm_patch"],
        iters=p["pm_iters"],
        max_radius=p["pm_radius"],
        h=p["pm_h"],
        seed=seed,
    )
    dyn = tfi_full.copy()
    dyn[y0:y1, x0:x1] = refined
    # 6. ATSR (Eq. 7)
    rate, _ = atsr_fuse(dyn, tfp, fine, tfi=tfi_full)
    return rate, masks


def _compute(window: np.ndarray, center: int, start: int, p: Mapping[str, Any]) -> Output:
    rate, masks = fine_stage(window, center, int(start) + int(center), p)
    return Output(rate, masks)


register(
    Method(
        name="cfsr",
        summary="Coarse-to-fine CFSR: CSR + MOG/DAISI fine mask + PatchMatch-refined TFI, ATSR",
        params={**CSR_PARAMS, **FINE_PARAMS},
        window=cfsr_window,
        compute=_compute,
        masks=("coarse", "fine"),
        presets=FINE_PRESETS,
        reference="CFSR paper Eq. 3-14 (coarse and fine stages)",
    )
)
