"""ATSR: adaptive temporal-spatial region fusion (CFSR paper Eq. 7).

The dynamic region takes the interval-based reconstruction (TFI, or its PatchMatch-refined form)
and the static region takes the window count (TFP). The two estimators live on slightly
different brightness scales (in the paper TFI carries the display constant C and TFP the window
length), so the static TFP is scaled by the mean ratio TFI/TFP over the static region before the
two are pasted together:

.. math::  I(x) = M(x)\\, I_{dyn}(x) + (1 - M(x))\\, \\alpha\\, I_{TFP}(x),
           \\qquad \\alpha = \\frac{\\sum_{x \\notin M} I_{TFI}(x)}{\\sum_{x \\notin M} I_{TFP}(x)}

Reading: the paper's "mean ratio" is taken as the ratio of the means over the static region.
The per-pixel mean of ratios is unbounded where TFP is near zero (a dark pixel with one spike
in w steps next to a short ISI gives ratios of 10+), the ratio of means is its robust form and
equals it when the ratio is constant. Guards: an empty static region, an all-dark static region
or a non-finite ratio give ``alpha = 1``; alpha is clipped to ``[1/alpha_max, alpha_max]`` and
the fused rate to ``[0, 1]`` spikes per step.
"""

from __future__ import annotations

import numpy as np

from cfsr._jit import njit

__all__ = ["atsr_alpha", "atsr_fuse", "atsr_fuse_isi"]


@njit
def _static_sums(tfi, tfp, static):  # pragma: no cover - numba
    """Sums of ``tfi`` and ``tfp`` over the ``static`` pixels, in float64 (flat arrays)."""
    num = 0.0
    den = 0.0
    for i in range(static.size):
        if static[i]:
            num += tfi[i]
            den += tfp[i]
    return num, den


@njit
def _paste_kernel(dynamic, tfp, mask, alpha, out):  # pragma: no cover - numba
    """``mask ? dynamic : alpha * tfp``, NaN -> 0, clipped to [0, 1] (flat arrays)."""
    for i in range(out.size):
        v = dynamic[i] if mask[i] else alpha * tfp[i]
        out[i] = 0.0 if np.isnan(v) else min(max(v, 0.0), 1.0)
    return out


def _flat(a: np.ndarray, dtype=None) -> np.ndarray:
    """Contiguous 1-D view (a copy only where needed); the kernels compile per dtype."""
    return np.ascontiguousarray(a, dtype=dtype).reshape(-1)


def atsr_alpha(
    tfi: np.ndarray, tfp: np.ndarray, static: np.ndarray, *, alpha_max: float = 4.0
) -> float:
    """Scale of the static TFP (Eq. 7): mean TFI / mean TFP over the ``static`` pixels.

    Returns 1.0 when the static region is empty or its TFP or TFI sum is not positive.
    """
    sel = np.asarray(static, dtype=bool)
    if not sel.any():
        return 1.0
    num, den = _static_sums(_flat(tfi), _flat(tfp), _flat(sel, bool))
    if not (np.isfinite(num) and np.isfinite(den)) or num <= 0.0 or den <= 0.0:
        return 1.0
    return float(np.clip(num / den, 1.0 / alpha_max, alpha_max))


def atsr_fuse(
    dynamic: np.ndarray,
    tfp: np.ndarray,
    mask: np.ndarray,
    *,
    tfi: np.ndarray | None = None,
    alpha_max: float = 4.0,
) -> tuple[np.ndarray, float]:
    """Fuse a dynamic-region reconstruction with the static TFP (Eq. 7).

    Parameters
    ----------
    dynamic : ndarray (H, W) float
        Rate (spikes/step) used where ``mask`` is True: TFI (CSR) or refined TFI (CFSR).
    tfp : ndarray (H, W) float
        TFP rate (spikes/step, Eq. 4), used where ``mask`` is False.
    mask : ndarray (H, W) bool
        Dynamic region.
    tfi : ndarray (H, W) float, optional
        The plain TFI used for the ratio; defaults to ``dynamic``.
    alpha_max : float
        Bound on the scale and its inverse (dimensionless).

    Returns
    -------
    rate : ndarray (H, W) float32
        Fused rate in [0, 1] spikes per step; never NaN or Inf.
    alpha : float
        The scale applied to the static TFP.
    """
    m = np.asarray(mask, dtype=bool)
    ref = dynamic if tfi is None else tfi
    alpha = atsr_alpha(ref, tfp, ~m, alpha_max=alpha_max)
    out = np.empty(m.shape, np.float32)
    _paste_kernel(
        _flat(dynamic, np.float32),
        _flat(tfp, np.float32),
        _flat(m, bool),
        np.float32(alpha),
        out.reshape(-1),
    )
    return out, alpha


