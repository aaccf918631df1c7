"""TFP: texture from playback, the windowed spike count (CFSR paper Eq. 4)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from cfsr._isi import search_range
from cfsr._jit import njit
from cfsr._packed import CHUNK, count_packed, isi_packed_at, stored_to_image
from cfsr._words import _load_u64, trailing_zeros
from cfsr.methods.registry import (
    MAX_WINDOW_STEPS,
    Method,
    MethodSettings,
    Output,
    Param,
    choices_of,
    register,
)
from cfsr.methods.tfi import tfi_rate

__all__ = [
    "tfp_extent",
    "tfp_rate",
    "tfp_rate_packed",
    "tfp_span",
    "count_spikes",
    "isi_span_rate",
    "isi_span_stored",
    "static_rate",
    "static_rate_packed",
    "STATIC_ESTIMATORS",
    "RateRule",
    "TfpMode",
]


class TfpMode(StrEnum):
    """Where a TFP window lies around t."""

    TRAILING = "trailing"  #: the ``window`` steps ending at t (Eq. 4, causal, for live use)
    CENTRED = "centred"  #: ``window`` steps with t in the middle (offline)


class RateRule(StrEnum):
    """How a static span's spikes give a rate."""

    ISI = "isi"  #: ``(count - 1) / (last - first)`` (:func:`span_rate`)
    TFP = "tfp"  #: count / steps (Eq. 4, the paper's)


#: Static-region estimators: ``isi`` (:func:`isi_span_rate`) or ``tfp`` (Eq. 4, the paper's).
STATIC_ESTIMATORS = choices_of(RateRule)


@njit
def _count_kernel(spikes, a, b, out):  # pragma: no cover - numba
    _, h, w = spikes.shape
    for y in range(h):
        for x in range(w):
            out[y, x] = 0
        # time in the middle, contiguous x innermost: ~10x faster than pixel-outer order
        for t in range(a, b):
            for x in range(w):
                out[y, x] += spikes[t, y, x]
    return out


def count_spikes(spikes: np.ndarray, a: int, b: int) -> np.ndarray:
    """Spikes per pixel in steps ``a..b-1`` of ``spikes`` (int32 (H, W))."""
    _, h, w = spikes.shape
    out = np.empty((h, w), np.int32)
    return _count_kernel(np.ascontiguousarray(spikes, dtype=np.uint8), a, b, out)


@njit(helper=True)
def span_rate(count, first, last, length):  # pragma: no cover - numba
    """The static-rate rule, spikes per step in [0, 1], from a span's spikes.

    ``count`` spikes in a span of ``length`` steps, the first at step ``first`` and the last at
    ``last``. Two or more spikes: ``(count - 1) / (last - first)``, the mean inter-spike
    interval's inverse. A steady integrate-and-fire pixel at rate r fires at the steps where
    its integral crosses a whole number, so the ``count - 1`` whole intervals between its first
    and last spike span ``(count - 1) / r`` steps to within one step: the relative error is at
    most ``1 / (last - first)``, and zero when ``1 / r`` is a whole number of steps. The window
    count (Eq. 4) is off by up to one whole spike instead, because the span's ends cut
    intervals at arbitrary phase: a pixel at 0.02 spikes/step fires 3 or 4 times in 160 steps
    (+-25 %), while its first-to-last spike distance gives 0.02 within ~1 %.
    Fewer than two spikes: no interval is observed inside the span, and this function returns
    the window count ``count / length`` (0, or 1 / length). The static estimators
    (:func:`static_rate`, CSR, CFSR) do not keep that: such a pixel fires less than about
    twice per span (its interval exceeds half the span), and the one interval around t, the
    TFI (Eq. 3, searched ``max_isi`` steps each side, which every CSR/CFSR window already
    holds), measures its rate to one step where the count says 0 or 1 / length (on the
    lowlight scene with CSR's 32-step span this is the difference between 10.5 and 36 dB).
    ``count - 1 <= last - first`` (distinct steps) keeps the result in [0, 1].
    """
    if count >= 2 and last > first:
        return (count - 1) / (last - first)
    return count / max(1, length)


