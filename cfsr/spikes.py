"""Spike recordings: memory-mapped ``.dat`` files and in-memory arrays behind one interface.

A :class:`SpikeRecording` never unpacks the whole recording. ``rec[a:b]`` unpacks only frames
``a..b-1`` to an upright ``(b - a, H, W)`` uint8 array of 0/1; ``rec.packed(a, b)`` returns the
stored bytes. Time is the step index (1 step = 25 us at 40 kHz).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cfsr._bits import pack_frames, unpack_layout
from cfsr.layout import STEP_RATE_HZ, Layout

__all__ = ["SpikeRecording", "as_recording"]


@dataclass
class SpikeRecording:
    """A sequence of spike frames stored packed (``.dat`` byte layout).

    Attributes
    ----------
    packed_frames : ndarray, shape (n_frames, layout.frame_bytes), uint8
        The stored bytes; a read-only ``np.memmap`` for files.
    layout : Layout
        Geometry and orientation of the stored frames.
    rate_hz : float
        Steps per second (40,000 for the sensor).
    meta : dict
        Sidecar metadata (brightness gain, provenance, ...); empty if none.
    path : str or None
        Source file, if any.
    """

    packed_frames: np.ndarray
    layout: Layout
    rate_hz: float = float(STEP_RATE_HZ)
    meta: dict[str, Any] = field(default_factory=dict)
    path: str | None = None

    @property
    def n_frames(self) -> int:
        return int(self.packed_frames.shape[0])

    def __len__(self) -> int:
        return self.n_frames

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(n_frames, height, width)`` of the upright unpacked recording."""
        return (self.n_frames, self.layout.height, self.layout.width)

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.rate_hz

    @property
    def gain(self) -> float | None:
        """Brightness gain: firing rate (spikes/step) that maps to display 255, if known."""
        g = self.meta.get("gain")
        return None if g is None else float(g)

    def _range(self, start: int, stop: int) -> tuple[int, int]:
        n = self.n_frames
        start, stop, step = slice(start, stop).indices(n)
        if step != 1:
            raise ValueError("only contiguous frame ranges are supported")
        return start, max(start, stop)

    def packed(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Packed bytes of frames ``start..stop-1`` (a view for memory-mapped files)."""
        a, b = self._range(start, self.n_frames if stop is None else stop)
        return self.packed_frames[a:b]

    def frames(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Unpacked upright frames ``start..stop-1`` as ``(n, H, W)`` uint8 0/1."""
        return unpack_layout(self.packed(start, stop), self.layout)

    def __getitem__(self, key: int | slice) -> np.ndarray:
        if isinstance(key, slice):
            if key.step not in (None, 1):
                raise ValueError("only contiguous frame ranges are supported")
            a, b = self._range(
                0 if key.start is None else key.start,
                self.n_frames if key.stop is None else key.stop,
            )
            return self.frames(a, b)
        i = int(key)
        if i < 0:
            i += self.n_frames
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {key} out of range for {self.n_frames} frames")
        return self.frames(i, i + 1)[0]

    def iter_blocks(self, block: int = 256):
        """Yield ``(start_step, packed_block)`` pairs covering the recording in order."""
        for a in range(0, self.n_frames, block):
            yield a, self.packed(a, min(self.n_frames, a + block))

    @classmethod
    def from_array(
        cls,
        spikes: np.ndarray,
        *,
        rate_hz: float = float(STEP_RATE_HZ),
        meta: Mapping[str, Any] | None = None,
    ) -> SpikeRecording:
        """Wrap upright ``(T, H, W)`` 0/1 spikes (packed in memory, default orientation)."""
        spikes = np.asarray(spikes)
        if spikes.ndim != 3:
            raise ValueError(f"spikes must be (T, H, W), got shape {spikes.shape}")
        if spikes.shape[0] == 0:
            raise ValueError("spikes hold no frames")
        t, h, w = spikes.shape
        if (h * w) % 8:
            # Pad by a head column group so the frame is a whole number of bytes.
            pad = next(k for k in range(1, 9) if (h * (w + k)) % 8 == 0)
            spikes = np.concatenate([spikes, np.zeros((t, h, pad), spikes.dtype)], axis=2)
            layout = Layout(width=w, height=h, head_cols=pad)
        else:
            layout = Layout(width=w, height=h)
        return cls(pack_frames(spikes), layout, float(rate_hz), dict(meta or {}))


def as_recording(spikes: SpikeRecording | np.ndarray) -> SpikeRecording:
    """Accept what :func:`cfsr.read_dat` returns or a ``(T, H, W)`` 0/1 array."""
    if isinstance(spikes, SpikeRecording):
        return spikes
    return SpikeRecording.from_array(np.asarray(spikes))
