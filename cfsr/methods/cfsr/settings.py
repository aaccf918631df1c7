"""CFSR's typed settings (:class:`CfsrSettings`): the parameters one frame runs with, under its
quality tier, read by every stage of the pipeline (:mod:`cfsr.methods.cfsr.pipeline`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

from cfsr.methods.cfsr.coarse import CoarseSettings, CsrSettings, DynamicEstimator, tfi_dynamic
from cfsr.methods.cfsr.params import MogSides, Quality
from cfsr.methods.cfsr.slow_motion_windows import SlowSettings
from cfsr.methods.cfsr.tiers import effective_params
from cfsr.methods.registry import MethodSettings, Params
from cfsr.methods.tfp import RateRule

__all__ = ["CfsrSettings", "pm_offsets"]


@dataclass(frozen=True)
class CfsrSettings(CoarseSettings, SlowSettings):
    """CFSR's parameters as one frame runs with them (its ``quality`` tier applied,
    :func:`effective_params`): the coarse stage's
    (:class:`~cfsr.methods.cfsr.coarse.CoarseSettings`), the slow-motion stage's
    (:class:`~cfsr.methods.cfsr.slow_motion_windows.SlowSettings`) and the fine stage's below.
    Meaning, unit and range of each: :data:`FINE_PARAMS`, :data:`CSR_PARAMS`.
    """

    mog_frames: int  #: CSR history frames K, ending at t
    mog_stride: int  #: steps between history frames
    mog_window: int  #: TFP window of the history frames, steps
    mog_estimator: RateRule
    mog_history: int  #: MOG history length, frames (0: mog_frames)
    mog_mixtures: int
    mog_ratio: float
    mog_noise: float  #: 8-bit levels (0: OpenCV's default)
    mog_gain: float  #: spikes/step shown as 255 (0: auto)
    mog_sides: MogSides
    mog_span: int  #: steps
    mog_future_frames: int
    mog_future_stride: int  #: steps
    mog_match: float  #: fraction of phi0
    still_reach: int  #: steps (0: no still-pixel proof)
    still_run: int  #: steps
    still_jump: float
    phi0: float  #: 8-bit levels (Eq. 9)
    phi: float  #: natural log ratio (Eq. 14)
    daisi_span: int  #: steps
    close_size: int  #: pixels
    min_area: int  #: pixels
    dilate: int  #: pixels
    pm_step: int  #: steps
    pm_count: int  #: frames on each side of t
    pm_far_count: int  #: frames on each side beyond the pm_count ones
    pm_far_step: int  #: steps between the far frames
    pm_patch: int  #: pixels
    pm_iters: int
    pm_radius: int  #: pixels
    pm_guide: int  #: intervals (0: the TFI)
    pm_sigma: float  #: pixels (0: none)
    pm_h: float  #: spikes/step (0: plain average)
    quality: Quality  #: already applied
    carry_span: int  #: steps (0: no carried work)
    carry_gap: int  #: steps
    adaptive: bool
    static_tol: int  #: spikes (-1: gate off)
    static_tile: int  #: pixels (0: whole frame only)
    static_window: int  #: steps

    @classmethod
    def of(cls, p: Params | MethodSettings) -> CfsrSettings:
        """A settings object as it is, else the resolved parameters ``p`` under their
        ``quality`` tier (:func:`effective_params`)."""
        if isinstance(p, cls):
            return p
        if isinstance(p, MethodSettings):
            return super().of(p)
        return super().of(effective_params(p))

    @cached_property
    def coarse(self) -> CsrSettings:
        """The coarse parameters for :mod:`cfsr.methods.cfsr.coarse`'s rules: CFSR has no dynamic
        estimator of its own there (its fine stage reconstructs the dynamic region)."""
        return tfi_dynamic(self)

    @cached_property
    def sharp(self) -> CsrSettings:
        """:attr:`coarse` with the span rule over ``mog_span`` centred steps at t as the
        dynamic estimate: Eq. 9's sharp rate under ``mog_sides = both``."""
        return replace(
            self.coarse, dynamic_estimator=DynamicEstimator.STEADY, dynamic_span=self.mog_span
        )

    @cached_property
    def pm_offsets(self) -> tuple[int, ...]:
        """Steps from t of the PatchMatch frames on each side, ascending: ``pm_step * i`` for
        ``i = 1..pm_count``, then ``pm_far_count`` more ``pm_far_step`` apart beyond them."""
        return pm_offsets(self)

    @property
    def two_sided(self) -> bool:
        """Whether Eq. 9 tests the sharp rate at t against both backgrounds (``mog_sides``)."""
        return self.mog_sides == MogSides.BOTH

    @cached_property
    def carry_key(self) -> CfsrSettings:
        """These settings but for the carry rule's own: outputs under another key carry
        nothing from one to the next."""
        return replace(self, carry_span=0, carry_gap=1)


def pm_offsets(s: CfsrSettings) -> tuple[int, ...]:
    """Steps from t of the PatchMatch frames on each side, ascending (Eq. 12's neighbouring
    frames): ``pm_step * i`` for ``i = 1..pm_count``, then ``pm_far_count`` more
    ``pm_far_step`` apart beyond them."""
    step, count = s.pm_step, s.pm_count
    near = [step * i for i in range(1, count + 1)]
    end = near[-1] if near else 0
    far = s.pm_far_step
    return (*near, *(end + far * j for j in range(1, s.pm_far_count + 1)))
