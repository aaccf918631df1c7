"""The live configuration as typed values, from the HTTP handler to the worker process.

Three frozen dataclasses, each validated when it is made and then passed on as is:

* :class:`DisplayScale`: how rates become 8-bit pixels (gain mode and gain);
* :class:`LiveConfig`: what the user chose (method and parameters as a
  :class:`cfsr.config.MethodConfig`, display scale, frame-rate cap); the runtime stores one
  and :meth:`LiveConfig.changed` makes the next from a partial update, a
  :class:`ConfigChange`;
* :class:`WorkerConfig`: what the worker needs of it (the effective gain resolved against
  the current source), sent over the process queue and answered by ``version``.

Why dataclasses and not the HTTP models: the same values come from the command line
(``cfsr serve --method --max-fps``) and from HTTP, and the worker must not depend on
the web stack's model classes; the HTTP models (:mod:`cfsr_live.service.models`) take their bounds
from the same constants, for the OpenAPI document.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from cfsr.config import MethodConfig
from cfsr_live.service.settings import MAX_FPS_RANGE

__all__ = [
    "GAIN_MODES",
    "ConfigChange",
    "DisplayScale",
    "GainMode",
    "LiveConfig",
    "QUALITIES",
    "Quality",
    "TIER_PARAM",
    "WorkerConfig",
    "refuse_tier_param",
    "check_max_fps",
]

GainMode = Literal["recording", "auto", "fixed"]
#: CFSR's tier in the live service: auto (full when max_fps allows it, fast frames between),
#: or the method's own quality parameter fixed
Quality = Literal["auto", "full", "fast"]
QUALITIES: tuple[Quality, ...] = ("auto", "full", "fast")
#: the method parameter the live tier sets (CFSR's, full or fast; a method without it has
#: no tiers)
TIER_PARAM = "quality"
#: recording: the source's display gain if it has one, else auto; auto: per frame; fixed: gain
GAIN_MODES: tuple[GainMode, ...] = ("recording", "auto", "fixed")


@dataclass(frozen=True)
class DisplayScale:
    """Display gain: the firing rate (spikes/step) shown as white, or how to choose it."""

    gain_mode: GainMode = "recording"
    gain: float | None = None

    def __post_init__(self) -> None:
        if self.gain_mode not in GAIN_MODES:
            raise ValueError(
                f"display gain_mode {self.gain_mode!r}: use recording, auto or fixed"
            )
        g = self.gain
        if g is not None and (
            isinstance(g, bool)
            or not isinstance(g, int | float)
            or not (math.isfinite(g) and 0 < g <= 1)
        ):
            raise ValueError(f"display gain must be in (0, 1] spikes/step, got {g!r}")
        if self.gain_mode == "fixed" and not g:
            raise ValueError("display gain_mode 'fixed' needs a gain (spikes/step)")

    def changed(self, changes: Mapping[str, Any]) -> DisplayScale:
        """This scale with the given fields replaced (``None`` values keep the old ones)."""
        keep = {"gain_mode": self.gain_mode, "gain": self.gain}
        keep.update({k: v for k, v in changes.items() if v is not None})
        return DisplayScale(**keep)

    def effective_gain(self, source_gain: float | None) -> float | None:
        """The gain the worker uses (None: automatic per frame), given the source's own."""
        if self.gain_mode == "fixed" and self.gain:
            return float(self.gain)
        if self.gain_mode == "recording" and source_gain:
            return float(source_gain)
        return None


def check_max_fps(max_fps: float) -> float:
    """``max_fps`` as a float within :data:`~cfsr_live.service.settings.MAX_FPS_RANGE`, else
    ValueError (written so that NaN fails too: every comparison with NaN is false)."""
    lo, hi = MAX_FPS_RANGE
    v = float(max_fps)
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ValueError(f"max_fps must be in [{lo}, {hi}] frames/s, got {max_fps}")
    return v


@dataclass(frozen=True)
class ConfigChange:
    """A partial update of the live configuration (``PUT /api/config``, checked for shape
    by the HTTP model); ``None`` keeps a value. :meth:`LiveConfig.changed` validates it."""

    method: str | None = None
    params: Mapping[str, Any] | None = None
    display: Mapping[str, Any] | None = None
    max_fps: float | None = None
    defects: bool | None = None
    #: CFSR's live tier (auto, full, fast); None keeps it (auto after a change of method)
    quality: Quality | None = None

    def __post_init__(self) -> None:
        refuse_tier_param(self.params)


