"""Grey-level textures from the images bundled with scikit-image (offline; no download).

Every texture is float32 in [0, 1]. Only images that ship inside the scikit-image wheel are
used (``camera``, ``brick``, ``coffee``, ``grass``, ``gravel``, ``astronaut``, ...), so the
simulator never touches the network (``pooch`` is not needed).
"""

from __future__ import annotations

from functools import cache, lru_cache

import numpy as np

__all__ = ["BUNDLED", "texture"]

#: Bundled scikit-image images usable as textures.
BUNDLED = ("astronaut", "brick", "camera", "clock", "coffee", "grass", "gravel", "rocket")


@cache
def _grey(name: str) -> np.ndarray:
    if name not in BUNDLED:
        raise ValueError(f"unknown texture {name!r}; available: {', '.join(BUNDLED)}")
    import skimage.data

    img = np.asarray(getattr(skimage.data, name)())
    if img.ndim == 3:
        rgb = img[..., :3].astype(np.float32)
        img = rgb @ np.array([0.299, 0.587, 0.114], np.float32)  # ITU-R 601 luma
    out = np.asarray(img, np.float32) / 255.0
    out.setflags(write=False)
    return out


@lru_cache(maxsize=64)
def _texture(name: str, height: int, width: int, lo: float, hi: float) -> np.ndarray:
    import cv2

    src = _grey(name)
    sh, sw = src.shape
    # Crop to the target aspect ratio (centre), then resize: no stretching.
    target = width / height
    if sw / sh > target:
        cw = max(1, round(sh * target))
        x0 = (sw - cw) // 2
        src = src[:, x0 : x0 + cw]
    else:
        ch = max(1, round(sw / target))
        y0 = (sh - ch) // 2
        src = src[y0 : y0 + ch]
    interp = cv2.INTER_AREA if src.shape[0] >= height else cv2.INTER_CUBIC
    img = cv2.resize(np.ascontiguousarray(src), (width, height), interpolation=interp)
    img = np.clip(img, 0.0, 1.0) * np.float32(hi - lo) + np.float32(lo)
    out = np.ascontiguousarray(img, dtype=np.float32)
    out.setflags(write=False)
    return out


def texture(name: str, height: int, width: int, *, lo: float = 0.0, hi: float = 1.0) -> np.ndarray:
    """A bundled image as a ``(height, width)`` float32 texture with values in ``[lo, hi]``.

    The image is converted to grey (ITU-R 601 luma), centre-cropped to the requested aspect
    ratio, resized, then mapped linearly from [0, 1] to ``[lo, hi]``. Results are cached and
    read-only.
    """
    if height < 1 or width < 1:
        raise ValueError(f"texture size must be positive, got {height} x {width}")
    if not 0.0 <= lo <= hi <= 1.0:
        raise ValueError(f"need 0 <= lo <= hi <= 1, got lo={lo}, hi={hi}")
    return _texture(name, int(height), int(width), float(lo), float(hi))
