"""Server-side rendering of the newest frame for PNG and MJPEG clients (the browser viewer
renders its own from the WebSocket message)."""

from __future__ import annotations

import io

import numpy as np

from cfsr_live.service.frameslot import SlotFrame
from cfsr_live.service.schema import MASK_ALPHA, mask_color

__all__ = ["render_rgb", "encode_png", "encode_jpeg", "HEAT_LUT"]


def _heat_lut() -> np.ndarray:
    # a perceptual dark-to-bright map (inferno-like anchors), 256 x RGB; the viewer takes
    # this very table from GET /api/schema
    anchors = np.array(
        [
            [0, 0, 4],
            [40, 11, 84],
            [101, 21, 110],
            [159, 42, 99],
            [212, 72, 66],
            [245, 125, 21],
            [250, 193, 39],
            [252, 255, 164],
        ],
        np.float64,
    )
    x = np.linspace(0, 1, len(anchors))
    t = np.linspace(0, 1, 256)
    return np.stack([np.interp(t, x, anchors[:, c]) for c in range(3)], 1).astype(np.uint8)


HEAT_LUT = _heat_lut()


def render_rgb(
    f: SlotFrame, *, view: str = "gray", overlays: tuple[str, ...] = ()
) -> np.ndarray:
    """``(H, W, 3)`` uint8: the image (gray, or the firing-rate heat map) plus mask tints."""
    if view == "heat":
        rgb = HEAT_LUT[f.image]
    elif view == "gray":
        rgb = np.repeat(f.image[:, :, None], 3, axis=2)
    else:
        raise ValueError(f"view must be 'gray' or 'heat', got {view!r}")
    rgb = rgb.astype(np.float32)
    for name in overlays:
        m = f.masks.get(name)
        if m is None:
            continue
        col = np.array(mask_color(name), np.float32)
        sel = m.astype(bool)
        rgb[sel] = (1 - MASK_ALPHA) * rgb[sel] + MASK_ALPHA * col
    return np.clip(rgb, 0, 255).astype(np.uint8)


def _encode(rgb: np.ndarray, fmt: str, **kw) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format=fmt, **kw)
    return buf.getvalue()


def encode_png(rgb: np.ndarray) -> bytes:
    return _encode(rgb, "PNG", compress_level=1)


def encode_jpeg(rgb: np.ndarray, quality: int = 85) -> bytes:
    return _encode(rgb, "JPEG", quality=quality)