@njit
def _isi_span_kernel(spikes, a, b, mark, out):  # pragma: no cover - numba
    # count with contiguous x innermost (as _count_kernel); the first and the last spike by a
    # forward and a backward scan that stop once every pixel of the row has been seen
    _, h, w = spikes.shape
    for y in range(h):
        cnt = np.zeros(w, np.int64)
        for t in range(a, b):
            for x in range(w):
                cnt[x] += spikes[t, y, x]
        first = np.full(w, -1, np.int64)
        last = np.full(w, -1, np.int64)
        left = 0
        for x in range(w):
            left += cnt[x] >= 2
        t = a
        while left > 0 and t < b:
            for x in range(w):
                if spikes[t, y, x] and first[x] < 0 and cnt[x] >= 2:
                    first[x] = t
                    left -= 1
            t += 1
        for x in range(w):
            left += cnt[x] >= 2
        t = b - 1
        while left > 0 and t >= a:
            for x in range(w):
                if spikes[t, y, x] and last[x] < 0 and cnt[x] >= 2:
                    last[x] = t
                    left -= 1
            t -= 1
        for x in range(w):
            if mark and cnt[x] < 2:
                out[y, x] = np.float32(-1.0)
            else:
                out[y, x] = np.float32(span_rate(cnt[x], first[x], last[x], b - a))
    return out


@njit
def _isi_span_packed_kernel(packed, a, b, counts, mark, out):  # pragma: no cover - numba
    # ``counts`` per stored pixel come from count_packed (SWAR); here the first and the last
    # spike of each pixel, by a forward and a backward scan of each 64-byte column chunk read
    # as eight-byte words (bytes at the frame's ragged end one by one). Only the units still
    # holding a pixel to find are read, and a scan stops once every pixel has been seen, so
    # bright pixels cost a few steps and each set bit is handled once.
    nb = packed.shape[1]
    nchunks = (nb + CHUNK - 1) // CHUNK
    one = np.uint64(1)
    zero = np.uint64(0)
    for c in range(nchunks):
        b0 = c * CHUNK
        m = min(nb, b0 + CHUNK) - b0
        mw = m // 8  # whole words; then m % 8 single bytes
        nu = mw + m % 8
        off = np.empty(CHUNK, np.int64)  # unit -> byte offset in the chunk
        for u in range(nu):
            off[u] = 8 * u if u < mw else 8 * mw + (u - mw)
        first = np.full(8 * CHUNK, -1, np.int64)
        last = np.full(8 * CHUNK, -1, np.int64)
        pend = np.zeros(CHUNK, np.uint64)  # bits of the pixels still to find, per unit
        active = np.empty(CHUNK, np.int64)  # units with such bits (unordered)
        for direction in range(2):
            left = 0
            for u in range(nu):
                width = 8 if u < mw else 1
                pu = zero
                for k in range(8 * width):
                    if counts[8 * (b0 + off[u]) + k] >= 2:
                        pu |= one << np.uint64(k)
                pend[u] = pu
                if pu:
                    active[left] = u
                    left += 1
            t = a if direction == 0 else b - 1
            while left > 0 and a <= t < b:
                j = 0
                while j < left:
                    u = active[j]
                    if u < mw:
                        v = _load_u64(packed, t, b0 + off[u]) & pend[u]
                    else:
                        v = np.uint64(packed[t, b0 + off[u]]) & pend[u]
                    if v:
                        pend[u] &= ~v
                        while v:
                            q = 8 * off[u] + np.int64(trailing_zeros(v))
                            v &= v - one
                            if direction == 0:
                                first[q] = t
                            else:
                                last[q] = t
                        if pend[u] == zero:  # done: the last active unit takes its place
                            left -= 1
                            active[j] = active[left]
                            continue
                    j += 1
                t += 1 if direction == 0 else -1
        for q in range(8 * m):
            p = 8 * b0 + q
            if mark and counts[p] < 2:
                out[p] = np.float32(-1.0)
            else:
                out[p] = np.float32(span_rate(counts[p], first[q], last[q], b - a))
    return out


def isi_span_rate(spikes: np.ndarray, a: int, b: int, *, mark: bool = False) -> np.ndarray:
    """Span rate (spikes per step, float32 ``(H, W)`` in [0, 1]) over steps ``[a, b)``.

    ``(count - 1) / (last - first)`` from the span's spikes; with fewer than two spikes
    ``count / (b - a)``, or -1 when ``mark`` (the caller fills those pixels with the TFI,
    :func:`static_rate`). :func:`span_rate` gives the reasoning.
    """
    _, h, w = spikes.shape
    out = np.empty((h, w), np.float32)
    sp = np.ascontiguousarray(spikes, dtype=np.uint8)
    return _isi_span_kernel(sp, int(a), int(b), bool(mark), out)


