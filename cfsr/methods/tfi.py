"""TFI: texture from inter-spike interval (CFSR paper Eq. 3).

For pixel x and output step t, the spikes s_prev <= t < s_next bracket t and the firing rate is
``1 / (s_next - s_prev)`` spikes per step. The paper's display constant C is applied later by
:func:`cfsr.display.to_display`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfsr._isi import isi_from_times, needs_after, needs_before, search_range, tfi_interval
from cfsr._jit import njit
from cfsr._packed import isi_packed, stored_to_image
from cfsr.methods._spiketimes import pixel_times, row_gather
from cfsr.methods.registry import Method, MethodSettings, Output, Param, register

__all__ = ["tfi_rate", "isi_at", "tfi_rates"]


@njit(helper=True)
def _isi_one(col, c, lo, hi):  # pragma: no cover - numba
    """ISI (steps) containing step ``c`` of the byte column ``col``, spikes searched in
    ``[lo, hi)``: :func:`cfsr._isi.tfi_interval`, open ends included."""
    p = _prev_in(col, c, lo)
    n = _next_in(col, c + 1, hi)
    pp = _prev_in(col, p - 1, lo) if needs_before(p, n) else -1
    nn = _next_in(col, n + 1, hi) if needs_after(p, n) else -1
    return tfi_interval(p, n, pp, nn, lo, hi)


@njit(helper=True)
def _prev_in(col, t, lo):  # pragma: no cover - numba
    """Last spike of ``col`` in ``[lo, t]`` (-1: none)."""
    while t >= lo:
        if col[t]:
            return t
        t -= 1
    return -1


@njit(helper=True)
def _next_in(col, t, hi):  # pragma: no cover - numba
    """First spike of ``col`` in ``[t, hi)`` (-1: none)."""
    while t < hi:
        if col[t]:
            return t
        t += 1
    return -1


@njit
def _isi_kernel(spikes, c, lo, hi, out):  # pragma: no cover - numba
    _, h, w = spikes.shape
    for y in range(h):
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


@njit
def _isi_multi_kernel(spikes, centers, m, lo, hi, out):  # pragma: no cover - numba
    """:func:`_isi_one` at every index of ``centers`` from one scan per pixel.

    Each pixel's spike times in ``[lo, hi)`` are gathered once (row slab, contiguous x), then
    every center gets exactly the interval, bounds and open-end rule of :func:`_isi_one` with
    its own search range (:func:`cfsr._isi.search_range`, ``m`` steps each side).
    """
    n, h, w = spikes.shape
    for y in range(h):
        slab, times = row_gather(spikes, lo, hi - lo, y)
        for x in range(w):
            ns = pixel_times(slab, x, lo, times)
            for k in range(centers.shape[0]):
                c = centers[k]
                a, b = search_range(c, m, n)
                # ip: last spike <= c (index into times)
                ip = np.searchsorted(times[:ns], c, side="right") - 1
                out[k, y, x] = isi_from_times(times, ns, ip, a, b)
    return out


def tfi_rates(spikes: np.ndarray, centers, *, max_isi: int = 400) -> np.ndarray:
    """:func:`tfi_rate` at several indices of one window, float32 ``(len(centers), H, W)``.

    Identical numbers to calling :func:`tfi_rate` per center, from one scan of each pixel's
    spikes (the PatchMatch stage of CFSR needs 33 TFI frames of the same window).
    """
    n, h, w = spikes.shape
    cs = np.atleast_1d(np.asarray(centers, dtype=np.int64))
    if cs.size and (cs.min() < 0 or cs.max() >= n):
        raise ValueError(f"centers {cs.tolist()} outside window of {n} steps")
    out = np.empty((cs.size, h, w), np.int32)
    if cs.size == 0:
        return out.astype(np.float32)
    lo = max(0, int(cs.min()) - max_isi)
    hi = min(n, int(cs.max()) + max_isi + 1)
    _isi_multi_kernel(np.ascontiguousarray(spikes, dtype=np.uint8), cs, int(max_isi), lo, hi, out)
    return (1.0 / out).astype(np.float32)


@dataclass(frozen=True)
class TfiSettings(MethodSettings):
    """TFI's parameters (its Param table below)."""

    max_isi: int  #: steps searched each side of t


def _window(s: TfiSettings) -> tuple[int, int]:
    return s.max_isi, s.max_isi


def _compute(window: np.ndarray, center: int, start: int, s: TfiSettings) -> Output:
    return Output(tfi_rate(window, center, max_isi=s.max_isi))


def tfi_rate_packed(packed: np.ndarray, layout, center: int, *, max_isi: int = 400) -> np.ndarray:
    """:func:`tfi_rate` computed from packed frames ``(n, frame_bytes)`` without unpacking."""
    n = packed.shape[0]
    if not 0 <= center < n:
        raise ValueError(f"center {center} outside window of {n} steps")
    lo, hi = search_range(center, max_isi, n)
    isi = stored_to_image(isi_packed(packed, center, lo, hi), layout)
    return (1.0 / isi).astype(np.float32)


def _compute_packed(packed, layout, center: int, start: int, s: TfiSettings) -> Output:
    return Output(tfi_rate_packed(packed, layout, center, max_isi=s.max_isi))


register(
    Method(
        name="tfi",
        summary="Texture from inter-spike interval: rate = 1 / ISI containing t",
        params={
            "max_isi": Param.steps(400, "longest ISI searched each side of t"),
        },
        window=_window,
        compute=_compute,
        compute_packed=_compute_packed,
        reference="CFSR paper Eq. 3 (Zhu et al., TFI)",
        settings=TfiSettings,
    )
)
