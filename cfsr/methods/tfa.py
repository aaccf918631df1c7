"""TFA: texture from an adaptive threshold (baseline of the CFSR paper).

Each pixel integrates spikes outward from t until it has collected ``threshold`` inter-spike
intervals, and its rate is ``intervals / time they span``. A bright pixel reaches the threshold
in a few steps (sharp in time), a dark one integrates longer (less noise): the integration window
adapts to the pixel's own firing instead of being one fixed w (TFP) or one interval (TFI).

Reading (the CFSR paper cites TFA as a baseline without restating it): growth starts from the
interval containing t (s_prev <= t < s_next, as TFI) and adds, one spike at a time, whichever of
the next-earlier and next-later spikes is closer to t; it stops at ``threshold`` intervals or
when the span would exceed ``2 * max_window`` steps. With one interval this is TFI (Eq. 3); a
large threshold tends to a centred TFP. Where fewer than two spikes fall in range, the rate is a
lower bound ``1 / (range + 1)``, as TFI's open intervals are.

The same kernel, with a refractory merge of too-short intervals, is SNM's motion estimator
(:mod:`cfsr.methods.snm`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfsr._isi import search_range
from cfsr._jit import njit
from cfsr.methods._spiketimes import pixel_times, row_gather
from cfsr.methods.registry import (
    MAX_UNPACKED_STEPS,
    Method,
    MethodSettings,
    Output,
    Param,
    register,
)

__all__ = ["adaptive_rate", "adaptive_rates"]


@njit(helper=True)
def grow_span(times, f0, f1, ip, c, n_int):  # pragma: no cover - numba
    """Spike indices ``(a, b)`` spanning ``n_int`` intervals around step ``c``.

    Starts from the interval containing ``c`` (spike ``ip`` is the last one <= c), or the one
    nearest ``c`` at an open end, and adds the neighbouring interval closer to ``c`` until
    ``n_int`` intervals are covered or ``times[f0:f1]`` runs out.

    Where ``n_int - 1`` spikes lie on each side of that interval within ``times[f0:f1]`` (the
    usual case), the span is found without branches: growth merges the left distances
    ``L_j = c - times[ip - j]`` with the right ones ``R_j = times[ip + 1 + j] - c`` (both
    increasing, ties to the left), and of its first ``n_int - 1`` picks,
    ``#{j : L_j <= R_(n_int - j)}`` are on the left.
    """
    if n_int >= 1 and ip - n_int + 1 >= f0 and ip + n_int < f1:
        k = 0
        for j in range(1, n_int):
            k += np.int64(c - times[ip - j] <= times[ip + 1 + n_int - j] - c)
        return ip - k, ip + n_int - k
    if ip < f0:
        a, b = f0, f0 + 1
    elif ip >= f1 - 1:
        a, b = f1 - 2, f1 - 1
    else:
        a, b = ip, ip + 1
    while b - a < n_int:
        can_l = a > f0
        can_r = b < f1 - 1
        if can_l and can_r:
            if c - times[a - 1] <= times[b + 1] - c:
                a -= 1
            else:
                b += 1
        elif can_l:
            a -= 1
        elif can_r:
            b += 1
        else:
            break
    return a, b


@njit
def _adaptive_kernel(spikes, centers, n_int, mw, lo, hi, refractory, out):
    # pragma: no cover - numba
    """Rate from the ``n_int`` intervals nearest each of ``centers`` (search ``+- mw`` steps).

    Each pixel's spike times in ``[lo, hi)`` are gathered once; every center then uses the
    spikes inside its own range (:func:`cfsr._isi.search_range`, ``mw`` steps each side).
    ``refractory > 0``: within the chosen spikes, a spike closer than ``refractory`` times the
    median chosen interval to the previously kept spike is dropped (merged into the next
    interval) before the rate is taken.
    """
    n, h, w = spikes.shape
    for y in range(h):
        slab, times = row_gather(spikes, lo, hi - lo, y)
        gaps = np.empty(n_int + 1, np.int64)
        for x in range(w):
            ns = pixel_times(slab, x, lo, times)
            for kk in range(centers.shape[0]):
                c = centers[kk]
                c_lo, c_hi = search_range(c, mw, n)
                f0 = np.searchsorted(times[:ns], c_lo, side="left")
                f1 = np.searchsorted(times[:ns], c_hi, side="left")  # one past the last
                if f1 - f0 < 2:
                    out[kk, y, x] = 1.0 / (c_hi - c_lo + 1)
                    continue
                ip = np.searchsorted(times[:ns], c, side="right") - 1  # last spike <= c
                a, b = grow_span(times, f0, f1, ip, c, n_int)
                if refractory > 0.0 and b - a >= 2:
                    m = b - a
                    for k in range(m):
                        gaps[k] = times[a + k + 1] - times[a + k]
                    srt = np.sort(gaps[:m])
                    med = 0.5 * (srt[(m - 1) // 2] + srt[m // 2])
                    limit = refractory * med
                    kept = 1
                    first = times[a]
                    last = first
                    for k in range(a + 1, b + 1):
                        if times[k] - last >= limit:
                            last = times[k]
                            kept += 1
                    if kept >= 2:
                        out[kk, y, x] = (kept - 1) / (last - first)
                    else:
                        out[kk, y, x] = 1.0 / (times[b] - times[a])
                else:
                    out[kk, y, x] = (b - a) / (times[b] - times[a])
    return out


def adaptive_rates(
    spikes: np.ndarray,
    centers,
    *,
    threshold: int = 8,
    max_window: int = 200,
    refractory: float = 0.0,
) -> np.ndarray:
    """:func:`adaptive_rate` at several indices of one window: float32 ``(K, H, W)``.

    One scan of each pixel's spikes serves all centers (CFSR's PatchMatch guides).
    """
    n, h, w = spikes.shape
    cs = np.atleast_1d(np.asarray(centers, dtype=np.int64))
    if cs.size and (cs.min() < 0 or cs.max() >= n):
        raise ValueError(f"centers {cs.tolist()} outside window of {n} steps")
    if threshold < 1:
        raise ValueError(f"threshold must be >= 1 interval, got {threshold}")
    out = np.empty((cs.size, h, w), np.float32)
    if cs.size == 0:
        return out
    lo = max(0, int(cs.min()) - max_window)
    hi = min(n, int(cs.max()) + max_window + 1)
    _adaptive_kernel(
        np.ascontiguousarray(spikes, dtype=np.uint8),
        cs,
        int(threshold),
        int(max_window),
        lo,
        hi,
        float(refractory),
        out,
    )
    return out


def adaptive_rate(
    spikes: np.ndarray,
    center: int,
    *,
    threshold: int = 8,
    max_window: int = 200,
    refractory: float = 0.0,
) -> np.ndarray:
    """Rate from the ``threshold`` inter-spike intervals nearest ``center`` (spikes/step).

    Parameters
    ----------
    spikes : ndarray (n, H, W) uint8 0/1
        Upright spike frames.
    center : int
        Index of the output step t.
    threshold : int
        Intervals to integrate (the adaptive threshold, in spikes).
    max_window : int
        Steps searched each side of t.
    refractory : float
        Fraction of the median interval below which a spike is dropped as refractory
        (0: keep all; used by SNM).

    Returns
    -------
    ndarray (H, W) float32 in (0, 1].
    """
    n = spikes.shape[0]
    if not 0 <= center < n:
        raise ValueError(f"center {center} outside window of {n} steps")
    return adaptive_rates(
        spikes, [center], threshold=threshold, max_window=max_window, refractory=refractory
    )[0]


@dataclass(frozen=True)
class TfaSettings(MethodSettings):
    """TFA's parameters (its Param table below)."""

    threshold: int  #: intervals integrated per pixel
    max_window: int  #: search range each side of t, steps


def _window(s: TfaSettings) -> tuple[int, int]:
    return s.max_window, s.max_window


def _compute(window: np.ndarray, center: int, start: int, s: TfaSettings) -> Output:
    return Output(adaptive_rate(window, center, threshold=s.threshold, max_window=s.max_window))


register(
    Method(
        name="tfa",
        summary="Texture from adaptive threshold: rate over the N intervals nearest t",
        params={
            "threshold": Param(
                8, "intervals", "intervals integrated per pixel", minimum=1, maximum=1000
            ),
            # no packed path: the whole window is unpacked, hence the tighter limit
            "max_window": Param.steps(
                200,
                "search range each side of t",
                maximum=MAX_UNPACKED_STEPS // 2,
            ),
        },
        window=_window,
        compute=_compute,
        presets={"paper": {"threshold": 12}},
        reference="CFSR paper baseline TFA (adaptive threshold); see docs/methods.md",
        settings=TfaSettings,
    )
)
