"""Two-sided Eq. 9 (what this project adds beyond the paper, ``mog_sides = both``): the sharp
rate at t against the background of the history before t and of its mirror after t.

Eq. 9 against the past alone marks the background a mover left within the history (a *ghost*:
the history's background is the mover) and, on the MOG frame at t, the mover's 64-step trail.
Under ``both``, f is the span rule over ``mog_span`` centred steps at t (:class:`SharpRate`) and
an object must also lie further than ``mog_match * phi0`` from the background of the mirrored
history after t (:func:`future_objects`); docs/methods.md, "Two-sided objects".
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cfsr._words import PackedWindow
from cfsr.methods.cfsr._history_kernels import crop_counts
from cfsr.methods.cfsr.mog import bounding_box, mog_background, mog_objects, mog_settings, to_u8
from cfsr.methods.cfsr.settings import CfsrSettings

__all__ = ["SharpRate", "future_objects"]


class SharpRate(NamedTuple):
    """Eq. 9's f under ``mog_sides = both``: the span rule over ``span`` centred steps at t
    (``rate``), where t's interval (``isi``, steps) is shorter than the span; the MOG frame
    at t (``frame``) elsewhere, where the span holds fewer than two spikes (its TFI cost the
    dim scene's fine IoU 0.05). Rates in spikes per step, (H, W)."""

    rate: np.ndarray
    isi: np.ndarray
    frame: np.ndarray
    span: int

    def u8(self, box: tuple[int, int, int, int], gain: float) -> np.ndarray:
        """f on the crop ``box = (y0, y1, x0, x1)`` on MOG's 8-bit scale (:func:`to_u8`)."""
        y0, y1, x0, x1 = box
        r = np.where(
            self.isi[y0:y1, x0:x1] < self.span,
            self.rate[y0:y1, x0:x1],
            self.frame[y0:y1, x0:x1],
        )
        return to_u8(r, gain)


def future_objects(
    src: PackedWindow,
    center: int,
    cand: np.ndarray,
    sharp: SharpRate,
    gain: float,
    match: float,
    adaptive: bool,
    s: CfsrSettings,
    hist: int,
) -> np.ndarray:
    """The candidate objects ``cand`` that are not ghosts by the **mirrored history**.

    The mirrored history: TFP frames (Eq. 4) over ``[t + k * s, t + k * s + mog_window)``, ``s =
    mog_future_stride``, ``k = mog_future_frames - 1 .. 0``, fed to a fresh MOG farthest first
    (time reversed, so the last frame is the one at t; frames past the window's end dropped),
    its background B as :func:`cfsr.methods.cfsr.mog.mog_background`'s. A ghost -- background that a
    mover uncovered within the history before t, which that history's B still holds as the
    mover -- is background for the whole history after t: where the sharp rate at t lies
    within ``match`` levels (half of phi0 by default) of this B the pixel is a ghost. A pixel
    the mover covers at t lies near neither background, except by chance on a moving texture,
    hence the tighter ``match``.

    The frames are counted on the packed bytes of the candidates' bounding box (the whole
    frame when not ``adaptive``), and MOG, which models every pixel on its own, runs on the
    candidates alone, gathered into one row: its cost follows their number.
    """
    n = src.n
    win, stride = s.mog_window, s.mog_future_stride
    starts = [
        center + k * stride
        for k in range(s.mog_future_frames - 1, -1, -1)
        if center + k * stride + win <= n
    ]
    if not starts:  # no frame after t in the window: no ghost can be told
        return cand.copy()
    box = bounding_box(cand, adaptive)
    y0, y1, x0, x1 = box
    sel = cand[y0:y1, x0:x1]
    # per row, the columns from its first to its last candidate (none: the row is skipped)
    rows = sel.any(axis=1)
    xa = np.where(rows, x0 + sel.argmax(axis=1), x0).astype(np.int64)
    xb = np.where(rows, x1 - sel[:, ::-1].argmax(axis=1), x0).astype(np.int64)
    counts = crop_counts(
        src.packed,
        src.geo,
        min(starts),
        max(starts) + win,
        np.asarray(starts, np.int64),
        win,
        y0,
        x0,
        xa,
        xb,
        np.zeros((len(starts), y1 - y0, x1 - x0), np.int32),
    )
    frames = to_u8(counts[:, sel].astype(np.float32) / np.float32(win), gain)
    _, background = mog_background(frames[:, None, :], **mog_settings(s, hist))
    keep = np.zeros_like(cand)
    keep[y0:y1, x0:x1][sel] = mog_objects(sharp.u8(box, gain)[sel], background[0], match)
    return keep
