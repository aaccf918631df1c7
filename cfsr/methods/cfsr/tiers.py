"""CFSR's quality tiers (what this project adds beyond the paper): named sets of settings
that trade accuracy for CPU, chosen on the measured Pareto front (docs/methods.md, "Quality
tiers"), and how a frame's parameters take its tier.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cfsr.methods.cfsr.coarse import CSR_PARAMS
from cfsr.methods.cfsr.params import FINE_PARAMS, MogSides, Quality
from cfsr.methods.registry import Params

if TYPE_CHECKING:
    from cfsr.config import MethodConfig

__all__ = ["QUALITY_TIERS", "effective_params", "fast_config"]


#: What each ``quality`` tier changes (docs/methods.md, "Quality tiers"). ``fast`` is the
#: cheapest point measured by ``cfsr bench --tiers`` that stays within 0.5 dB (whole frame) and
#: 1.0 dB (motion region) of ``full`` on every simulator scene.
QUALITY_TIERS: dict[Quality, Params] = {
    Quality.FULL: {},
    Quality.FAST: {
        # the same reach of history (~380 steps) in 4 frames instead of 12, and the paper's
        # Eq. 9 on the past alone (no mirrored history after t): no scene moved by 0.1 dB
        "mog_frames": 4,
        "mog_stride": 96,
        "mog_sides": MogSides.PAST,
        # a 200-step distinction window and a 300-step still-pixel reach: within 0.05 dB
        "T": 200,
        "still_reach": 300,
        # the first PatchMatch target's full search from 8 pixels instead of 16 (no scene
        # moved), and 17 PatchMatch targets a side instead of 24: 15 two steps apart, then 2
        # nine apart (t +- 2, ..., 30, 39, 48: the same 48-step reach for the slow pan, full's
        # spacing near t for the turning disk). 16 x 3 fell 0.53 dB behind full on the small
        # disk of tests/test_cfsr_tiers.py, 20 x 2 0.68 on the pan, 16 x 2 + 40, 48 cost 6 %
        "pm_radius": 8,
        "pm_count": 15,
        "pm_far_count": 2,
        "pm_far_step": 9,
    },
}


_DEFAULTS = {k: prm.default for k, prm in {**CSR_PARAMS, **FINE_PARAMS}.items()}


def effective_params(p: Params) -> Params:
    """The parameters one frame runs with: ``p`` with its ``quality`` tier's settings
    (:data:`QUALITY_TIERS`) in place of the values left at their defaults. A parameter set to
    any other value keeps it (a value equal to the default cannot be told from an unset one:
    the tier replaces it). ``full`` returns ``p`` itself."""
    tier = QUALITY_TIERS[Quality(p.get("quality", Quality.FULL))]
    if not tier:
        return p
    return {**p, **{k: v for k, v in tier.items() if p.get(k, _DEFAULTS[k]) == _DEFAULTS[k]}}


def fast_config(cfg: MethodConfig) -> MethodConfig:
    """The ``fast`` tier of a CFSR :class:`~cfsr.config.MethodConfig` (its other parameters
    kept); a config of another method is returned as it is."""
    if cfg.method != "cfsr":
        return cfg
    return cfg.replace(params={"quality": Quality.FAST})
