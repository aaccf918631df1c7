"""Conversion of firing rates (spikes per step) to 8-bit display values (0..255)."""

from __future__ import annotations

import numpy as np

__all__ = ["to_display", "auto_gain"]


def auto_gain(rate: np.ndarray, percentile: float = 99.5) -> float:
    """A gain (spikes/step mapped to 255) from the rate image's upper percentile."""
    r = np.asarray(rate, dtype=np.float64)
    finite = r[np.isfinite(r)]
    if finite.size == 0:
        return 1.0
    g = float(np.percentile(finite, percentile))
    return g if g > 0 else 1.0


def to_display(rate: np.ndarray, gain: float | None = None) -> np.ndarray:
    """Map firing rate to uint8: ``clip(rate / gain * 255)`` (the paper's C = 255 / gain).

    ``gain`` is the rate shown as white; e.g. 0.6 for the REDS simulations (brightness =
    rate / 0.6 * 255). ``None`` picks it from the image (:func:`auto_gain`).
    """
    g = auto_gain(rate) if gain is None else float(gain)
    if not np.isfinite(g) or g <= 0:
        raise ValueError(f"gain must be a positive rate in spikes/step, got {gain}")
    img = np.nan_to_num(np.asarray(rate, dtype=np.float32), nan=0.0, posinf=g, neginf=0.0)
    return np.clip(np.rint(img * (255.0 / g)), 0, 255).astype(np.uint8)
