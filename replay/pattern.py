"""A tiny built-in synthetic scene (a toy device in OpenEB's sense): a bright bar sweeping over a
textured static background, through per-pixel integrate-and-fire.

It needs nothing but NumPy, so tests and the fallback demo never depend on the full simulator
(:mod:`cfsr.simulate`). Ground truth is known: the intensity image at each step.
"""

from __future__ import annotations

import numpy as np

from cfsr.layout import Layout
from cfsr.spikes import SpikeRecording

__all__ = ["pattern_intensity", "pattern_recording"]


def pattern_intensity(step: int, height: int, width: int, *, speed_px: float = 0.02) -> np.ndarray:
    """Intensity (firing probability per step, 0.05..0.6) of the scene at ``step``.

    The left half holds a static texture, the right half a static gradient; a 40-pixel bar
    with stripes (0.05..0.6) moves right by ``speed_px`` pixels per step (800 px/s at 40 kHz
    for 0.02) and wraps around, so pixels it crosses see their intensity change.
    """
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    base = 0.1 + 0.25 * (0.5 + 0.5 * np.sin(x / 9.0) * np.cos(y / 7.0))
    base[:, width // 2 :] = 0.05 + 0.15 * (y[:, width // 2 :] / max(1, height - 1))
    pos = (step * speed_px) % width
    rel = ((x - pos + width / 2) % width) - width / 2
    bar = np.abs(rel) < 20
    stripes = 0.325 + 0.275 * np.sin(rel * (2 * np.pi / 8.0))
    return np.where(bar, stripes, base).astype(np.float32)


def pattern_recording(
    steps: int,
    *,
    height: int = 250,
    width: int = 400,
    seed: int = 0,
    speed_px: float = 0.02,
    chunk: int = 512,
) -> SpikeRecording:
    """Simulate ``steps`` steps of the pattern scene into a packed in-memory recording.

    The sidecar meta carries ``gain`` 0.6 (the brightest rate, shown as white) and
    ``scene`` ``pattern``.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    lay = Layout(width=width, height=height)
    rng = np.random.default_rng(seed)
    pot = rng.random((height, width), dtype=np.float32)
    out = np.empty((steps, lay.frame_bytes), np.uint8)
    buf = np.empty((chunk, height, width), np.bool_)
    from cfsr._bits import pack_frames

    # the intensity changes slowly: recompute it every 8 steps
    inten = pattern_intensity(0, height, width, speed_px=speed_px)
    for a in range(0, steps, chunk):
        m = min(chunk, steps - a)
        for k in range(m):
            t = a + k
            if t % 8 == 0:
                inten = pattern_intensity(t, height, width, speed_px=speed_px)
            pot += inten
            s = pot >= 1.0
            pot -= s
            buf[k] = s
        out[a : a + m] = pack_frames(buf[:m].view(np.uint8))
    meta = {"gain": 0.6, "scene": "pattern", "seed": seed, "speed_px_per_step": speed_px}
    return SpikeRecording(out, lay, meta=meta)