def isi_span_stored(packed: np.ndarray, a: int, b: int, *, mark: bool = False) -> np.ndarray:
    """:func:`isi_span_rate` per stored pixel of packed frames ``(n, frame_bytes)``, float32."""
    packed = np.ascontiguousarray(packed, dtype=np.uint8)
    out = np.empty(packed.shape[1] * 8, np.float32)
    counts = count_packed(packed, int(a), int(b))
    return _isi_span_packed_kernel(packed, int(a), int(b), counts, bool(mark), out)


def _fill_sparse(rate: np.ndarray, tfi) -> np.ndarray:
    """Pixels marked -1 (fewer than two spikes in the span) take the TFI rate; ``tfi`` is the
    array or a function that computes it (called only when some pixel needs it)."""
    sparse = rate < 0
    if sparse.any():
        t = tfi() if callable(tfi) else tfi
        rate[sparse] = t[sparse]
    return rate


def static_rate(
    spikes: np.ndarray,
    center: int,
    *,
    window: int,
    mode: TfpMode = TfpMode.TRAILING,
    estimator: str,
    max_isi: int = 200,
    tfi: np.ndarray | None = None,
    layout=None,
) -> np.ndarray:
    """Static-region rate at ``center``, float32 ``(H, W)`` spikes per step in [0, 1].

    ``estimator`` ``tfp``: :func:`tfp_rate` (Eq. 4) over the ``window``-step span of
    :func:`tfp_span`. ``isi``: over the same span, ``(count - 1) / (last - first)``
    (:func:`span_rate`); a pixel with fewer than two spikes there takes the TFI rate at
    ``center`` (Eq. 3, ``max_isi`` steps searched each side; ``tfi`` when given). Such a
    pixel fires less than about twice per span, so the one interval around ``center``
    measures its rate to one step where the count says 0 or ``1 / window``.

    ``layout`` (a :class:`cfsr.layout.Layout`): ``spikes`` are packed frames ``(n,
    frame_bytes)`` of that layout, read without unpacking (:func:`static_rate_packed`).
    """
    if estimator == RateRule.TFP:
        if layout is not None:
            return tfp_rate_packed(spikes, layout, center, window=window, mode=mode)
        return tfp_rate(spikes, center, window=window, mode=mode)
    if estimator != RateRule.ISI:
        raise ValueError(f"estimator must be one of {STATIC_ESTIMATORS}, got {estimator!r}")
    if window < 1:
        raise ValueError(f"window must be >= 1 step, got {window}")
    a, b = tfp_span(center, spikes.shape[0], window, mode)
    if layout is not None:
        return _isi_static_packed(spikes, layout, a, b, center, max_isi, tfi)

    rate = isi_span_rate(spikes, a, b, mark=True)
    if tfi is None:
        return _fill_sparse(rate, lambda: tfi_rate(spikes, center, max_isi=max_isi))
    return _fill_sparse(rate, tfi)


def static_rate_packed(packed: np.ndarray, layout, center: int, **rule) -> np.ndarray:
    """:func:`static_rate` (the same keywords) from packed frames ``(n, frame_bytes)`` of
    ``layout`` without unpacking."""
    return static_rate(packed, center, layout=layout, **rule)


def _isi_static_packed(packed, layout, a, b, center, max_isi, tfi) -> np.ndarray:
    """The ``isi`` rule of :func:`static_rate` over steps ``[a, b)`` of packed frames."""
    flat = isi_span_stored(packed, a, b, mark=True)
    if tfi is None:  # the TFI of the pixels below two spikes only, read in place
        fill_sparse_stored(
            flat, packed, layout.height, layout.stored_width, layout.width, center, max_isi
        )
        return np.ascontiguousarray(stored_to_image(flat, layout))
    return _fill_sparse(np.ascontiguousarray(stored_to_image(flat, layout)), tfi)


