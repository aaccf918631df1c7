"""The fusion (CFSR paper Eq. 7, the last stage): the PatchMatch-refined dynamic region fused
with the static estimate by ATSR (:mod:`cfsr.methods.cfsr.atsr`); the plain static estimate
where the fine region is empty.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from cfsr._words import PackedWindow
from cfsr.methods.cfsr.atsr import atsr_fuse
from cfsr.methods.cfsr.history import tfi_at
from cfsr.methods.cfsr.refinement import patchmatch_refine
from cfsr.methods.cfsr.settings import CfsrSettings

if TYPE_CHECKING:
    from cfsr.methods.cfsr.pipeline import Coarse, Masks

__all__ = ["Refined", "refine_stage"]


class Refined(NamedTuple):
    """Steps 5-6, the fine reconstruction (:func:`refine_stage`)."""

    rate: np.ndarray  #: float32 (H, W): spikes per step in [0, 1]
    used: np.ndarray | None  #: bool (H, W): where the refined rates were taken (None: none)


def refine_stage(
    src: PackedWindow,
    center: int,
    seed: int,
    coarse: Coarse,
    masks: Masks,
    s: CfsrSettings,
    bank: dict[str, Any] | None,
) -> Refined:
    """Steps 5-6: the TFI at t refined by PatchMatch on the fine region (adaptive: only on
    the tiles within a patch's reach of a fine-mask pixel), fused with the static estimate
    by ATSR (Eq. 7); the plain static estimate where the region is empty. The ATSR reads the
    refined rates on region & ~left only: the still pixels left out (and, always-full, the
    pixels outside the region) are matched but not averaged."""
    if s.adaptive and not masks.region.any():
        return Refined(np.clip(masks.tfp, 0.0, 1.0).astype(np.float32), None)
    used = masks.region if masks.left is None else masks.region & ~masks.left
    refined, (y0, x0), domain = patchmatch_refine(src, center, seed, masks.region, used, s, bank)
    if not masks.region.any():  # always-full pipeline on a static window: the same TFP output
        return Refined(np.clip(masks.tfp, 0.0, 1.0).astype(np.float32), None)
    # TFI at t (computed here when the history did not need it)
    tfi_full = coarse.tfi if coarse.tfi is not None else tfi_at(src, center, s.max_isi)
    dyn = tfi_full.copy()
    crop = dyn[y0 : y0 + domain.shape[0], x0 : x0 + domain.shape[1]]
    crop[domain] = refined[domain]
    rate, _ = atsr_fuse(dyn, masks.tfp, used, tfi=tfi_full)
    return Refined(rate, used)
