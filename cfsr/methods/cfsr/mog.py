"""MOG background subtraction over consecutive CSR frames (CFSR paper Eq. 8-9).

The paper runs a Gaussian-mixture background model (MOG, Kaewtrakulpong & Bowden 2001; OpenCV
contrib ``cv2.bgsegm.createBackgroundSubtractorMOG``) over the stream of CSR frames, takes its
background image B and marks moving objects where the current frame departs from it:

.. math::  D'(x) = 1 \\text{ if } |f_t(x) - B(x)| \\ge \\varphi_0   (Eq. 8-9)

with f and B on the 8-bit display scale (phi0 = 50 in the paper).

Two readings, forced by what the library offers and by purity:

* History inside the window. A MOG model is stateful; to keep every method a pure function of
  its spike window (so offline random access and the streaming path give the same frame), the
  model is rebuilt for every output from K CSR frames at a fixed stride before t (see
  :mod:`cfsr.methods.cfsr.pipeline` for K and the stride).
* Background image. ``bgsegm`` MOG does not implement ``getBackgroundImage`` (OpenCV 4.x and
  5.x raise "not implemented"), so B is the per-pixel mean of the history frames in which MOG
  labelled the pixel background (the mean of its dominant mode), and the temporal median of the
  history where MOG never did.

OpenCV is imported lazily here, so ``import cfsr`` does not load it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from cfsr._jit import njit
from cfsr.methods.cfsr.settings import CfsrSettings

if TYPE_CHECKING:  # the two-sided test builds on this module
    from cfsr.methods.cfsr.mog_two_sided import SharpRate

__all__ = [
    "bounding_box",
    "history_objects",
    "mog_background",
    "mog_objects",
    "mog_settings",
    "to_u8",
]


@njit
def _u8_kernel(r, scale, out):  # pragma: no cover - numba
    for i in range(r.size):
        v = r[i]
        if np.isnan(v) or v < 0:  # NaN and -inf are dark
            out[i] = 0
        else:  # +inf is the gain itself: 255
            q = np.rint(v * scale)
            out[i] = 255 if not q < 255 else np.uint8(q)
    return out


def to_u8(rates: np.ndarray, gain: float) -> np.ndarray:
    """Rates (spikes/step) to the 8-bit scale MOG works on: ``clip(rint(rate / gain * 255))``.

    NaN and negative rates give 0, ``+inf`` gives 255; a non-positive or non-finite ``gain``
    falls back to 1. One pass (the MOG history is 12 frames per output).
    """
    g = float(gain) if np.isfinite(gain) and gain > 0 else 1.0
    r = np.ascontiguousarray(rates, dtype=np.float32)
    out = np.empty(r.shape, np.uint8)
    _u8_kernel(r.reshape(-1), np.float32(255.0 / g), out.reshape(-1))
    return out


def mog_background(
    frames: np.ndarray,
    *,
    history: int = 20,
    nmixtures: int = 3,
    background_ratio: float = 0.7,
    noise_sigma: float = 0.0,
    learning_rate: float = -1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Run MOG over ``frames`` (oldest first) and return its last mask and background image.

    Parameters
    ----------
    frames : ndarray (K, H, W) uint8
        History frames ending with the current one (8-bit display scale).
    history, nmixtures, background_ratio, noise_sigma
        ``cv2.bgsegm.createBackgroundSubtractorMOG`` settings (history in frames; noise sigma
        in 8-bit levels, 0 = OpenCV's default 15).
    learning_rate : float
        Passed to ``apply``; negative = automatic (1 / frames seen, capped by ``history``).

    Returns
    -------
    foreground : ndarray (H, W) bool
        MOG's foreground mask of the last frame.
    background : ndarray (H, W) float32
        Background image B on the 8-bit scale (see module notes).
    """
    import cv2

    f = np.ascontiguousarray(frames, dtype=np.uint8)
    if f.ndim != 3 or f.shape[0] == 0:
        raise ValueError(f"frames must be (K, H, W) with K >= 1, got {f.shape}")
    sub = cv2.bgsegm.createBackgroundSubtractorMOG(
        int(history), int(nmixtures), float(background_ratio), float(noise_sigma)
    )
    fg = np.zeros(f.shape, bool)
    for k in range(f.shape[0]):
        fg[k] = sub.apply(f[k], learningRate=float(learning_rate)) > 0
    hist = f[:-1] if f.shape[0] > 1 else f
    bgm = ~fg[:-1] if f.shape[0] > 1 else np.ones(f.shape, bool)
    n_bg = bgm.sum(axis=0)
    s = np.where(bgm, hist, 0).sum(axis=0, dtype=np.float64)
    background = (s / np.maximum(n_bg, 1)).astype(np.float32)
    never = n_bg == 0  # the temporal median only where MOG never saw background (it is slow)
    if never.any():
        background[never] = np.median(hist[:, never], axis=0).astype(np.float32)
    return fg[-1], background


