"""No-reference metrics used on real data (CFSR paper, Table 1): STD and CPBD.

Both reward contrast and sharp edges, and both also reward noise: a noisy TFI frame scores
"sharper" than the ground truth (see ``notes/components.md``, section 2). Never report them
alone; on simulated data report them next to PSNR/SSIM against ground truth.

CPBD here is our own implementation of the published algorithm:

    N. D. Narvekar and L. J. Karam, "A No-Reference Image Blur Metric Based on the Cumulative
    Probability of Blur Detection (CPBD)", IEEE Transactions on Image Processing 20(9),
    pp. 2678-2683, 2011.

It follows the structure of the authors' reference software ("CPBD Sharpness Metric Software",
Image, Video and Usability Lab, Arizona State University, http://ivulab.asu.edu/Quality/CPBD),
which is to be cited as above whenever results computed with it are reported. No code of that
software or of the ``cpbd`` PyPI package is copied here.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from cfsr._jit import njit

__all__ = ["std_metric", "cpbd"]


def _grey_image(img: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim != 2:
        raise ValueError(f"{what} needs a 2-D grey image, got shape {a.shape}")
    if a.size == 0:
        raise ValueError(f"{what}: image is empty")
    a = a.astype(np.float64, copy=False)
    if not np.isfinite(a).all():
        raise ValueError(f"{what}: image holds NaN or Inf values")
    return a


def std_metric(img: np.ndarray) -> float:
    """STD: standard deviation of the image's grey levels (a no-reference contrast measure).

    Parameters
    ----------
    img : ndarray (H, W)
        Reconstructed image in display units, grey levels 0..255 (e.g. ``cfsr.to_display``).

    Returns
    -------
    float
        ``sqrt(mean((img - mean(img))**2))`` over all pixels (population standard deviation,
        in grey levels). Higher means more contrast / detail; 0.0 for a constant image.

    Notes
    -----
    This is the STD of the CFSR paper's Table 1 as used in the spike-camera reconstruction
    literature: the global standard deviation of the reconstructed image's grey levels,
    reported on real captures where no ground truth exists (higher is better). It measures
    contrast, not fidelity: noise raises it too, so report it beside PSNR/SSIM or CPBD.

    Examples
    --------
    >>> import numpy as np
    >>> std_metric(np.array([[0, 255], [0, 255]]))
    127.5
    """
    a = _grey_image(img, "std_metric")
    return float(np.std(a))


# --------------------------------------------------------------------------- CPBD

_BLOCK = 64  # block side (pixels)
_EDGE_BLOCK_FRACTION = 0.002  # a block is an edge block if > 0.2 % of its pixels are edges
_BETA = 3.6  # slope of the psychometric function
_P_JNB = 63  # cumulative probability taken at P_JNB = 63 % (histogram buckets 0..63)
_SOBEL_THRESHOLD = 2.0  # grey levels per pixel (normalised Sobel) for vertical edges
_MAX_WIDTH_SEARCH = 100  # pixels searched each side of an edge


@njit(parallel=True)
def _edge_widths(img, edges, out):  # pragma: no cover - numba
    """Marziliano edge widths along rows at the given (vertical) edge pixels.

    For an edge pixel whose gradient direction is horizontal (quantised to 0 or 180 degrees),
    walk left and right from the pixel to the local extrema of the row profile; the width is
    the distance between them (in pixels). Other pixels get 0.
    """
    h, w = img.shape
    for r in prange(1, h - 1):
        for c in range(1, w - 1):
            out[r, c] = 0.0
            if not edges[r, c]:
                continue
            # np.gradient: central differences inside the image
            gx = 0.5 * (img[r, c + 1] - img[r, c - 1])
            gy = 0.5 * (img[r + 1, c] - img[r - 1, c])
            if gx == 0.0 and gy != 0.0:
                continue  # purely vertical gradient: not a vertical edge
            ang = math.atan2(gy, gx) * (180.0 / math.pi) if gx != 0.0 else 0.0
            q = ang / 45.0
            q = math.floor(q + 0.5) if q >= 0 else -math.floor(-q + 0.5)  # round half away
            q *= 45.0
            if q == 0.0:
                rising = True  # intensity increases to the right
            elif q == 180.0 or q == -180.0:
                rising = False
            else:
                continue
            # right side: follow the profile while it keeps going the same way
            k = 0
            while k <= _MAX_WIDTH_SEARCH:
                a = c + 1 + k
                b = c + 2 + k
                if b > w - 1:
                    break
                d = img[r, b] - img[r, a]
                if (rising and d <= 0.0) or ((not rising) and d >= 0.0):
                    break
                k += 1
            right = min(k, _MAX_WIDTH_SEARCH) + 1
            # left side
            k = 0
            while k <= _MAX_WIDTH_SEARCH:
                a = c - 1 - k
                b = c - 2 - k
                if b < 0:
                    break
                d = img[r, b] - img[r, a]
                if (rising and d >= 0.0) or ((not rising) and d <= 0.0):
                    break
                k += 1
            left = min(k, _MAX_WIDTH_SEARCH) + 1
            out[r, c] = left + right
    return out


def _vertical_sobel_edges(a: np.ndarray) -> np.ndarray:
    """Thinned vertical edges: |normalised horizontal Sobel| > 2 grey levels, local maxima."""
    from scipy.ndimage import correlate

    kx = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0
    b = correlate(a, kx, mode="nearest") ** 2
    e = b > _SOBEL_THRESHOLD**2
    # thinning: strict local maximum of the response along x or along y
    left = np.pad(b, ((0, 0), (1, 0)), mode="edge")[:, :-1]
    right = np.pad(b, ((0, 0), (0, 1)), mode="edge")[:, 1:]
    up = np.pad(b, ((1, 0), (0, 0)), mode="edge")[:-1, :]
    down = np.pad(b, ((0, 1), (0, 0)), mode="edge")[1:, :]
    return e & (((left < b) & (right < b)) | ((up < b) & (down < b)))


def _canny_edges(a: np.ndarray) -> np.ndarray:
    """Canny edges with MATLAB-like automatic thresholds (sigma sqrt 2, 70 % non-edges)."""
    from scipy.ndimage import gaussian_filter, sobel
    from skimage.feature import canny

    x = a / 255.0
    sigma = math.sqrt(2.0)
    sm = gaussian_filter(x, sigma, mode="nearest")
    mag = np.hypot(sobel(sm, axis=0), sobel(sm, axis=1))
    high = float(np.percentile(mag, 70.0))
    if not high > 0.0:
        return np.zeros(a.shape, bool)
    return canny(x, sigma=sigma, low_threshold=0.4 * high, high_threshold=high, mode="nearest")


def cpbd(img: np.ndarray) -> float:
    """CPBD: cumulative probability of blur detection (no-reference sharpness, 0..1).

    Parameters
    ----------
    img : ndarray (H, W)
        Grey image in display units, 0..255 (uint8 or float).

    Returns
    -------
    float
        Fraction of the edges in edge blocks whose probability of blur detection is at most
        ``P_JNB = 63 %``; higher means sharper. 0.0 when the image has no edge block (e.g. a
        constant image, or one smaller than 64 x 64 pixels): no sharp edge was detected.

    Notes
    -----
    Steps (Narvekar & Karam 2011):

    1. Canny edges (sigma sqrt(2), high threshold at the 70th percentile of the gradient
       magnitude, low = 0.4 x high) decide which 64 x 64 blocks are edge blocks (more than
       0.2 % edge pixels). Blocks are tiled from the top-left; the remainder is ignored.
    2. Vertical edges from the normalised horizontal Sobel (threshold 2 grey levels, thinned)
       get widths ``w`` by the Marziliano method: the distance between the local extrema of
       the row profile on each side (numba kernel).
    3. Per edge block, the just-noticeable-blur width is ``w_JNB = 5`` if the block contrast
       ``max - min <= 50`` grey levels, else 3; each edge's probability of blur detection is
       ``P = 1 - exp(-(w / w_JNB) ** 3.6)``.
    4. CPBD is the fraction of all those edges with ``round(100 P) <= 63``.

    CPBD rewards noise (noise creates narrow "edges"); never report it alone.

    References
    ----------
    N. D. Narvekar and L. J. Karam, "A No-Reference Image Blur Metric Based on the Cumulative
    Probability of Blur Detection (CPBD)", IEEE TIP 20(9), 2011.

    P. Marziliano, F. Dufaux, S. Winkler and T. Ebrahimi, "A no-reference perceptual blur
    metric", ICIP 2002.

    Examples
    --------
    >>> import numpy as np
    >>> cpbd(np.full((128, 128), 100.0))
    0.0
    """
    a = _grey_image(img, "cpbd")
    if a.min() < 0.0 or a.max() > 255.0:
        raise ValueError(
            f"cpbd expects grey levels 0..255, got values in [{a.min():g}, {a.max():g}]"
        )
    h, w = a.shape
    nby, nbx = h // _BLOCK, w // _BLOCK
    if nby == 0 or nbx == 0 or h < 3 or w < 3:
        return 0.0
    a = np.ascontiguousarray(a)
    canny_edges = _canny_edges(a)
    widths = _edge_widths(a, _vertical_sobel_edges(a), np.zeros((h, w), np.float64))
    hist = np.zeros(101, np.int64)
    for i in range(nby):
        for j in range(nbx):
            sl = (slice(i * _BLOCK, (i + 1) * _BLOCK), slice(j * _BLOCK, (j + 1) * _BLOCK))
            if np.count_nonzero(canny_edges[sl]) <= _BLOCK * _BLOCK * _EDGE_BLOCK_FRACTION:
                continue
            bw = widths[sl]
            bw = bw[bw > 0]
            if bw.size == 0:
                continue
            block = a[sl]
            contrast = int(math.floor(float(block.max() - block.min())))
            w_jnb = 5.0 if contrast <= 50 else 3.0
            p = 1.0 - np.exp(-(np.abs(bw / w_jnb) ** _BETA))
            buckets = np.floor(p * 100.0 + 0.5).astype(np.int64)  # round half up (p >= 0)
            hist += np.bincount(buckets, minlength=101)[:101]
    total = int(hist.sum())
    if total == 0:
        return 0.0
    return float(hist[: _P_JNB + 1].sum() / total)