def refuse_tier_param(params: Mapping[str, Any] | None) -> None:
    """ValueError when method ``params`` hold CFSR's tier (:data:`TIER_PARAM`): in the live
    service the tier is the configuration's own field (:attr:`LiveConfig.quality`, where
    ``auto`` lives), and the method's parameter follows it. Offline the parameter is the
    method's own (``cfsr reconstruct --param quality=fast``)."""
    if params is not None and TIER_PARAM in params:
        raise ValueError(
            f"parameter {TIER_PARAM}={repr(params[TIER_PARAM])[:32]}: the live tier is the "
            "configuration's own field 'quality' (auto, full or fast: PUT /api/config "
            '{"quality": "auto"}, cfsr serve --quality), not a method parameter'
        )


@dataclass(frozen=True)
class LiveConfig:
    """The service's configuration: method, display scale, frame-rate cap, and CFSR's tier
    (``quality``: auto, the live default, picks full or fast per frame to hold ``max_fps``;
    methods without a ``quality`` parameter ignore it; ``defects``: correct hot and dead
    pixels, and a calibration's gain, before every method (cfsr.defects)).

    The tier is this object's field, the one place ``auto`` lives; the method's own
    ``quality`` parameter follows it (full under auto, which runs both tiers from full)."""

    method: MethodConfig
    display: DisplayScale = field(default_factory=DisplayScale)
    max_fps: float = 30.0
    quality: Quality = "auto"
    defects: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_fps", check_max_fps(self.max_fps))
        if self.quality not in QUALITIES:
            raise ValueError(f"quality {self.quality!r}: use auto, full or fast")
        want = "full" if self.quality == "auto" else self.quality
        if self.method.params.get(TIER_PARAM, want) != want:
            object.__setattr__(self, "method", self.method.replace(params={TIER_PARAM: want}))

    @classmethod
    def make(
        cls,
        method: str,
        params: Mapping[str, Any] | None = None,
        display: DisplayScale | None = None,
        max_fps: float = 30.0,
        quality: Quality = "auto",
    ) -> LiveConfig:
        """A configuration from a method name, its parameters and the tier (the service's
        start: ``cfsr serve --method --quality`` and the settings' parameters); ValueError
        for a tier among the parameters (:func:`refuse_tier_param`)."""
        refuse_tier_param(params)
        return cls(MethodConfig(method, params), display or DisplayScale(), max_fps, quality)

    def changed(self, change: ConfigChange) -> LiveConfig:
        """The next configuration after the partial update ``change``, all or nothing
        (ValueError naming the first bad value; this one is unchanged). Parameters not given
        keep their values, except on a change of method, which starts from its defaults
        (and CFSR's tier from auto)."""
        new_method = (
            change.method is not None and change.method.strip().lower() != self.method.method
        )
        q = change.quality or ("auto" if new_method else self.quality)
        m = self.method.replace(method=change.method, params=change.params)
        d = self.display if change.display is None else self.display.changed(change.display)
        return LiveConfig(m, d, self.max_fps if change.max_fps is None else change.max_fps, q,
                          self.defects if change.defects is None else bool(change.defects))

    def public(self) -> dict[str, Any]:
        """The JSON shape of ``GET /api/config`` (without the effective gain): the method's
        parameters less the tier, which is ``quality`` (None for a method without tiers), so
        that what is read can be sent back."""
        params = dict(self.method.params)
        tiers = params.pop(TIER_PARAM, None) is not None
        return {
            "method": self.method.method,
            "params": params,
            "quality": self.quality if tiers else None,
            "display": {"gain_mode": self.display.gain_mode, "gain": self.display.gain},
            "max_fps": self.max_fps,
            "defects": self.defects,
        }


@dataclass(frozen=True)
class WorkerConfig:
    """One configuration of the worker process; ``version`` is issued by the supervisor and
    comes back in the worker's answer (applied or rejected)."""

    method: MethodConfig
    gain: float | None = None  # spikes/step shown as white; None: automatic per frame
    max_fps: float = 30.0
    deterministic: bool = False  # read every ring block (replay mode unpaced, tests)
    version: int = 0
    #: CFSR's tier: its own ``quality`` parameter (full, fast), or auto: full when the
    #: frame rate allows it, fast frames between (methods without the parameter: ignored)
    quality: Quality = "auto"
    #: correct hot/dead pixels (and divide a calibration's gain out) before every method;
    #: False: the map is still learnt, the spikes go to the methods as they came
    defects: bool = True
    #: the source's own defect map (its sidecar's, JSON form of cfsr.defects.DefectMap):
    #: the correction starts from it, then from the map learnt in the stream
    defect_map: Mapping[str, Any] | None = None
