"""Fixed-pattern sensor noise and defects of the simulated spike camera (:class:`Noise`).

All maps are per pixel and drawn once from the seed (:class:`~cfsr.simulate.sensor.Sensor`);
shot noise is the one temporal term. Sources and what is ours: docs/methods.md ("Noise").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

__all__ = ["Noise", "NOISE_PRESETS"]

@dataclass(frozen=True)
class Noise:
    """Fixed-pattern sensor noise (all per pixel, drawn once from the seed).

    Parameters
    ----------
    threshold_sd : float
        Relative standard deviation of the per-pixel threshold (SPCS: 3/400 = 0.0075).
    gain_sd : float
        Relative standard deviation of the per-pixel gain (SPCS: 0.027).
    dark_rate : float
        Mean dark-current firing rate in spikes per step, i.e. the rate of a pixel in total
        darkness (SPCS: 1/400 = 0.0025).
    dark_sd : float
        Relative standard deviation of the per-pixel dark current (SPCS: 0.008).
    electrons_per_spike : float
        Temporal photon shot noise (ours, not in SPCS): the charge of one threshold counts
        this many photo-electrons, and each step's charge is a Poisson draw of its expected
        electron count (normal approximation above 12 per step). 0 (default) turns it off;
        the ``shot`` preset uses 100 (an illustrative value, not a measured one), giving an
        ISI jitter of about ``1/sqrt(100) = 10 %``. Expected rates are unchanged.
    hot_fraction : float
        Fraction of pixels that are *hot* (ours, not in SPCS): their dark current alone makes
        them fire at ``hot_rate`` times a uniform draw in [0.5, 1] spikes per step, whatever
        the light. Hot pixels are drawn once from the seed (``Sensor.hot_mask``); at least one
        pixel is hot when ``hot_fraction > 0``.
    hot_rate : float
        Dark firing rate of the hottest pixels in spikes per step (at most 1); required
        (> 0) with ``hot_fraction``.
    dead_fraction : float
        Fraction of pixels that are *dead* (never fire, whatever the light), drawn among the
        pixels that are not hot, after every other map (``Sensor.dead_mask``).
    """

    threshold_sd: float = 0.0
    gain_sd: float = 0.0
    dark_rate: float = 0.0
    dark_sd: float = 0.0
    electrons_per_spike: float = 0.0
    hot_fraction: float = 0.0
    hot_rate: float = 0.0
    dead_fraction: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"noise {f.name}={v!r}: must be a finite number >= 0")
        if self.threshold_sd >= 0.5:
            raise ValueError(f"noise threshold_sd={self.threshold_sd}: must be < 0.5 (relative)")
        if self.dark_rate >= 1:
            raise ValueError(f"noise dark_rate={self.dark_rate}: must be < 1 spike/step")
        if self.hot_fraction > 1:
            raise ValueError(f"noise hot_fraction={self.hot_fraction}: must be <= 1")
        if self.hot_fraction + self.dead_fraction > 1:
            raise ValueError("noise hot_fraction + dead_fraction must be <= 1")
        if self.hot_rate > 1:
            raise ValueError(f"noise hot_rate={self.hot_rate}: must be <= 1 spike/step")
        if self.hot_fraction > 0 and self.hot_rate <= 0:
            raise ValueError("noise hot_fraction > 0 needs hot_rate > 0 (spikes/step)")

    @property
    def is_zero(self) -> bool:
        return not any(getattr(self, f.name) for f in fields(self))

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @classmethod
    def parse(cls, spec: str | Mapping[str, Any] | Noise | None) -> Noise:
        """A preset name (``none``, ``spcs``, ``shot``, ``sensor``, ``defects``),
        ``"NAME=VALUE,..."`` (optionally after a preset, ``"spcs,dark_rate=0.01"``), a mapping,
        a Noise, or None (no noise)."""
        if spec is None:
            return cls()
        if isinstance(spec, Noise):
            return spec
        if isinstance(spec, Mapping):
            names = {f.name for f in fields(cls)}
            bad = sorted(set(spec) - names)
            if bad:
                raise ValueError(f"unknown noise parameter(s) {bad}; known: {sorted(names)}")
            return cls(**{k: float(v) for k, v in spec.items()})
        base: dict[str, float] = {}
        for part in str(spec).split(","):
            part = part.strip()
            if not part:
                continue
            if "=" in part:
                k, v = (s.strip() for s in part.split("=", 1))
                try:
                    base[k] = float(v)
                except ValueError:
                    raise ValueError(f"noise {k}={v!r}: not a number") from None
            elif part.lower() in NOISE_PRESETS:
                base.update(NOISE_PRESETS[part.lower()].to_dict())
            else:
                raise ValueError(
                    f"unknown noise preset {part!r}; presets: {', '.join(NOISE_PRESETS)}, "
                    "or NAME=VALUE with NAME in "
                    f"{', '.join(f.name for f in fields(cls))}"
                )
        return cls.parse(base)


NOISE_PRESETS: dict[str, Noise] = {
    "none": Noise(),
    "spcs": Noise(threshold_sd=3 / 400, gain_sd=0.027451, dark_rate=1 / 400, dark_sd=0.008),
    "shot": Noise(electrons_per_spike=100.0),
    # Fixed-pattern noise of a real sensor, for the ``noisy`` scene: SPCS's gain spread and
    # mean dark current, and our own choices for the rest (no published spike-camera values
    # verified): threshold mismatch 3 % (4x SPCS), per-pixel dark current spread 50 %, 0.1 %
    # hot pixels firing at 0.25-0.5 spikes/step.
    "sensor": Noise(
        threshold_sd=0.03,
        gain_sd=0.027451,
        dark_rate=1 / 400,
        dark_sd=0.5,
        hot_fraction=0.001,
        hot_rate=0.5,
    ),
    # A sensor with defects: 0.5 % hot pixels firing 0.125-0.25 spikes/step in the dark, 0.1 %
    # dead pixels and a 5 % threshold spread (our choices, as for ``sensor``).
    "defects": Noise(threshold_sd=0.05, hot_fraction=0.005, hot_rate=0.25, dead_fraction=0.001),
}

