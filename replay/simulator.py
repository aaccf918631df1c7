"""The simulator as a source: a synthetic scene simulated in memory and played like the camera.

``pattern`` is the built-in toy scene (:mod:`cfsr_live.replay.pattern`, NumPy only); other scene
names are
simulated by :func:`cfsr.simulate.simulate` when that module is available. The clip loops, so
the source streams for as long as it is read, through the same interface (and the same replay
controls) as a recording.
"""

from __future__ import annotations

import functools
import os
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from cfsr.spikes import SpikeRecording
from cfsr_live.replay.device import ReplayDevice

__all__ = ["SimulatorSource", "simulate_recording"]


def simulate_recording(
    scene: str,
    steps: int,
    *,
    height: int = 250,
    width: int = 400,
    seed: int = 0,
    cache_dir: str | os.PathLike | None = None,
) -> SpikeRecording:
    """Simulate ``steps`` steps of ``scene`` into a packed recording.

    With ``cache_dir``, scenes of :mod:`cfsr.simulate` are written there once as ``.dat`` +
    sidecar (streamed in chunks, never fully unpacked) and memory-mapped afterwards.
    """
    if scene == "pattern":
        clip = _pattern_clip(steps, height, width, seed)
        return replace(clip, meta=dict(clip.meta))  # the frames are shared, read-only
    try:
        from cfsr.simulate import SCENES, simulate, simulate_to_dat
    except ImportError as exc:
        raise ValueError(f"scene {scene!r} needs cfsr.simulate, which is unavailable") from exc
    if scene not in SCENES:
        raise ValueError(f"unknown scene {scene!r}; scenes: pattern, {', '.join(SCENES)}")
    if cache_dir is not None:
        from cfsr.datfile import read_dat

        target = Path(cache_dir) / f"sim-{scene}-{steps}-{height}x{width}-s{seed}.dat"
        if not target.with_name(target.name + ".json").exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=".sim-", dir=target.parent))
            try:
                simulate_to_dat(scene, steps, tmp / "x.dat", seed=seed, height=height,
                                width=width, gt_every=None)
                os.replace(tmp / "x.dat", target)
                os.replace(tmp / "x.dat.json", target.with_name(target.name + ".json"))
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
        return read_dat(target)
    res: Any = simulate(scene, steps=steps, height=height, width=width, seed=seed)
    meta: dict[str, Any] = {"scene": scene, "seed": seed}
    g = getattr(res, "rate_scale", None)
    if g:
        meta["gain"] = float(g)
    return SpikeRecording.from_array(np.asarray(res.spikes, dtype=np.uint8), meta=meta)


@functools.lru_cache(maxsize=2)
def _pattern_clip(steps: int, height: int, width: int, seed: int) -> SpikeRecording:
    """The pattern clip of these arguments, made once (it is deterministic).

    Every switch of the live service to the simulator used to simulate its clip again (15 MB
    packed at 1200 steps of 400 x 250, and ~60 MB of temporaries in the request's thread):
    the process's resident memory grew by ~1 MB a switch though nothing stayed referenced
    (tracemalloc showed no growth), because the allocator keeps the freed blocks of each
    thread's arena. The frames are made read-only: every source made from them shares them.
    """
    from cfsr_live.replay.pattern import pattern_recording

    rec = pattern_recording(steps, height=height, width=width, seed=seed)
    rec.packed_frames.flags.writeable = False
    return rec


class SimulatorSource(ReplayDevice):
    """A looping simulated clip served as a live source (kind ``simulator``)."""

    def __init__(
        self,
        scene: str = "pattern",
        *,
        steps: int = 1200,
        speed: float = 1.0,
        height: int = 250,
        width: int = 400,
        seed: int = 0,
        cache_dir: str | os.PathLike | None = None,
        **kw: Any,
    ) -> None:
        rec = simulate_recording(
            scene, steps, height=height, width=width, seed=seed, cache_dir=cache_dir
        )
        super().__init__(
            rec, speed=speed, loop=True, kind="sim", name=f"simulator: {scene}", **kw
        )
        self.scene = scene
