"""Offline reconstruction of a recording through the streaming reconstructor.

The CLI and batch tools use this, so offline results come from exactly the code the live
worker runs: blocks of packed frames are pushed into a :class:`StreamingReconstructor`. Only
the blocks that the requested times need are read, so sparse times in a long file cost little.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any

from cfsr.methods.registry import Output
from cfsr.spikes import SpikeRecording
from cfsr.streaming import StreamingReconstructor

__all__ = ["stream_reconstruct"]


def _spans(
    times: Sequence[int], before: int, after: int, n: int
) -> list[tuple[int, int, list[int]]]:
    """Group sorted times into contiguous frame spans ``[a, b)`` that cover their windows."""
    spans: list[tuple[int, int, list[int]]] = []
    for t in times:
        a, b = max(0, t - before), min(n, t + after + 1)
        if spans and a <= spans[-1][1]:
            pa, pb, ts = spans[-1]
            spans[-1] = (pa, max(pb, b), ts + [t])
        else:
            spans.append((a, b, [t]))
    return spans


def stream_reconstruct(
    rec: SpikeRecording,
    method: str,
    times: Sequence[int],
    *,
    params: Mapping[str, Any] | None = None,
    preset: str | None = None,
    block: int = 1024,
) -> Iterator[tuple[int, Output]]:
    """Yield ``(t, Output)`` for each requested step, in increasing ``t``.

    Blocks of ``block`` packed frames are read from ``rec`` (memory-mapped) and pushed through
    one :class:`StreamingReconstructor`; spans between distant times are skipped.
    """
    ts = sorted({int(t) for t in times})
    bad = [t for t in ts if not 0 <= t < rec.n_frames]
    if bad:
        raise ValueError(f"times {bad} outside the recording (0..{rec.n_frames - 1} steps)")
    sr = StreamingReconstructor(method, rec.layout, params=params, preset=preset, slack=block)
    for a, b, group in _spans(ts, sr.before, sr.after, rec.n_frames):
        sr.reset(a)
        blocks = ((s, rec.packed(s, min(b, s + block))) for s in range(a, b, block))
        # The span ends where the recording ends only if b == n; otherwise every window in the
        # group is complete inside [a, b), so "final" never clips a window early.
        yield from sr.run(blocks, group)
