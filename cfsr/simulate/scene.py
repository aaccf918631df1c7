"""A simulated scene: a static background plus moving layers, renderable at any step.

Intensity is the normalised scene radiance in [0, 1] at the pixel centre. The true motion mask
at step ``t`` marks every pixel a moving object covers, even partly (coverage > 0): exactly
the pixels whose intensity the moving objects affect at ``t``. Rendering only touches the
region of interest (ROI) that moving layers can reach; the rest of the frame is the
background.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from cfsr.simulate.layers import Layer

__all__ = ["Scene"]



class Scene:
    """A scene: static background plus moving layers, renderable at any step.

    Attributes
    ----------
    name : str
    height, width : int
        Frame size (pixels).
    background : ndarray (H, W) float32
        Static part of the scene, intensity in [0, 1].
    layers : list of Rotor or Slider
        Moving objects, composited in order.
    illumination : float
        Relative light level (1.0 normal; ``lowlight`` and ``dim`` use 0.1). The simulator
        multiplies its gain by it, so intensities stay normalised to [0, 1] while firing rates
        drop.
    noise : str, mapping or None
        The scene's default sensor noise (a :class:`cfsr.simulate.Noise` spec, e.g.
        ``"sensor"`` for the ``noisy`` scene); the simulator uses it when no noise is given
        (an explicit noise, ``"none"`` included, replaces it). None: an ideal sensor.
    roi : (y0, y1, x0, x1)
        Bounding box of everything the layers can cover; empty for a static scene.
    """

    def __init__(
        self,
        name: str,
        background: np.ndarray,
        layers: Sequence[Layer] = (),
        *,
        illumination: float = 1.0,
        noise: str | dict[str, float] | None = None,
        summary: str = "",
        info: dict[str, Any] | None = None,
    ) -> None:
        bg = np.ascontiguousarray(background, dtype=np.float32)
        if bg.ndim != 2:
            raise ValueError(f"background must be (H, W), got shape {bg.shape}")
        if not 0.0 < illumination <= 1.0:
            raise ValueError(f"illumination must be in (0, 1], got {illumination}")
        self.name = name
        self.background = np.clip(bg, 0.0, 1.0)
        self.layers = list(layers)
        self.illumination = float(illumination)
        self.noise = noise
        self.summary = summary
        self.info = dict(info or {})
        h, w = self.background.shape
        boxes = [ly.bbox(h, w) for ly in self.layers]
        boxes = [b for b in boxes if b[1] > b[0] and b[3] > b[2]]
        if boxes:
            self.roi = (
                min(b[0] for b in boxes),
                max(b[1] for b in boxes),
                min(b[2] for b in boxes),
                max(b[3] for b in boxes),
            )
        else:
            self.roi = (0, 0, 0, 0)

    @property
    def height(self) -> int:
        return int(self.background.shape[0])

    @property
    def width(self) -> int:
        return int(self.background.shape[1])

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def moving(self) -> bool:
        """True if anything in the scene moves."""
        y0, y1, x0, x1 = self.roi
        return y1 > y0 and x1 > x0

    def render_roi(
        self, t0: int, n: int, *, coverage: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Intensity of the ROI at steps ``t0 .. t0+n-1``: ``(n, rh, rw)`` float32 in [0, 1].

        Also returns the coverage of moving objects (same shape, float32 0..1) when
        ``coverage``, else an empty ``(0, 0, 0)`` array.
        """
        y0, y1, x0, x1 = self.roi
        dyn = np.empty((n, y1 - y0, x1 - x0), np.float32)
        dyn[:] = self.background[y0:y1, x0:x1]
        cov = np.zeros(dyn.shape, np.float32) if coverage else np.zeros((0, 0, 0), np.float32)
        if dyn.size:
            for layer in self.layers:
                layer.render(int(t0), n, dyn, cov, y0, x0)
            np.clip(dyn, 0.0, 1.0, out=dyn)
        return dyn, cov

    def intensity_and_mask(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth intensity (float32 (H, W) in [0, 1]) and motion mask at step ``t``."""
        img = self.background.copy()
        mask = np.zeros(self.shape, bool)
        if self.moving:
            y0, y1, x0, x1 = self.roi
            dyn, cov = self.render_roi(int(t), 1, coverage=True)
            img[y0:y1, x0:x1] = dyn[0]
            mask[y0:y1, x0:x1] = cov[0] > 0.0
        return img, mask

    def intensity(self, t: int) -> np.ndarray:
        """Ground-truth intensity at step ``t``: float32 ``(H, W)`` in [0, 1]."""
        return self.intensity_and_mask(t)[0]

    def motion_mask(self, t: int) -> np.ndarray:
        """Pixels covered (even partly) by a moving object at step ``t`` (bool ``(H, W)``)."""
        return self.intensity_and_mask(t)[1]

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "summary": self.summary,
            "height": self.height,
            "width": self.width,
            "illumination": self.illumination,
            "noise": self.noise,
            "moving": self.moving,
            "roi": list(self.roi),
            "layers": [ly.describe() for ly in self.layers],
            **self.info,
        }

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, {self.width}x{self.height}, layers={len(self.layers)})"