def mog_objects(current: np.ndarray, background: np.ndarray, phi0: float) -> np.ndarray:
    """Eq. 9: ``|f - B| >= phi0`` (8-bit levels), bool ``(H, W)``."""
    return np.abs(current.astype(np.float32) - background) >= np.float32(phi0)


def mog_settings(s: CfsrSettings, hist: int) -> dict[str, Any]:
    """:func:`cfsr.methods.cfsr.mog.mog_background`'s keywords from the settings (both MOGs)."""
    return {
        "history": hist,
        "nmixtures": s.mog_mixtures,
        "background_ratio": s.mog_ratio,
        "noise_sigma": s.mog_noise,
    }


def history_objects(
    u8: np.ndarray,
    phi0: float,
    adaptive: bool,
    s: CfsrSettings,
    hist: int,
    sharp: SharpRate | None = None,
    gain: float = 1.0,
):
    """Eq. 8-9 on the history ``u8`` (oldest first): ``|f - B| >= phi0`` with f the last
    history frame, or the sharp rate at t (``sharp``, put on the 8-bit scale with ``gain``).

    MOG models every pixel on its own, and its background B lies between the pixel's smallest
    and largest history value, so ``|f - B| >= phi0`` with f in the history is impossible where
    the history's range is below phi0. A sharp f outside the history could pass there, but
    such a pixel has not seen a mover in its history (its light changed only within the last
    few steps) and is left out too: f's noise would otherwise scatter objects, and the
    pixels MOG must run on, over the frame. The adaptive pipeline therefore runs MOG only on
    the pixels whose range reaches phi0 (none: no objects, MOG skipped), gathered into one
    row (as :func:`future_objects` does): the same objects, at a cost that follows their
    number rather than their bounding box's.
    """
    h, w = u8.shape[1:]
    varies = None
    if adaptive or sharp is not None:
        varies = (u8.max(axis=0).astype(np.int16) - u8.min(axis=0)) >= phi0
    settings = mog_settings(s, hist)
    if not adaptive:
        _, background = mog_background(u8, **settings)
        f = u8[-1] if sharp is None else sharp.u8((0, h, 0, w), gain)
        found = mog_objects(f, background, phi0)
        return found if sharp is None else found & varies
    if not varies.any():
        return np.zeros((h, w), bool)
    box = bounding_box(varies, True)
    y0, y1, x0, x1 = box
    sel = varies[y0:y1, x0:x1]
    # the history of the varying pixels alone, as one row (MOG models each pixel on its own)
    row = np.ascontiguousarray(u8[:, y0:y1, x0:x1][:, sel][:, None, :])
    _, background = mog_background(row, **settings)
    f = row[-1, 0] if sharp is None else sharp.u8(box, gain)[sel]
    objects = np.zeros((h, w), bool)
    objects[y0:y1, x0:x1][sel] = mog_objects(f, background[0], phi0)
    return objects


def bounding_box(mask: np.ndarray, adaptive: bool) -> tuple[int, int, int, int]:
    """The bounding box ``(y0, y1, x0, x1)`` of a non-empty ``mask`` (adaptive), or the frame."""
    if not adaptive:
        return 0, mask.shape[0], 0, mask.shape[1]
    ys, xs = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    return int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1
