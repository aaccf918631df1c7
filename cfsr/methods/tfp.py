"""TFP: texture from playback, the windowed spike count (CFSR paper Eq. 4)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numba import njit, prange

from cfsr._packed import count_packed, stored_to_image
from cfsr.methods.registry import MAX_WINDOW_STEPS, Method, Output, Param, register

__all__ = ["tfp_rate", "tfp_rate_packed", "tfp_span", "count_spikes"]


@njit(parallel=True, cache=True)
def _count_kernel(spikes, a, b, out):  # pragma: no cover - numba
    _, h, w = spikes.shape
    for y in prange(h):
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


def tfp_span(center: int, n: int, window: int, mode: str) -> tuple[int, int]:
    """Steps ``[a, b)`` of a ``window``-step TFP at index ``center`` of an ``n``-step array.

    ``trailing``: the ``window`` steps ending at ``center`` (Eq. 4, causal, for live use);
    ``centred``: ``window`` steps with ``center`` in the middle (offline). Clipped at the ends.
    """
    if mode == "trailing":
        a, b = center - window + 1, center + 1
    elif mode == "centred":
        a = center - window // 2
        b = a + window
    else:
        raise ValueError(f"mode must be 'trailing' or 'centred', got {mode!r}")
    return max(0, a), min(n, b)


def tfp_rate(
    spikes: np.ndarray, center: int, *, window: int = 160, mode: str = "trailing"
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


def _window(p: Mapping[str, Any]) -> tuple[int, int]:
    w = p["window"]
    if p["mode"] == "trailing":
        return w - 1, 0
    return w // 2, w - w // 2 - 1


def _compute(window: np.ndarray, center: int, start: int, p: Mapping[str, Any]) -> Output:
    return Output(tfp_rate(window, center, window=p["window"], mode=p["mode"]))


def tfp_rate_packed(
    packed: np.ndarray, layout, center: int, *, window: int = 160, mode: str = "trailing"
) -> np.ndarray:
    """:func:`tfp_rate` computed from packed frames ``(n, frame_bytes)`` without unpacking."""
    if window < 1:
        raise ValueError(f"window must be >= 1 step, got {window}")
    a, b = tfp_span(center, packed.shape[0], window, mode)
    counts = stored_to_image(count_packed(packed, a, b), layout).astype(np.int32)
    return (counts / np.float32(max(1, b - a))).astype(np.float32)


def _compute_packed(packed, layout, center: int, start: int, p: Mapping[str, Any]) -> Output:
    return Output(tfp_rate_packed(packed, layout, center, window=p["window"], mode=p["mode"]))


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
                choices=("trailing", "centred"),
            ),
        },
        window=_window,
        compute=_compute,
        compute_packed=_compute_packed,
        presets={"paper": {"window": 160}, "simulated": {"window": 30}},
        reference="CFSR paper Eq. 4 (Zhu et al., TFP)",
    )
)