@njit
def _fuse_isi_kernel(isi, tfp, mask, counted, alpha_max, out):  # pragma: no cover - numba
    """:func:`atsr_fuse` of each frame ``j`` (flat rows), the dynamic rate being TFI
    ``float32(1 / isi)``; the same sums (float64, pixel order), scale and paste. The sums of
    the frames before the last take only the static pixels where ``counted`` (flat bool;
    empty: all)."""
    last = isi.shape[0] - 1
    for j in range(isi.shape[0]):
        every = counted.shape[0] == 0 or j == last
        n = isi.shape[1]
        dynamic = False
        static = False
        num = 0.0
        den = 0.0
        for i in range(n):
            if mask[j, i]:
                dynamic = True
            elif every or counted[i]:
                static = True
                num += np.float32(1.0 / isi[j, i])
                den += tfp[j, i]
        if not dynamic:  # no dynamic pixel: the TFP itself (as csr_frames)
            for i in range(n):
                out[j, i] = min(max(tfp[j, i], 0.0), 1.0)
            continue
        alpha = 1.0
        if static and np.isfinite(num) and np.isfinite(den) and num > 0.0 and den > 0.0:
            alpha = min(max(num / den, 1.0 / alpha_max), alpha_max)
        a32 = np.float32(alpha)
        for i in range(n):
            v = np.float32(1.0 / isi[j, i]) if mask[j, i] else a32 * tfp[j, i]
            out[j, i] = 0.0 if np.isnan(v) else min(max(v, 0.0), 1.0)
    return out


def atsr_fuse_isi(
    isi: np.ndarray,
    tfp: np.ndarray,
    mask: np.ndarray,
    *,
    alpha_max: float = 4.0,
    counted: np.ndarray | None = None,
) -> np.ndarray:
    """CSR frames from TFI intervals: :func:`atsr_fuse` with ``dynamic = tfi = 1 / isi`` for
    every frame of a stack, frames without a dynamic pixel giving their clipped TFP.

    Parameters
    ----------
    isi : ndarray (K, H, W) int
        TFI intervals (steps, >= 1, Eq. 3).
    tfp : ndarray (K, H, W) float32
        TFP rates (spikes/step, Eq. 4).
    mask : ndarray (K, H, W) bool
        Dynamic regions.
    counted : ndarray (H, W) bool, optional
        The pixels whose static values the scales of the frames before the last sum (default:
        all; the last frame's scale sums every static pixel); the others' ``isi`` in those
        frames is not read unless they are dynamic.

    Returns
    -------
    rates : ndarray (K, H, W) float32
        In [0, 1] spikes per step; the numbers of ``atsr_fuse`` frame by frame (one pass per
        frame, frames in parallel).
    """
    k = isi.shape[0]
    out = np.empty(isi.shape, np.float32)
    sel = np.empty(0, np.bool_) if counted is None else np.ascontiguousarray(counted, bool)
    _fuse_isi_kernel(
        np.ascontiguousarray(isi).reshape(k, -1),
        np.ascontiguousarray(tfp, dtype=np.float32).reshape(k, -1),
        np.ascontiguousarray(mask, dtype=bool).reshape(k, -1),
        sel.reshape(-1),
        float(alpha_max),
        out.reshape(k, -1),
    )
    return out
