"""Mask morphology shared by the coarse and the fine distinction.

A per-pixel motion test marks where a pixel's spikes *changed*; a moving object's flat interior
does not change and is left out, and the test's misses scatter inside the object. Both the
steady-interval coarse mask (:mod:`cfsr.methods.cfsr.steady_distinction`) and CFSR's fine mask (the
union of coarse mask, MOG objects and DAISI edges, Eq. 8-14) therefore go through the same
regularisation: a closing with a square, hole filling, removal of small components, and an
optional dilation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cfsr._words import PackedWindow
from cfsr.methods.cfsr.mog import history_objects, to_u8
from cfsr.methods.cfsr.mog_two_sided import SharpRate, future_objects
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.cfsr.still_pixels import still_pixels

__all__ = ["fine_mask", "fine_region", "moving_objects", "regularise"]


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
    (:mod:`cfsr.methods.cfsr.still_pixels`). They leave the union before the closing and again after
    it (the closing bridges them back; the second hole filling returns those a mover encloses, small
    pieces left outside them are dropped by ``min_area``), and the dilation grows the
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


def moving_objects(
    src: PackedWindow,
    center: int,
    rates: np.ndarray,
    coarse: np.ndarray,
    sharp: SharpRate | None,
    s: CfsrSettings,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Eq. 8-9 on the CSR history ``rates`` (oldest first): the moving objects, and the
    ghosts (None: not tested) that the mirrored history after t tells apart
    (``mog_sides = both``)."""
    gain = s.mog_gain
    if gain <= 0:
        gain = float(np.percentile(rates[-1], 99.5)) if rates[-1].size else 1.0
        if not np.isfinite(gain) or gain <= 0:
            gain = 1.0
    u8 = to_u8(rates, gain)
    # one spike more or less in the MOG frames' window moves the 8-bit value by `quantum`
    # levels; in dark scenes that exceeds phi0 and Eq. 9 would mark noise, so phi0 is kept
    # at least two quanta (no effect at ordinary brightness: 16 levels at rate_scale 0.5)
    quantum = 255.0 / (s.mog_window * gain)
    phi0 = max(s.phi0, 2.0 * quantum)
    hist = s.mog_history or s.mog_frames
    objects = history_objects(u8, phi0, s.adaptive, s, hist, sharp, gain)
    match = phi0 * s.mog_match
    ghosts = None
    if sharp is not None and match > 0:  # a ghost matches the background after t
        # only objects outside the coarse mask can change the fine mask (the union is what
        # is regularised), so only they are tested
        cand = objects & ~coarse
        if cand.any():
            keep = future_objects(src, center, cand, sharp, gain, match, s.adaptive, s, hist)
            ghosts = cand & ~keep
            objects = (objects & coarse) | keep
    return objects, ghosts


def fine_region(
    src: PackedWindow,
    center: int,
    coarse: np.ndarray,
    objects: np.ndarray,
    edges: np.ndarray,
    ghosts: np.ndarray | None,
    tfp: np.ndarray,
    words: Any,
    s: CfsrSettings,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Step 4: ``(fine, region, left, tfp)``: the fine mask (the cues' union regularised,
    its still pixels left out), the region PatchMatch reconstructs (the mask before the still
    pixels, and the ghosts), the still pixels left out (None: none) and the static estimate
    with their run's rate there."""

    def cues(still: np.ndarray | None = None) -> np.ndarray:
        return fine_mask(
            coarse,
            objects,
            edges,
            close_size=s.close_size,
            min_area=s.min_area,
            dilate=s.dilate,
            still=still,
        )

    fine = cues()
    region = fine  # what PatchMatch reconstructs
    left = None  # still pixels the reported fine mask leaves out: their run's rate
    if s.still_reach > 0 and fine.any():
        # the still pixels among the mask's: background at t, proven by their own spikes
        still, still_rate = still_pixels(
            src,
            center,
            fine,
            reach=s.still_reach,
            min_run=s.still_run,
            jump=s.still_jump,
            words=words,
        )
        if still.any():
            fine = cues(still)
            # the still pixels it leaves out take their run's rate (exact over 64-760
            # steps); PatchMatch keeps its region (what it matches there is unchanged:
            # a region without them cost the fan's moving pixels 3.7 % more squared error)
            left = still & ~fine
            tfp = np.where(left, still_rate, tfp)
    if ghosts is not None:
        # the ghosts are background and leave the fine mask, but stay in the region
        # PatchMatch reconstructs (at zero motion it averages 33 TFI frames there): left to
        # the static estimate, the car lost 1.1 dB (docs/methods.md, "Two-sided objects")
        region = region | ghosts
    return fine, region, left, tfp
