"""TFI: texture from inter-spike interval (CFSR paper Eq. 3).

For pixel x and output step t, the spikes s_prev <= t < s_next bracket t and the firing rate is
``1 / (s_next - s_prev)`` spikes per step. The paper's display constant C is applied later by
:func:`cfsr.display.to_display`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numba import njit, prange

from cfsr.methods.registry import Method, Output, Param, register

__all__ = ["tfi_rate", "isi_at"]


@njit(cache=True, inline="always")
def _isi_one(col, c, lo, hi):  # pragma: no cover - numba
    """ISI (steps) containing step ``c`` in ``col[lo:hi]``; bounded guess when one side is open.

    With no spike before ``c`` (or after it) the interval is at least as long as the distance to
    the search edge, and at least as long as the neighbouring complete interval; the larger of
    the two is used, so dark pixels get small, finite rates instead of 0 or Inf.
    """
    p = -1
    i = c
    while i >= lo:
        if col[i]:
            p = i
            break
        i -= 1
    n = -1
    i = c + 1
    while i < hi:
        if col[i]:
            n = i
            break
        i += 1
    if p >= 0 and n >= 0:
        return n - p
    if p >= 0:
        pp = -1
        i = p - 1
        while i >= lo:
            if col[i]:
                pp = i
                break
            i -= 1
        bound = hi - p
        return max(bound, p - pp) if pp >= 0 else bound
    if n >= 0:
        nn = -1
        i = n + 1
        while i < hi:
            if col[i]:
                nn = i
                break
            i += 1
        bound = n - lo + 1
        return max(bound, nn - n) if nn >= 0 else bound
    return hi - lo + 1


@njit(parallel=True, cache=True)
def _isi_kernel(spikes, c, lo, hi, out):  # pragma: no cover - numba
    _, h, w = spikes.shape
    for y in prange(h):
        for x in range(w):
            out[y, x] = _isi_one(spikes[:, y, x], c, lo, hi)
    return out


def isi_at(spikes: np.ndarray, center: int, max_isi: int) -> np.ndarray:
    """Inter-spike interval (steps, int32 >= 1) containing step ``center`` of ``spikes``.

    Searches at most ``max_isi`` steps each side of ``center`` (clipped to the array).
    """
    t, h, w = spikes.shape
    if not 0 <= center < t:
        raise ValueError(f"center {center} outside window of {t} steps")
    lo = max(0, center - max_isi)
    hi = min(t, center + max_isi + 1)
    out = np.empty((h, w), np.int32)
    return _isi_kernel(np.ascontiguousarray(spikes, dtype=np.uint8), center, lo, hi, out)


def tfi_rate(spikes: np.ndarray, center: int, *, max_isi: int = 400) -> np.ndarray:
    """TFI firing rate at step ``center`` (paper Eq. 3), spikes per step, float32 in (0, 1].

    Parameters
    ----------
    spikes : ndarray (T, H, W) uint8 0/1
        Upright spike frames.
    center : int
        Index into ``spikes`` of the output step.
    max_isi : int
        Search range each side of ``center`` (steps); pixels with no spike in range get
        ``1 / (range)``, a lower bound on their rate.
    """
    return (1.0 / isi_at(spikes, center, max_isi)).astype(np.float32)


def _compute(window: np.ndarray, center: int, start: int, p: Mapping[str, Any]) -> Output:
    return Output(tfi_rate(window, center, max_isi=p["max_isi"]))


register(
    Method(
        name="tfi",
        summary="Texture from inter-spike interval: rate = 1 / ISI containing t",
        params={
            "max_isi": Param(400, "steps", "longest ISI searched each side of t", minimum=1),
        },
        window=lambda p: (p["max_isi"], p["max_isi"]),
        compute=_compute,
        reference="CFSR paper Eq. 3 (Zhu et al., TFI)",
    )
)
