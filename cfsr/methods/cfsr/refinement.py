"""The fine reconstruction's PatchMatch refinement (CFSR paper, fine stage): the TFI at t
refined by matching every fine-region pixel's patch in the TFI frames around t and averaging.

This module runs the stage on a window: the frames and guides on the tiles within reach of the
region (:mod:`cfsr.methods.cfsr.patchmatch_frames`), the search and the averaging
(:mod:`cfsr.methods.cfsr.patchmatch`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cfsr._words import PackedWindow
from cfsr.methods.cfsr.patchmatch import finish_padding, padded_guides, patchmatch_fuse
from cfsr.methods.cfsr.patchmatch_frames import TILE, match_reach, pm_frames, pm_tiles
from cfsr.methods.cfsr.settings import CfsrSettings

__all__ = ["patchmatch_refine"]


def patchmatch_refine(
    src: PackedWindow,
    center: int,
    seed: int,
    region: np.ndarray,
    used: np.ndarray,
    s: CfsrSettings,
    bank: dict[str, Any] | None = None,
) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """Step 5: the TFI at t refined by PatchMatch (Eq. 3 + the paper's patch averaging) on
    ``region`` (adaptive: TFI frames and guides only on the tiles within a patch's reach of
    it), averaged on ``used``. Returns ``(refined, (y0, x0), domain)``: the refined rates of
    the crop at ``(y0, x0)`` and the crop's pixels they hold. ``bank``: the PatchMatch frames
    carried within a group of outputs (:func:`cfsr.methods.cfsr.patchmatch_frames.pm_frames`)."""
    h, w, n = src.h, src.w, src.n
    if s.adaptive:
        # a match reaching beyond the computed tiles reads NaN and is never taken (pm_frames);
        # one tile more than a pixel's own patch reads at zero motion leaves room for the
        # motion (with none, the blades' moving pixels lost 0.11 dB; docs/methods.md)
        reach = match_reach(s.pm_patch, s.pm_sigma) + TILE
        tiles = pm_tiles(region, reach)
        ty, tx = np.nonzero(tiles)
        y0, y1 = ty.min() * TILE, min(h, (ty.max() + 1) * TILE)
        x0, x1 = tx.min() * TILE, min(w, (tx.max() + 1) * TILE)
        domain = region[y0:y1, x0:x1]
    else:
        # frames and guides on the whole frame, but PatchMatch on the region alone, as the
        # adaptive pipeline: the temporal schedule searches blocks of the matched pixels of a
        # row (their end pixels' predictions, their distinct bests, their neighbours'
        # offsets), so matching the pixels outside the region too changed the candidates of
        # the region's edge pixels, and with them the ghosts' rates outside the fine mask
        # (0.6 % at one pixel with pm_count 24 x pm_step 2); their matches were never used
        y0, y1, x0, x1 = 0, h, 0, w
        tiles = None
        domain = region
    # the reference t first, then t -+ each offset inside the window
    tcs = [center] + [c for d in s.pm_offsets for c in (center - d, center + d) if 0 <= c < n]
    # the guides go straight into the buffer the search reads (no padded copy of every frame)
    padded, view = padded_guides(len(tcs), int(y1 - y0), int(x1 - x0), s.pm_patch)
    raw, guides = pm_frames(
        src,
        tcs,
        (int(y0), int(y1), int(x0), int(x1)),
        s,
        tiles,
        guide_out=view,
        bank=bank,
        shift=seed - center,
    )
    finish_padding(padded, s.pm_patch)
    refined = patchmatch_fuse(
        raw[0],
        guides[0],
        raw[1:],
        guides[1:],
        domain,
        wanted=used[y0:y1, x0:x1],
        patch=s.pm_patch,
        iters=s.pm_iters,
        max_radius=s.pm_radius,
        h=s.pm_h,
        seed=seed,
        origin=(int(y0), int(x0)),
        # temporal schedule: each target starts from the motion predicted by the nearer ones
        offsets_steps=[c - center for c in tcs[1:]],
        padded=padded,
    )
    return refined, (int(y0), int(x0)), domain
