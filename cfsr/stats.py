"""Recording statistics for ``cfsr info``: per-pixel firing rates and problems found."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import prange

from cfsr._jit import njit
from cfsr.spikes import SpikeRecording

__all__ = ["RecordingStats", "recording_stats"]

# popcount of every byte value, for counting spikes straight from packed frames
_POP = np.array([bin(v).count("1") for v in range(256)], dtype=np.uint8)


@njit(parallel=True)
def _frame_counts(packed, pop, out):  # pragma: no cover - numba
    n, nb = packed.shape
    for t in prange(n):
        s = 0
        for i in range(nb):
            s += pop[packed[t, i]]
        out[t] = s
    return out


@dataclass
class RecordingStats:
    """Summary of ``n_scanned`` frames: rates are spikes per step."""

    n_frames: int
    n_scanned: int
    mean_rate: float
    pixel_rate_min: float
    pixel_rate_median: float
    pixel_rate_max: float
    pixel_rate_p01: float
    pixel_rate_p99: float
    dead_fraction: float  # pixels that never fired
    saturated_fraction: float  # pixels firing at >= 0.95 spikes/step
    empty_frames: int  # frames with no spike at all (often dropped data)
    problems: list[str] = field(default_factory=list)


def recording_stats(
    rec: SpikeRecording, *, max_frames: int | None = 40_000, block: int = 2048, progress=None
) -> RecordingStats:
    """Scan up to ``max_frames`` frames (all if None) block by block; never unpack it all."""
    n = rec.n_frames if max_frames is None else min(rec.n_frames, max_frames)
    h, w = rec.layout.height, rec.layout.width
    counts = np.zeros((h, w), np.int64)
    per_frame = np.empty(n, np.int64)
    for a in range(0, n, block):
        b = min(n, a + block)
        frames = rec.frames(a, b)
        counts += frames.sum(axis=0, dtype=np.int64)
        _frame_counts(np.ascontiguousarray(rec.packed(a, b)), _POP, per_frame[a:b])
        if progress is not None:
            progress(b - a)
    rates = counts / max(1, n)
    problems: list[str] = []
    tail = rec.meta.get("dropped_tail_bytes")
    if tail:
        problems.append(f"{tail} trailing bytes do not form a whole frame (dropped)")
    side_n = rec.meta.get("n_frames")
    if side_n is not None and int(side_n) != rec.n_frames:
        problems.append(f"sidecar says {side_n} frames, file holds {rec.n_frames}")
    # head columns may carry non-spike bits, so count empties on the image pixels when present
    empty = int(np.count_nonzero(per_frame == 0))
    dead = float(np.mean(counts == 0))
    sat = float(np.mean(rates >= 0.95))
    if n and empty:
        problems.append(f"{empty} of {n} frames hold no spike at all (lost data or a dark scene)")
    if dead > 0.01:
        problems.append(f"{dead:.1%} of pixels never fired in the scanned frames")
    if sat > 0.01:
        problems.append(f"{sat:.1%} of pixels fire at >= 0.95 spikes/step (saturated)")
    if n < rec.n_frames:
        problems.append(
            f"statistics from the first {n} of {rec.n_frames} frames (--all to scan all)"
        )
    p01, med, p99 = np.percentile(rates, [1, 50, 99])
    return RecordingStats(
        n_frames=rec.n_frames,
        n_scanned=n,
        mean_rate=float(rates.mean()),
        pixel_rate_min=float(rates.min()),
        pixel_rate_median=float(med),
        pixel_rate_max=float(rates.max()),
        pixel_rate_p01=float(p01),
        pixel_rate_p99=float(p99),
        dead_fraction=dead,
        saturated_fraction=sat,
        empty_frames=empty,
        problems=problems,
    )
