"""Per-pixel gain (threshold spread): measured from a flat field, divided out of every output.

A spike pixel integrates its light and fires at its own threshold, so its long-run rate is
``g[y, x] * r`` where ``r`` is the rate the nominal pixel would have (SPCS, Zhao et al. 2022,
eq. 1: a spike when the integral reaches the threshold; ``g`` is the nominal threshold over
this pixel's, times its relative light-to-charge gain). On a still part of a scene only the
product ``g * r`` reaches the stream: the gain and the texture cannot be told apart from the
spikes alone, so the gain is measured once, from a **flat field** (a recording of uniform
light): ``g = count / median(count)`` over the pixels the defect map does not flag.

The correction is the same for every method, offline and live: a method's output rate
(spikes/step) is divided by ``g`` (:func:`flatten`). A flagged pixel takes its donor's spikes
(:mod:`cfsr.defects.correct`), so its gain is its good neighbours' median.

The gain travels with the defect map (:class:`~cfsr.defects.DefectMap`, field ``gain``): in a
recording's sidecar and in a calibration file, as ``{"scale", "data"}``: ``data`` is the
upright row-major image of ``round(g * scale)`` as little-endian uint16, zlib-compressed and
base64-encoded (about 1.6 bytes a pixel).
"""

from __future__ import annotations

import base64
import binascii
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["GainMap", "GAIN_RANGE", "gain_from_counts", "flatten", "inverse_gain"]

#: Gains outside this range are no threshold spread but a broken pixel (the defect map's
#: business) or a flat field that is not flat; they are clipped to it.
GAIN_RANGE = (0.25, 4.0)
#: uint16 steps per unit gain in the stored form (a resolution of 6e-5, far below the spread).
_SCALE = 1 << 14


@dataclass(frozen=True, eq=False)
class GainMap:
    """Relative gain of every pixel: its rate over the nominal pixel's, upright float32 (H, W).

    ``steps``: flat-field steps it was measured over (1 step = 25 us).
    """

    gain: np.ndarray
    steps: int = 0

    def __post_init__(self) -> None:
        g = np.asarray(self.gain, np.float32)
        if g.ndim != 2 or not np.isfinite(g).all():
            raise ValueError(f"gain map must be a finite (H, W) image, got shape {g.shape}")
        object.__setattr__(self, "gain", np.clip(g, *GAIN_RANGE).astype(np.float32))

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.gain.shape[0]), int(self.gain.shape[1]))

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (see module)."""
        q = np.round(self.gain.astype(np.float64) * _SCALE).astype("<u2")
        data = base64.b64encode(zlib.compress(q.tobytes(), 6)).decode("ascii")
        return {"scale": _SCALE, "steps": int(self.steps), "data": data}

    @classmethod
    def from_dict(cls, obj: Any, shape: tuple[int, int], where: str = "gain map") -> GainMap:
        """Check a JSON form and build the map: ``shape`` (H, W) is the frame's; the decoded
        image must be exactly ``H * W`` uint16 (a larger stream is not inflated past that)."""
        if not isinstance(obj, dict) or set(obj) - {"scale", "steps", "data"}:
            raise ValueError(f"{where}: expected an object with scale, steps and data")
        scale, steps, data = obj.get("scale"), obj.get("steps", 0), obj.get("data")
        if not (isinstance(scale, int) and not isinstance(scale, bool) and 1 <= scale <= 1 << 15):
            raise ValueError(f"{where}: scale {scale!r}: an integer in [1, 32768]")
        if not (isinstance(steps, int) and not isinstance(steps, bool) and 0 <= steps <= 1 << 40):
            raise ValueError(f"{where}: steps {steps!r}: an integer in [0, 2**40]")
        if not isinstance(data, str):
            raise ValueError(f"{where}: data must be a base64 string")
        want = 2 * shape[0] * shape[1]
        try:
            z = zlib.decompressobj()
            raw = z.decompress(base64.b64decode(data, validate=True), want + 1)
        except (binascii.Error, ValueError, zlib.error) as exc:
            raise ValueError(f"{where}: data is not base64 zlib ({exc})") from None
        if len(raw) != want or z.unconsumed_tail:
            raise ValueError(f"{where}: data holds {len(raw)}+ bytes, the frame needs {want}")
        g = np.frombuffer(raw, "<u2").reshape(shape).astype(np.float32) / np.float32(scale)
        lo, hi = GAIN_RANGE
        if not ((g >= lo - 1.0 / scale) & (g <= hi + 1.0 / scale)).all():
            raise ValueError(f"{where}: a gain outside [{lo}, {hi}]")
        return cls(g, steps)


def gain_from_counts(counts: np.ndarray, steps: int, flagged: np.ndarray | None = None
                     ) -> GainMap:
    """The gain map of a flat field's upright spike ``counts`` (H, W) over ``steps`` steps:
    each pixel's count over the median count of the pixels not ``flagged`` (hot or dead);
    a flagged pixel gets the median gain of its good 8 neighbours (it takes a neighbour's
    spikes), or 1 with none. ValueError when the flat field is too dark to measure (under
    100 spikes a pixel: 1 % of resolution)."""
    c = np.asarray(counts, np.float64)
    bad = np.zeros(c.shape, bool) if flagged is None else np.asarray(flagged, bool)
    good = c[~bad]
    ref = float(np.median(good)) if good.size else 0.0
    if ref < 100:
        raise ValueError(f"flat field too dark or too short: median {ref:.0f} spikes a pixel "
                         f"over {steps} steps, at least 100 needed")
    g = c / ref
    if bad.any():
        h, w = c.shape
        pad = np.pad(np.where(bad, np.nan, g), 1, constant_values=np.nan)
        for y, x in zip(*np.nonzero(bad), strict=True):
            near = pad[y : y + 3, x : x + 3]
            g[y, x] = float(np.nanmedian(near)) if np.isfinite(near).any() else 1.0
    return GainMap(g, int(steps))


def inverse_gain(gain: GainMap | None) -> np.ndarray | None:
    """``1 / g`` as float32 (H, W), what :func:`flatten` multiplies by; None without a map."""
    return None if gain is None else (np.float32(1.0) / gain.gain).astype(np.float32)


def flatten(out: Any, inv: np.ndarray | None, method: Any = None) -> Any:
    """A method's :class:`~cfsr.methods.registry.Output` with its rate divided by the gain
    (``inv`` = :func:`inverse_gain`), clipped to 1 spike/step; ``out`` itself when ``inv`` is
    None. The rate is spikes/step, linear in the pixel's own; where ``method`` (a
    :class:`~cfsr.methods.registry.Method`) builds a pixel from other pixels' spikes (its
    ``borrowed_mask``, when the output has it), the pixel is left as it is: those pixels'
    gains average out, its own does not apply."""
    if inv is None:
        return out
    from dataclasses import replace

    rate = np.minimum(np.asarray(out.rate, np.float32) * inv, np.float32(1.0))
    borrowed = out.masks.get(getattr(method, "borrowed_mask", None) or "")
    if borrowed is not None:
        rate = np.where(borrowed, np.asarray(out.rate, np.float32), rate)
    return replace(out, rate=rate)