def fill_sparse_stored(
    flat: np.ndarray,
    packed: np.ndarray,
    h: int,
    stored_width: int,
    w: int,
    center: int,
    max_isi: int,
) -> np.ndarray:
    """Give the pixels of ``flat`` (per stored pixel, -1 = fewer than two spikes in the span)
    the TFI rate at ``center`` (Eq. 3, ``max_isi`` steps each side, the numbers of
    :func:`cfsr.methods.tfi.tfi_rate_packed`), computed for those pixels only; in place."""
    grid = flat[: h * stored_width].reshape(h, stored_width)[:, :w]
    ys, xs = np.nonzero(grid < 0)
    if ys.size:
        n = packed.shape[0]
        lo, hi = search_range(center, max_isi, n)
        isi = isi_packed_at(packed, ys * stored_width + xs, center, lo, hi)
        grid[ys, xs] = (1.0 / isi).astype(np.float32)
    return flat


def tfp_span(center: int, n: int, window: int, mode: TfpMode) -> tuple[int, int]:
    """Steps ``[a, b)`` of a ``window``-step TFP at index ``center`` of an ``n``-step array.

    ``trailing``: the ``window`` steps ending at ``center`` (Eq. 4, causal, for live use);
    ``centred``: ``window`` steps with ``center`` in the middle (offline). Clipped at the ends.
    """
    lo, hi = _offsets(window, mode)
    return max(0, center + lo), min(n, center + hi)


def _offsets(window: int, mode: TfpMode) -> tuple[int, int]:
    """``[lo, hi)`` of a TFP window relative to its centre."""
    if mode == TfpMode.TRAILING:
        return 1 - window, 1
    if mode == TfpMode.CENTRED:
        return -(window // 2), window - window // 2
    raise ValueError(f"mode must be 'trailing' or 'centred', got {mode!r}")


def tfp_extent(window: int, mode: TfpMode) -> tuple[int, int]:
    """Steps ``(before, after)`` the centre that a ``window``-step TFP placed as ``mode``
    reads (:func:`tfp_span` before clipping): ``trailing`` ``(window - 1, 0)``, ``centred``
    the window with the centre in its middle."""
    lo, hi = _offsets(window, mode)
    return -lo, hi - 1


def tfp_rate(
    spikes: np.ndarray, center: int, *, window: int = 160, mode: TfpMode = TfpMode.TRAILING
) -> np.ndarray:
    """TFP firing rate at step ``center`` (paper Eq. 4): spike count / steps counted.

    Returns float32 ``(H, W)`` spikes per step in [0, 1]. Near the ends of the recording the
    window is clipped and the divisor is the number of steps actually counted.
    """
    if window < 1:
        raise ValueError(f"window must be >= 1 step, got {window}")
    a, b = tfp_span(center, spikes.shape[0], window, mode)
    counts = count_spikes(spikes, a, b)
    return (counts / np.float32(max(1, b - a))).astype(np.float32)


@dataclass(frozen=True)
class TfpSettings(MethodSettings):
    """TFP's parameters (its Param table below)."""

    window: int  #: window length w, steps
    mode: TfpMode


def _window(s: TfpSettings) -> tuple[int, int]:
    return tfp_extent(s.window, s.mode)


def _compute(window: np.ndarray, center: int, start: int, s: TfpSettings) -> Output:
    return Output(tfp_rate(window, center, window=s.window, mode=s.mode))


def tfp_rate_packed(
    packed: np.ndarray, layout, center: int, *, window: int = 160, mode: TfpMode = TfpMode.TRAILING
) -> np.ndarray:
    """:func:`tfp_rate` computed from packed frames ``(n, frame_bytes)`` without unpacking."""
    if window < 1:
        raise ValueError(f"window must be >= 1 step, got {window}")
    a, b = tfp_span(center, packed.shape[0], window, mode)
    counts = stored_to_image(count_packed(packed, a, b), layout).astype(np.int32)
    return (counts / np.float32(max(1, b - a))).astype(np.float32)


def _compute_packed(packed, layout, center: int, start: int, s: TfpSettings) -> Output:
    return Output(tfp_rate_packed(packed, layout, center, window=s.window, mode=s.mode))


register(
    Method(
        name="tfp",
        summary="Texture from playback: spike count over a window / window length",
        params={
            "window": Param(160, "steps", "window length w", minimum=1, maximum=MAX_WINDOW_STEPS),
            "mode": Param(
                "trailing",
                "",
                "trailing (causal) or centred window",
                choices=choices_of(TfpMode),
            ),
        },
        window=_window,
        compute=_compute,
        compute_packed=_compute_packed,
        presets={"paper": {"window": 160}, "simulated": {"window": 30}},
        reference="CFSR paper Eq. 4 (Zhu et al., TFP)",
        settings=TfpSettings,
    )
)
