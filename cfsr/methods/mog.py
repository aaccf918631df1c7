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
  :mod:`cfsr.methods.cfsr_fine` for K and the stride).
* Background image. ``bgsegm`` MOG does not implement ``getBackgroundImage`` (OpenCV 4.x and
  5.x raise "not implemented"), so B is the per-pixel mean of the history frames in which MOG
  labelled the pixel background (the mean of its dominant mode), and the temporal median of the
  history where MOG never did.

OpenCV is imported lazily here, so ``import cfsr`` does not load it.
"""

from __future__ import annotations

import numpy as np

from cfsr._jit import njit

__all__ = ["to_u8", "mog_background", "mog_objects"]


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
