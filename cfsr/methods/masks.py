"""Mask morphology shared by the coarse and the fine distinction.

A per-pixel motion test marks where a pixel's spikes *changed*; a moving object's flat interior
does not change and is left out, and the test's misses scatter inside the object. Both the
steady-interval coarse mask (:mod:`cfsr.methods.steady`) and CFSR's fine mask (the union of
coarse mask, MOG objects and DAISI edges, Eq. 8-14) therefore go through the same
regularisation: a closing with a square, hole filling, removal of small components, and an
optional dilation.
"""

from __future__ import annotations

import numpy as np

__all__ = ["regularise", "fine_mask"]


def regularise(
    mask: np.ndarray, *, close_size: int = 9, min_area: int = 16, dilate: int = 0
) -> np.ndarray:
    """``mask`` closed with a ``close_size`` square (pixels; <= 1: no closing), holes filled,
    components under ``min_area`` pixels dropped, grown by ``dilate`` pixels (a disk).

    Runs on the mask's bounding box plus a margin the closing and the dilation cannot cross
    (and one pixel of background, so hole filling sees the same outside): the same result as
    on the whole frame, at the cost of the moving area only.
    """
    m = np.asarray(mask, bool)
    if not m.any():
        return m.copy()
    ys, xs = np.nonzero(m.any(axis=1))[0], np.nonzero(m.any(axis=0))[0]
    pad = max(0, int(close_size)) + max(0, int(dilate)) + 2
    h, w = m.shape
    y0, y1 = max(0, ys[0] - pad), min(h, ys[-1] + pad + 1)
    x0, x1 = max(0, xs[0] - pad), min(w, xs[-1] + pad + 1)
    out = np.zeros((h, w), bool)
    out[y0:y1, x0:x1] = _regularise_crop(m[y0:y1, x0:x1], close_size, min_area, dilate)
    return out


def fine_mask(
    coarse: np.ndarray,
    objects: np.ndarray,
    edges: np.ndarray,
    *,
    close_size: int = 9,
    min_area: int = 16,
    dilate: int = 0,
    still: np.ndarray | None = None,
) -> np.ndarray:
    """Fine dynamic mask: the union of the cues (coarse mask, MOG objects, DAISI edges),
    :func:`regularise`\\ d ("the edges refine the object mask").

    ``still`` (bool ``(H, W)``, optional): pixels proven static at t
    (:mod:`cfsr.methods.still`). They leave the union before the closing and again after it
    (the closing bridges them back; the second hole filling returns those a mover encloses,
    small pieces left outside them are dropped by ``min_area``), and the dilation grows the
    mask only into pixels that are not still: the safety margin is for pixels the cues could
    not place, not for proven background.
    """
    m = np.asarray(coarse, bool) | np.asarray(objects, bool) | np.asarray(edges, bool)
    if still is None or not still.any():
        return regularise(m, close_size=close_size, min_area=min_area, dilate=dilate)
    still = np.asarray(still, bool)
    core = regularise(m & ~still, close_size=close_size, min_area=min_area)
    core = regularise(core & ~still, close_size=0, min_area=min_area)
    if dilate > 0 and core.any():
        grown = regularise(core, close_size=0, min_area=0, dilate=dilate)
        core |= grown & ~still
    return core


def _regularise_crop(m: np.ndarray, close_size: int, min_area: int, dilate: int) -> np.ndarray:
    import cv2

    m = np.asarray(m, bool)
    if close_size > 1:
        # outside the frame is background: OpenCV's erosion treats the border as foreground,
        # which would glue anything within close_size / 2 of the edge to it
        c = int(close_size)
        k = np.ones((c, c), np.uint8)
        padded = np.pad(m.astype(np.uint8), c)
        m = cv2.morphologyEx(padded, cv2.MORPH_CLOSE, k)[c:-c, c:-c] > 0
    m = _fill_holes(m)
    if min_area > 1 and m.any():
        # 4-connected components, as scipy.ndimage.label's default structure
        n, lab, stats, _ = cv2.connectedComponentsWithStats(m.astype(np.uint8), connectivity=4)
        keep = stats[:, cv2.CC_STAT_AREA] >= int(min_area)
        keep[0] = False
        m = keep[lab]
    if dilate > 0 and m.any():
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(dilate) + 1,) * 2)
        m = cv2.dilate(m.astype(np.uint8), k) > 0
    return m


def _fill_holes(m: np.ndarray) -> np.ndarray:
    """Background not 4-connected to the outside becomes foreground (the result of
    ``scipy.ndimage.binary_fill_holes``, by one flood fill from a one-pixel frame)."""
    import cv2

    h, w = m.shape
    bg = np.ones((h + 2, w + 2), np.uint8)  # 1: background, the frame included
    bg[1:-1, 1:-1] = ~m
    flood = np.zeros((h + 4, w + 4), np.uint8)
    cv2.floodFill(bg, flood, (0, 0), 2, flags=4)
    return bg[1:-1, 1:-1] != 2
