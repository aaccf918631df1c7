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

"Skip what the scene does not need" (``adaptive``, default True): an empty fine mask skips the
TFI frames and PatchMatch entirely (the output is then the plain TFP), MOG runs only where the
8-bit history varies by phi0 or more, and PatchMatch works only on the fine mask's pixels, with
TFI frames and guides computed on its bounding box. ``adaptive=False`` is the always-full
pipeline (every stage on the whole frame, same output rule) that the benchmark compares with.

Speed: every per-pixel quantity above is a function of the pixel's spike times, so two fused
scans gather them once per pixel straight from the packed frames (``compute_packed``; no
unpacking) and compute, with the same numbers as the stand-alone kernels: the whole-frame
history scan (steps 1 and 3, the TFP and TFI at t) and the PatchMatch-region scan (step 5).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numba import njit, prange

from cfsr.methods.atsr import atsr_fuse
from cfsr.methods.csr import CSR_PARAMS, CSR_PRESETS, csr_window
from cfsr.methods.daisi import daisi_from_times
from cfsr.methods.mog import mog_background, mog_objects, to_u8
from cfsr.methods.patchmatch import patchmatch_fuse
from cfsr.methods.registry import Method, Output, Param, register
from cfsr.methods.tfa import grow_span
from cfsr.methods.tfp import tfp_span

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
    "adaptive": Param(
        True,
        "",
        "skip what the scene does not need (False: every stage on the whole frame)",
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


# --------------------------------------------------------------------------- fused scans
#
# Every per-pixel quantity of the pipeline is a function of the pixel's spike times. The
# stand-alone kernels (coarse distinction, TFI at many centers, TFP, DAISI, TFA) each gather
# those times again from the unpacked window, which costs more than the arithmetic; the two
# scans below gather them once per pixel and compute, with the same rules and the same
# numbers as those kernels (tests/test_methods_adaptive.py checks equality):
#
# * :func:`_history_kernel` (whole frame): the CSR history of MOG (distinct-ISI counts, TFI and
#   TFP counts at the K history steps), DAISI at t and the static TFP count at t;
# * :func:`_pm_kernel` (only the pixels PatchMatch can read): TFI and TFA at the PatchMatch
#   steps.


_CHUNK = 64  # pixels per column chunk of the scans (a multiple of 8: byte-aligned reads)


class _Spikes:
    """A window as packed frames (``.dat`` layout) with the geometry the scans need.

    ``compute_packed`` wraps the buffered bytes as they are (no unpacking: 900 steps of
    400 x 250 unpack in ~50 ms, more than a whole scan); ``compute`` packs its window.
    """

    def __init__(self, packed, height, width, stored_width, flipud, fliplr):
        self.packed = np.ascontiguousarray(packed, dtype=np.uint8)
        self.n = self.packed.shape[0]
        self.h = int(height)
        self.w = int(width)
        # stored bit of image pixel (y, x): row_of(y) * stored_width + x0 + xs * x
        self.geo = np.array(
            [
                stored_width,
                height,
                int(bool(flipud)),
                width - 1 if fliplr else 0,
                -1 if fliplr else 1,
            ],
            np.int64,
        )

    @classmethod
    def from_frames(cls, window: np.ndarray) -> _Spikes:
        from cfsr._bits import pack_frames

        n, h, w = window.shape
        return cls(pack_frames(window), h, w, w, True, False)

    @classmethod
    def from_packed(cls, packed: np.ndarray, layout: Any) -> _Spikes:
        return cls(
            packed, layout.height, layout.width, layout.stored_width, layout.flipud, layout.fliplr
        )


@njit(cache=True, inline="always")
def _gather_row(packed, geo, lo, hi, y, x0, x1, times, ns):  # pragma: no cover - numba
    """Spike steps in ``[lo, hi)`` of image pixels ``x0 .. x1-1`` of row ``y``, read from
    packed frames: ``times[x - x0, :ns[x - x0]]``.

    Reads the window in memory order (frame by frame, one stored row), without branches.
    """
    sw, height, flipud, xo, xs = geo[0], geo[1], geo[2], geo[3], geo[4]
    yy = np.int64(y)
    count = np.int64(x1 - x0)
    # stored bits of the row's pixels x0 .. x1-1 in stored (memory) order
    if xs > 0:
        sc0 = xo + np.int64(x0)
    else:
        sc0 = xo - np.int64(x1 - 1)
    q0 = ((height - 1 - yy) if flipud else yy) * sw + sc0
    aligned = (q0 & 7) == 0
    nbytes = (count + 7) >> 3
    bits = np.empty(nbytes * 8, np.uint8)  # the row's bits of one frame, stored order
    for k in range(count):
        ns[k] = 0
    for t in range(lo, hi):
        frame = packed[t]
        if aligned:
            b0 = q0 >> 3
            for k in range(nbytes):
                v = frame[b0 + k]
                for b in range(8):
                    bits[8 * k + b] = (v >> b) & 1
        else:
            for k in range(count):
                q = q0 + k
                bits[k] = (frame[q >> 3] >> (q & 7)) & 1
        # branch-free scatter: always write, advance only on a spike
        if xs > 0:
            for k in range(count):
                times[k, ns[k]] = t
                ns[k] += bits[k]
        else:
            for k in range(count):
                j = count - 1 - k
                times[j, ns[j]] = t
                ns[j] += bits[k]


@njit(cache=True, inline="always")
def _isi_from_times(tv, ns, ip, a, b):  # pragma: no cover - numba
    """TFI interval at a step c with search range ``[a, b)`` (the rule of ``tfi._isi_one``);
    ``ip`` indexes the last spike ``<= c`` (-1: none)."""
    i_n = ip + 1
    p_ok = ip >= 0 and tv[ip] >= a
    n_ok = i_n < ns and tv[i_n] < b
    if p_ok and n_ok:
        return tv[i_n] - tv[ip]
    if p_ok:
        bound = b - tv[ip]
        if ip >= 1 and tv[ip - 1] >= a:
            return max(bound, tv[ip] - tv[ip - 1])
        return bound
    if n_ok:
        bound = tv[i_n] - a + 1
        if i_n + 1 < ns and tv[i_n + 1] < b:
            return max(bound, tv[i_n + 1] - tv[i_n])
        return bound
    return b - a + 1


@njit(parallel=True, cache=True)
def _history_kernel(
    packed,
    geo,
    lo,
    hi,
    ends,
    span,
    m,
    ta,
    tb,
    c,
    dspan,
    d_lo,
    d_hi,
    pa,
    pb,
    counts,
    isi,
    cnt,
    daisi,
    pcnt,
):  # pragma: no cover - numba
    n = packed.shape[0]
    h, w = counts.shape[1:]
    k_count = ends.shape[0]
    length = hi - lo
    for y in prange(h):
        # columns in chunks: the chunk's spike times stay in cache between gather and use
        times = np.empty((_CHUNK, length + 1), np.int32)
        ns_row = np.empty(_CHUNK, np.int64)
        hist = np.zeros(span + 1, np.int32)
        for cx in range(0, w, _CHUNK):
            cx1 = min(w, cx + _CHUNK)
            _gather_row(packed, geo, lo, hi, y, cx, cx1, times, ns_row)
            for x in range(cx, cx1):
                tv = times[x - cx]
                ns = ns_row[x - cx]
                # distinct ISI values in (e - span, e] (sliding histogram, distinction.py)
                a = 0
                b = 0
                distinct = 0
                for k in range(k_count):
                    e = ends[k]
                    s = e - span + 1
                    # an ISI longer than span never lies inside one window: not counted, so
                    # not removed either; the count itself is branch-free
                    while b < ns and tv[b] <= e:
                        if b > a:
                            d = tv[b] - tv[b - 1]
                            if d <= span:
                                distinct += hist[d] == 0
                                hist[d] += 1
                        b += 1
                    while a < b and tv[a] < s:
                        if a + 1 < b:
                            d = tv[a + 1] - tv[a]
                            if d <= span:
                                hist[d] -= 1
                                distinct -= hist[d] == 0
                        a += 1
                    counts[k, y, x] = distinct
                while a + 1 < b:
                    d = tv[a + 1] - tv[a]
                    if d <= span:
                        hist[d] = 0
                    a += 1
                # TFI and TFP counts at the (ascending) history steps: monotone pointers
                ip = -1
                ia = 0
                ib = 0
                for k in range(k_count):
                    e = ends[k]
                    while ip + 1 < ns and tv[ip + 1] <= e:
                        ip += 1
                    isi[k, y, x] = _isi_from_times(tv, ns, ip, max(0, e - m), min(n, e + m + 1))
                    while ia < ns and tv[ia] < ta[k]:
                        ia += 1
                    while ib < ns and tv[ib] < tb[k]:
                        ib += 1
                    cnt[k, y, x] = ib - ia
                pcnt[y, x] = np.searchsorted(tv[:ns], pb, side="left") - np.searchsorted(
                    tv[:ns], pa, side="left"
                )
                f0 = np.searchsorted(tv[:ns], d_lo, side="left")
                f1 = np.searchsorted(tv[:ns], d_hi, side="left")
                daisi[y, x] = daisi_from_times(tv[f0:f1], c - dspan, c + dspan)


@njit(parallel=True, cache=True)
def _pm_kernel(packed, geo, lo, hi, y0, x0, centers, m, thr, isi, tfa):
    # pragma: no cover - numba
    """TFI intervals and TFA rates at ``centers`` (ascending) on the crop at ``(y0, x0)``."""
    n = packed.shape[0]
    kc, ch, cw = isi.shape
    length = hi - lo
    for yy in prange(ch):
        times = np.empty((_CHUNK, length + 1), np.int32)
        ns_row = np.empty(_CHUNK, np.int64)
        for cx in range(0, cw, _CHUNK):
            cx1 = min(cw, cx + _CHUNK)
            _gather_row(packed, geo, lo, hi, y0 + yy, x0 + cx, x0 + cx1, times, ns_row)
            for x in range(cx, cx1):
                tv = times[x - cx]
                ns = ns_row[x - cx]
                ip = -1  # last spike <= cc
                f0 = 0  # first spike >= c_lo
                f1 = 0  # first spike >= c_hi
                for kk in range(kc):
                    cc = centers[kk]
                    c_lo = max(0, cc - m)
                    c_hi = min(n, cc + m + 1)
                    while ip + 1 < ns and tv[ip + 1] <= cc:
                        ip += 1
                    isi[kk, yy, x] = _isi_from_times(tv, ns, ip, c_lo, c_hi)
                    if thr <= 0:
                        continue
                    # TFA over thr intervals (the rule of tfa._adaptive_kernel, no refractory)
                    while f0 < ns and tv[f0] < c_lo:
                        f0 += 1
                    while f1 < ns and tv[f1] < c_hi:
                        f1 += 1
                    if f1 - f0 < 2:
                        tfa[kk, yy, x] = 1.0 / (c_hi - c_lo + 1)
                        continue
                    a, b = grow_span(tv, f0, f1, ip, cc, thr)
                    tfa[kk, yy, x] = (b - a) / (tv[b] - tv[a])


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


def _history(src: _Spikes, center: int, p: Mapping[str, Any]) -> dict[str, Any]:
    """One whole-frame scan: the CSR history of MOG, DAISI at t, TFI and TFP at t.

    The same numbers as ``csr_frames`` (history frames' static TFP over ``mog_window`` steps),
    ``daisi_strength``, ``tfi_rate`` and ``tfp_rate`` on the window.
    """
    n, h, w = src.n, src.h, src.w
    ks = range(p["mog_frames"] - 1, -1, -1)
    ends = np.array(
        [center - k * p["mog_stride"] for k in ks if center - k * p["mog_stride"] >= 0], np.int64
    )
    span, m, dspan = int(p["T"]), int(p["max_isi"]), int(p["daisi_span"])
    spans = [tfp_span(int(e), n, p["mog_window"], p["tfp_mode"]) for e in ends]
    ta = np.array([a for a, _ in spans], np.int64)
    tb = np.array([b for _, b in spans], np.int64)
    pa, pb = tfp_span(center, n, p["tfp_window"], p["tfp_mode"])
    d_lo, d_hi = max(0, center - dspan - m), min(n, center + dspan + m + 1)
    lo = max(0, min(int(ends[0]) - span + 1, int(ends[0]) - m, int(ta.min()), pa, d_lo))
    hi = min(n, max(int(ends[-1]) + m + 1, int(tb.max()), pb, d_hi))
    k = ends.size
    counts = np.empty((k, h, w), np.int32)
    isi = np.empty((k, h, w), np.int32)
    cnt = np.empty((k, h, w), np.int32)
    daisi = np.empty((h, w), np.float32)
    pcnt = np.empty((h, w), np.int32)
    _history_kernel(
        src.packed,
        src.geo,
        lo,
        hi,
        ends,
        span,
        m,
        ta,
        tb,
        int(center),
        dspan,
        d_lo,
        d_hi,
        pa,
        pb,
        counts,
        isi,
        cnt,
        daisi,
        pcnt,
    )
    masks = counts >= int(p["theta"])
    rates = np.empty((k, h, w), np.float32)
    for j in range(k):
        tfp_j = (cnt[j] / np.float32(max(1, tb[j] - ta[j]))).astype(np.float32)
        if masks[j].any():  # TFI only where a frame has dynamic pixels (as csr_frames)
            rates[j] = atsr_fuse((1.0 / isi[j]).astype(np.float32), tfp_j, masks[j])[0]
        else:
            rates[j] = np.clip(tfp_j, 0.0, 1.0)
    tfp = (pcnt / np.float32(max(1, pb - pa))).astype(np.float32)
    return {
        "rates": rates,
        "coarse": masks[-1],
        "tfi": (1.0 / isi[-1]).astype(np.float32),
        "tfp": tfp,
        "daisi": daisi,
    }


def _pm_frames(
    src: _Spikes, centers, box: tuple[int, int, int, int], p: Mapping[str, Any]
) -> tuple[np.ndarray, np.ndarray]:
    """Raw TFI rates and matching guides at ``centers`` on ``box = (y0, y1, x0, x1)``.

    Guides: TFA over ``pm_guide`` intervals (or the TFI), Gaussian-smoothed. TFA adapts its
    integration to the pixel's own firing, so the guide is equally clean in bright and dark
    scenes (a fixed-window TFP guide is mostly 0 or 1/w in low light). The same numbers as
    ``tfi_rates`` and ``adaptive_rates`` on the crop.
    """
    n = src.n
    y0, y1, x0, x1 = box
    cs = np.asarray(centers, np.int64)
    order = np.argsort(cs, kind="stable")
    m = int(p["max_isi"])
    lo, hi = max(0, int(cs.min()) - m), min(n, int(cs.max()) + m + 1)
    isi = np.empty((cs.size, y1 - y0, x1 - x0), np.int32)
    tfa = np.empty(isi.shape, np.float32)
    thr = int(p["pm_guide"])
    _pm_kernel(src.packed, src.geo, lo, hi, y0, x0, cs[order], m, thr, isi, tfa)
    inv = np.empty_like(order)
    inv[order] = np.arange(order.size)
    raw = (1.0 / isi[inv]).astype(np.float32)
    g = raw.copy() if thr <= 0 else tfa[inv]
    if p["pm_sigma"] > 0:
        import cv2

        for k in range(g.shape[0]):
            g[k] = cv2.GaussianBlur(g[k], (0, 0), float(p["pm_sigma"]))
    return raw, g


def fine_stage(
    window: np.ndarray | _Spikes, center: int, seed: int, p: Mapping[str, Any]
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The whole CFSR pipeline on one window; returns ``(rate, {"coarse", "fine"})``.

    ``p["adaptive"]`` (default True) skips what the scene does not need: no fine-mask pixel ->
    the plain TFP; otherwise TFI frames and guides only on the fine mask's bounding box (plus
    the search margin) and PatchMatch only on the fine-mask pixels. ``adaptive=False`` is the
    always-full pipeline: MOG on the whole frame, TFI frames, guides and PatchMatch on every
    pixel, then the same output rule (TFP where the fine mask is empty, ATSR with the fine mask
    otherwise), so the two differ only where PatchMatch's propagation from pixels outside the
    mask changes a match.
    """
    src = window if isinstance(window, _Spikes) else _Spikes.from_frames(window)
    n, h, w = src.n, src.h, src.w
    adaptive = bool(p.get("adaptive", True))
    # 1. CSR history (oldest first; frames before the window start dropped), DAISI, TFI, TFP
    hs = _history(src, center, p)
    rates, coarse, tfp, tfi_full = hs["rates"], hs["coarse"], hs["tfp"], hs["tfi"]
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
    objects = _mog_objects(u8, phi0, adaptive, p, hist)
    # 3. DAISI edges (Eq. 10-14)
    edges = hs["daisi"] >= p["phi"]
    # 4. fine mask
    fine = fine_mask(
        coarse,
        objects,
        edges,
        close_size=p["close_size"],
        min_area=p["min_area"],
        dilate=p["dilate"],
    )
    masks = {"coarse": coarse, "fine": fine}
    if adaptive and not fine.any():
        return np.clip(tfp, 0.0, 1.0).astype(np.float32), masks
    # 5. TFI refined by PatchMatch on the fine region (adaptive: on its bounding box only)
    if adaptive:
        ys, xs = np.nonzero(fine)
        margin = p["pm_radius"] + p["pm_patch"] + int(3 * p["pm_sigma"]) + 1
        y0, y1 = max(0, ys.min() - margin), min(h, ys.max() + margin + 1)
        x0, x1 = max(0, xs.min() - margin), min(w, xs.max() + margin + 1)
        domain = fine[y0:y1, x0:x1]
    else:
        y0, y1, x0, x1 = 0, h, 0, w
        domain = np.ones((h, w), bool)
    offs = [p["pm_step"] * i for i in range(1, p["pm_count"] + 1)]
    # the reference t first, then t -+ step*i inside the window
    tcs = [center] + [c for s in offs for c in (center - s, center + s) if 0 <= c < n]
    raw, guides = _pm_frames(src, tcs, (int(y0), int(y1), int(x0), int(x1)), p)
    refined = patchmatch_fuse(
        raw[0],
        guides[0],
        raw[1:],
        guides[1:],
        domain,
        patch=p["pm_patch"],
        iters=p["pm_iters"],
        max_radius=p["pm_radius"],
        h=p["pm_h"],
        seed=seed,
        origin=(int(y0), int(x0)),
    )
    if not fine.any():  # always-full pipeline on a static window: the same TFP output
        return np.clip(tfp, 0.0, 1.0).astype(np.float32), masks
    dyn = tfi_full.copy()
    dyn[y0:y1, x0:x1] = refined
    # 6. ATSR (Eq. 7)
    rate, _ = atsr_fuse(dyn, tfp, fine, tfi=tfi_full)
    return rate, masks


def _mog_objects(u8: np.ndarray, phi0: float, adaptive: bool, p: Mapping[str, Any], hist: int):
    """Eq. 8-9 on the history ``u8`` (oldest first).

    MOG models every pixel on its own, and its background B lies between the pixel's smallest
    and largest history value, so ``|f_t - B| >= phi0`` is impossible where the history's range
    is below phi0. The adaptive pipeline runs MOG only on the bounding box of the pixels whose
    range reaches phi0 (none: no objects, MOG skipped), with the same result.
    """
    h, w = u8.shape[1:]
    if adaptive:
        varies = (u8.max(axis=0).astype(np.int16) - u8.min(axis=0)) >= phi0
        if not varies.any():
            return np.zeros((h, w), bool)
        ys, xs = np.nonzero(varies)
        y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    else:
        y0, y1, x0, x1 = 0, h, 0, w
    crop = np.ascontiguousarray(u8[:, y0:y1, x0:x1])
    _, background = mog_background(
        crop,
        history=hist,
        nmixtures=p["mog_mixtures"],
        background_ratio=p["mog_ratio"],
        noise_sigma=p["mog_noise"],
    )
    objects = np.zeros((h, w), bool)
    objects[y0:y1, x0:x1] = mog_objects(crop[-1], background, phi0)
    return objects


def _compute(window: np.ndarray, center: int, start: int, p: Mapping[str, Any]) -> Output:
    rate, masks = fine_stage(window, center, int(start) + int(center), p)
    return Output(rate, masks)


def _compute_packed(packed, layout, center: int, start: int, p: Mapping[str, Any]) -> Output:
    src = _Spikes.from_packed(packed, layout)
    rate, masks = fine_stage(src, center, int(start) + int(center), p)
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
    )
)
