"""Full-reference metrics: PSNR and SSIM (whole frame or inside a mask), and mask IoU.

Images are compared in display units: 8-bit grey levels 0..255 by default (``data_range``),
i.e. after the named rate-to-display step (:func:`cfsr.to_display`), as the CFSR paper and the
spike-camera toolkits do.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["psnr", "ssim", "mask_iou"]


def _check_pair(ref: np.ndarray, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(ref)
    b = np.asarray(img)
    if a.ndim != 2 or b.ndim != 2:
        raise ValueError(f"images must be 2-D grey images, got shapes {a.shape} and {b.shape}")
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: ref {a.shape}, img {b.shape}")
    if a.size == 0:
        raise ValueError("images are empty")
    a = a.astype(np.float64, copy=False)
    b = b.astype(np.float64, copy=False)
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError("images hold NaN or Inf values")
    return a, b


def _check_range(data_range: float) -> float:
    try:
        dr = float(data_range)
    except (TypeError, ValueError):
        raise ValueError(f"data_range must be a number, got {data_range!r}") from None
    if not (math.isfinite(dr) and dr > 0):
        raise ValueError(f"data_range must be positive and finite, got {data_range!r}")
    return dr


def _check_mask(mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray | None:
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(f"mask shape {m.shape} differs from image shape {shape}")
    if m.dtype != np.bool_:
        if not np.isin(m, (0, 1)).all():
            raise ValueError("mask must be boolean (or 0/1)")
        m = m.astype(bool)
    if not m.any():
        raise ValueError(
            "mask selects no pixels: the metric is undefined on an empty region "
            "(check mask.any() first)"
        )
    return m


def psnr(
    ref: np.ndarray,
    img: np.ndarray,
    *,
    data_range: float = 255,
    mask: np.ndarray | None = None,
) -> float:
    """Peak signal-to-noise ratio of ``img`` against ``ref``, in dB.

    Parameters
    ----------
    ref, img : ndarray (H, W)
        Reference (ground truth) and test image, in display units (grey levels).
    data_range : float, keyword-only
        Peak value of the images' range in the same units (default 255 for 8-bit display).
    mask : ndarray of bool (H, W), keyword-only, optional
        Compute the mean squared error over these pixels only (e.g. the true motion region).

    Returns
    -------
    float
        ``10 log10(data_range**2 / MSE)`` in dB. ``inf`` when the images are identical on the
        evaluated pixels (MSE = 0), as in ``skimage.metrics.peak_signal_noise_ratio``.

    Raises
    ------
    ValueError
        Shapes differ, non-finite values, ``data_range <= 0``, or ``mask`` selects no pixels
        (an empty region has no error to measure; test ``mask.any()`` first).

    Notes
    -----
    MSE is computed in float64. Constant images are fine (no division by their variance).

    Examples
    --------
    >>> import numpy as np
    >>> ref = np.zeros((4, 4)); img = np.full((4, 4), 10.0)
    >>> round(psnr(ref, img), 4)  # MSE = 100
    28.1308
    """
    a, b = _check_pair(ref, img)
    dr = _check_range(data_range)
    m = _check_mask(mask, a.shape)
    d = a - b
    mse = float(np.mean(d[m] ** 2)) if m is not None else float(np.mean(d * d))
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(dr * dr / mse)


def ssim(
    ref: np.ndarray,
    img: np.ndarray,
    *,
    data_range: float = 255,
    mask: np.ndarray | None = None,
    win_size: int | None = None,
    gaussian_weights: bool = False,
) -> float:
    """Structural similarity of ``img`` to ``ref`` (mean SSIM), whole frame or inside a mask.

    Parameters
    ----------
    ref, img : ndarray (H, W)
        Reference and test image in display units (grey levels), at least 7 x 7 pixels.
    data_range : float, keyword-only
        Peak value of the images' range (default 255).
    mask : ndarray of bool (H, W), keyword-only, optional
        Average the SSIM map over these pixels only.
    win_size : int, optional
        Odd side of the local window (default 7, scikit-image's default).
    gaussian_weights : bool
        Use a Gaussian window (sigma 1.5) as Wang et al. instead of a uniform one.

    Returns
    -------
    float
        Mean of the SSIM map in [-1, 1]: over the frame minus a border of ``(win_size-1)//2``
        pixels (exactly ``skimage.metrics.structural_similarity``), or over the mask pixels
        inside that border (over all mask pixels if the mask lies only in the border).
        Identical images give 1.0, constant images included.

    Raises
    ------
    ValueError
        Shapes differ, non-finite values, ``data_range <= 0``, image smaller than the window,
        or an empty ``mask``.

    References
    ----------
    Z. Wang, A. C. Bovik, H. R. Sheikh and E. P. Simoncelli, "Image quality assessment: from
    error visibility to structural similarity", IEEE TIP 13(4), 2004.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.arange(100.0).reshape(10, 10)
    >>> ssim(x, x)
    1.0
    """
    from skimage.metrics import structural_similarity

    a, b = _check_pair(ref, img)
    dr = _check_range(data_range)
    m = _check_mask(mask, a.shape)
    ws = 7 if win_size is None else int(win_size)
    if gaussian_weights and win_size is None:
        ws = 11
    if ws < 3 or ws % 2 == 0:
        raise ValueError(f"win_size must be odd and >= 3, got {win_size}")
    if min(a.shape) < ws:
        raise ValueError(f"images of shape {a.shape} are smaller than the {ws} x {ws} window")
    kw = {"sigma": 1.5, "use_sample_covariance": False} if gaussian_weights else {}
    mean, smap = structural_similarity(
        a,
        b,
        data_range=dr,
        full=True,
        win_size=ws,
        gaussian_weights=gaussian_weights,
        **kw,
    )
    if m is None:
        return float(mean)
    pad = (ws - 1) // 2
    inner = np.zeros_like(m)
    inner[pad : m.shape[0] - pad, pad : m.shape[1] - pad] = True
    sel = m & inner
    if not sel.any():
        sel = m
    return float(np.mean(smap[sel], dtype=np.float64))


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks.

    Parameters
    ----------
    a, b : ndarray of bool, same shape
        E.g. a method's dynamic-pixel mask and the true motion mask.

    Returns
    -------
    float
        ``|a & b| / |a | b|`` in [0, 1]. Two empty masks agree perfectly: 1.0 (a static scene
        where the method marks nothing dynamic). One empty, one not: 0.0.

    Examples
    --------
    >>> import numpy as np
    >>> mask_iou(np.array([1, 1, 0, 0], bool), np.array([0, 1, 1, 0], bool))
    0.3333333333333333
    """
    x = np.asarray(a)
    y = np.asarray(b)
    if x.shape != y.shape:
        raise ValueError(f"masks differ in shape: {x.shape} and {y.shape}")
    for name, v in (("a", x), ("b", y)):
        if v.dtype != np.bool_ and v.size and not np.isin(v, (0, 1)).all():
            raise ValueError(f"mask {name} must be boolean (or 0/1)")
    x = x.astype(bool, copy=False)
    y = y.astype(bool, copy=False)
    union = int(np.count_nonzero(x | y))
    if union == 0:
        return 1.0
    return int(np.count_nonzero(x & y)) / union
