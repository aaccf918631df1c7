"""The defect map: which pixels are hot or dead, how it was found, and how it is stored.

A :class:`DefectMap` is two upright boolean images (``hot``, ``dead``) with the number of steps
that produced it and where it came from. It travels as a small JSON object: in a recording's
sidecar under ``"defects"`` (so a replay starts corrected) or as a calibration file of its own
(:func:`save_map` / :func:`load_map`). Pixels are listed by their upright row-major index
``y * width + x``, so the object stays a few kilobytes for a few hundred defects.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cfsr.defects.gain import GainMap
from cfsr.sidecar import (
    MAX_SIDECAR_BYTES,
    _sidecar_dict,
    read_sidecar,
    sidecar_path,
    write_json_atomic,
)

__all__ = [
    "DefectMap",
    "DEFECTS_KEY",
    "MAX_DEFECT_FRACTION",
    "save_map",
    "load_map",
    "write_to_sidecar",
]

#: Key of the defect map in a recording's sidecar.
DEFECTS_KEY = "defects"
#: A map flagging more than this fraction of the pixels is refused: that is a broken sensor or
#: a broken file, and correcting it from neighbours would invent most of the image.
MAX_DEFECT_FRACTION = 0.05
_SOURCES = ("stream", "calibration", "simulator")


@dataclass(frozen=True)
class DefectMap:
    """Hot and dead pixels of one sensor geometry.

    Attributes
    ----------
    hot, dead : ndarray bool (H, W)
        Upright masks; a pixel is never both.
    steps : int
        Steps (1 step = 25 us) the estimate was built from (0 for a calibration file).
    source : str
        ``"stream"`` (estimated online), ``"calibration"`` (given from a file) or
        ``"simulator"`` (the simulator's true map).
    gain : GainMap, optional
        Every pixel's relative gain, measured on a flat field (:mod:`cfsr.defects.gain`);
        None: not measured (the stream alone cannot tell it from the scene's texture).
    """

    hot: np.ndarray
    dead: np.ndarray
    steps: int = 0
    source: str = "stream"
    gain: GainMap | None = None

    def __post_init__(self) -> None:
        hot = np.asarray(self.hot, bool)
        dead = np.asarray(self.dead, bool)
        if hot.ndim != 2 or hot.shape != dead.shape:
            raise ValueError(f"hot {hot.shape} and dead {dead.shape} must be one (H, W) shape")
        if self.source not in _SOURCES:
            raise ValueError(f"defect map source {self.source!r}: one of {_SOURCES}")
        if self.gain is not None and self.gain.shape != hot.shape:
            raise ValueError(f"gain map {self.gain.shape} and defects {hot.shape} differ")
        object.__setattr__(self, "hot", hot)
        object.__setattr__(self, "dead", dead & ~hot)

    @classmethod
    def empty(cls, shape: tuple[int, int], *, source: str = "stream") -> DefectMap:
        return cls(np.zeros(shape, bool), np.zeros(shape, bool), 0, source)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.hot.shape[0]), int(self.hot.shape[1]))

    @property
    def mask(self) -> np.ndarray:
        """Every flagged pixel (hot or dead), upright bool (H, W)."""
        return self.hot | self.dead

    @property
    def n_hot(self) -> int:
        return int(self.hot.sum())

    @property
    def n_dead(self) -> int:
        return int(self.dead.sum())

    def to_dict(self) -> dict[str, Any]:
        """The JSON form: ``{"width", "height", "steps", "source", "hot": [...], "dead":
        [...]}`` with upright row-major pixel indices, and ``"gain"`` when measured
        (:meth:`GainMap.to_dict`)."""
        h, w = self.shape
        out: dict[str, Any] = {
            "width": w,
            "height": h,
            "steps": int(self.steps),
            "source": self.source,
            "hot": np.flatnonzero(self.hot).tolist(),
            "dead": np.flatnonzero(self.dead).tolist(),
        }
        if self.gain is not None:
            out["gain"] = self.gain.to_dict()
        return out

    @classmethod
    def from_dict(cls, obj: Any, shape: tuple[int, int] | None = None,
                  where: str = "defect map") -> DefectMap:
        """Check a JSON form (from a sidecar or a file) and build the map.

        Every value from outside is checked here once: the geometry (equal to ``shape`` when
        given), the indices (integers inside the frame, no repeats) and their count (at most
        :data:`MAX_DEFECT_FRACTION` of the pixels). ValueError names ``where`` and the value.
        """
        if not isinstance(obj, dict):
            raise ValueError(f"{where}: expected a JSON object, found {type(obj).__name__}")
        unknown = sorted(set(obj) - {"width", "height", "steps", "source", "hot", "dead",
                                     "gain"})
        if unknown:
            raise ValueError(f"{where}: unknown field(s) {unknown}")
        w, h = obj.get("width"), obj.get("height")
        if not (_is_int(w) and _is_int(h) and 0 < w <= 65_535 and 0 < h <= 65_535):
            raise ValueError(f"{where}: width/height {w!r} x {h!r}: integers in [1, 65535]")
        if shape is not None and (h, w) != tuple(shape):
            raise ValueError(f"{where}: map is {w} x {h}, the recording {shape[1]} x {shape[0]}")
        steps = obj.get("steps", 0)
        if not (_is_int(steps) and 0 <= steps <= 1 << 40):
            raise ValueError(f"{where}: steps {steps!r}: an integer in [0, 2**40]")
        source = obj.get("source", "calibration")
        if source not in _SOURCES:
            raise ValueError(f"{where}: source {source!r}: one of {_SOURCES}")
        n = w * h
        cap = int(MAX_DEFECT_FRACTION * n) + 1
        masks = []
        for key in ("hot", "dead"):
            idx = obj.get(key, [])
            if not isinstance(idx, list) or len(idx) > cap:
                raise ValueError(f"{where}: {key} must be a list of at most {cap} pixel indices")
            if not all(_is_int(i) and 0 <= i < n for i in idx):
                raise ValueError(f"{where}: {key} holds an index outside 0..{n - 1}")
            m = np.zeros(n, bool)
            m[np.asarray(idx, np.int64)] = True
            if int(m.sum()) != len(idx):
                raise ValueError(f"{where}: {key} lists a pixel twice")
            masks.append(m.reshape(h, w))
        if (masks[0] & masks[1]).any():
            raise ValueError(f"{where}: a pixel is listed both hot and dead")
        if int(masks[0].sum() + masks[1].sum()) > cap:
            raise ValueError(f"{where}: more than {cap} defects ({MAX_DEFECT_FRACTION:.0%})")
        gain = obj.get("gain")
        if gain is not None:
            gain = GainMap.from_dict(gain, (h, w), where=f"{where}: gain")
        return cls(masks[0], masks[1], int(steps), str(source), gain)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def save_map(dmap: DefectMap, path: str | os.PathLike) -> Path:
    """Export ``dmap`` as a calibration file (JSON, the form :meth:`DefectMap.to_dict` gives)."""
    p = Path(path)
    write_json_atomic(p, dmap.to_dict())
    return p


def load_map(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> DefectMap:
    """Read a calibration file written by :func:`save_map` (or by hand), checked; its
    ``source`` reads as ``"calibration"`` unless it says otherwise."""
    p = Path(path)
    if p.stat().st_size > MAX_SIDECAR_BYTES:
        raise ValueError(f"{p}: more than {MAX_SIDECAR_BYTES} bytes: not a defect map")
    try:
        obj = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p}: unreadable defect map ({exc})") from exc
    return DefectMap.from_dict(obj, shape, where=str(p))


def write_to_sidecar(rec: Any, dmap: DefectMap) -> Path:
    """Store ``dmap`` in the sidecar of ``rec`` (a recording read from a ``.dat`` file), so a
    replay of it starts corrected; the sidecar is written whole (temporary file + rename),
    with its other values kept, or made from the recording's geometry if it had none."""
    if rec.path is None:
        raise ValueError("the recording has no file: nowhere to store its defect map")
    if dmap.shape != rec.layout.shape:
        raise ValueError(f"defect map {dmap.shape} does not fit the recording "
                         f"{rec.layout.shape} (H, W)")
    side = read_sidecar(rec.path)
    if side is None:
        side = _sidecar_dict(rec.layout, rec.n_frames, rec.rate_hz, None)
    side[DEFECTS_KEY] = dmap.to_dict()

    if len(json.dumps(side)) > MAX_SIDECAR_BYTES:  # it would not be read back
        raise ValueError(f"the map with its gain is more than a sidecar's {MAX_SIDECAR_BYTES} "
                         "bytes: keep it as a calibration file (--export-defects)")
    p = sidecar_path(rec.path)
    write_json_atomic(p, side)
    return p
