"""The replay device: a ``.dat`` recording played back as if it were the camera.

Frames come straight from the memory map (seek is O(1): frame ``n`` is at byte
``n * frame_bytes``). Two modes:

``paced``
    Frames are released on the sensor's schedule, 25 us per step divided by ``speed``,
    measured against the monotonic clock from the frame index (never fixed sleeps). If the
    consumer of ``read_block`` falls more than ``max_lag_s`` behind, the device skips ahead
    like a camera whose FIFO overflowed: the index jumps and the skipped frames are counted
    (``replay_behind``).
``fast``
    Deterministic, as fast as the consumer reads (no pacing, nothing skipped); used by tests
    together with a blocking ring so every frame reaches the worker.

The block index is the device's step clock: it keeps counting across loops (the content
wraps, the clock does not), jumps when frames are skipped, and a seek is flagged
``DISCONTINUITY``. The file position is reported by ``ReplayControl.state()``.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any

from cfsr.spikes import SpikeRecording
from driver.source import (
    Block,
    BlockFlags,
    ReplayControl,
    Source,
    SourceEnded,
    SourceInfo,
    SourceState,
)

__all__ = ["ReplayDevice", "MAX_SPEED", "MIN_SPEED"]

MIN_SPEED = 1e-4
MAX_SPEED = 1000.0


class _ReplayControl(ReplayControl):
    def __init__(self, dev: ReplayDevice) -> None:
        self._d = dev

    def play(self) -> None:
        self._d._set(playing=True)

    def pause(self) -> None:
        self._d._set(playing=False)

    def step(self, n: int = 1) -> None:
        if int(n) < 1:
            raise ValueError(f"step needs n >= 1 frames, got {n}")
        self._d._set(step=int(n))

    def seek(self, frame: int) -> None:
        self._d._set(seek=int(frame))

    def set_speed(self, speed: float) -> None:
        s = float(speed)
        if not MIN_SPEED <= s <= MAX_SPEED:
            raise ValueError(f"speed must be in [{MIN_SPEED}, {MAX_SPEED}], got {speed}")
        self._d._set(speed=s)

    def set_loop(self, loop: bool) -> None:
        self._d._set(loop=bool(loop))

    def state(self) -> dict[str, Any]:
        return self._d._state()


class ReplayDevice(Source):
    """Play a recording through the :class:`~driver.source.Source` interface.

    Parameters
    ----------
    recording : SpikeRecording or path-like
        What to play (``.dat`` files are memory-mapped via :func:`cfsr.read_dat`).
    speed : float
        Playback speed relative to real time (1.0 = 40,000 steps/s).
    loop : bool
        Start again at ``start`` after ``end``.
    mode : {"paced", "fast"}
        See the module notes.
    block_frames : int
        Frames per block (256 = 6.4 ms at 40 kHz).
    start, end : int
        File frame range played (``end`` exclusive; default the whole file).
    max_lag_s : float
        In paced mode, how far behind schedule (seconds of wall time) the reader may fall
        before frames are skipped.
    kind : str
        ``replay`` (default) or ``simulator`` for synthetic in-memory recordings.
    clock : callable
        Monotonic clock in seconds (tests pass a fake one to check pacing exactly).
    """

    def __init__(
        self,
        recording: SpikeRecording | str | os.PathLike,
        *,
        speed: float = 1.0,
        loop: bool = True,
        mode: str = "paced",
        block_frames: int = 256,
        start: int = 0,
        end: int | None = None,
        max_lag_s: float = 0.1,
        playing: bool = True,
        kind: str = "replay",
        name: str | None = None,
        clock=time.monotonic,
    ) -> None:
        super().__init__()
        if not isinstance(recording, SpikeRecording):
            from cfsr.datfile import read_spikes

            recording = read_spikes(recording)
        if mode not in ("paced", "fast"):
            raise ValueError(f"mode must be 'paced' or 'fast', got {mode!r}")
        if block_frames < 1:
            raise ValueError(f"block_frames must be >= 1, got {block_frames}")
        n = recording.n_frames
        end = n if end is None else int(end)
        if not 0 <= start < end <= n:
            raise ValueError(f"frame range [{start}, {end}) not inside the recording (0..{n})")
        if not MIN_SPEED <= speed <= MAX_SPEED:
            raise ValueError(f"speed must be in [{MIN_SPEED}, {MAX_SPEED}], got {speed}")
        self.rec = recording
        self._now = clock
        self.mode = mode
        self.block_frames = int(block_frames)
        self.start, self.end = int(start), end
        self.max_lag_s = float(max_lag_s)
        rpath = recording.path
        self.info = SourceInfo(
            kind=kind,
            name=name or (os.path.basename(rpath) if rpath else "in-memory recording"),
            layout=recording.layout,
            rate_hz=recording.rate_hz,
            max_block_frames=self.block_frames,
            meta=dict(recording.meta),
        )
        self._cond = threading.Condition()
        self._speed = float(speed)
        self._loop = bool(loop)
        self._playing = bool(playing)
        self._pos = self.start  # file frame of the next block
        self._clock = 0  # step index of the next block
        self._pending_steps = 0
        self._discontinuity = False
        self._t_ref = 0.0
        self._clock_ref = 0
        self._ended = False
        self._loops = 0
        self.frames_delivered = 0
        self.frames_skipped = 0  # replay_behind
        self._facilities = {ReplayControl: _ReplayControl(self)}

    # -- lifecycle ------------------------------------------------------------------------
    def open(self) -> None:
        with self._cond:
            self._reset_pacing()
            self.state = SourceState.STREAMING if self._playing else SourceState.PAUSED

    def close(self) -> None:
        with self._cond:
            self.state = SourceState.CLOSED
            self._cond.notify_all()

    # -- controls (called from other threads) ------------------------------------------------
    def _reset_pacing(self) -> None:
        self._t_ref = self._now()
        self._clock_ref = self._clock

    def _set(self, **kw: Any) -> None:
        with self._cond:
            if "playing" in kw:
                self._playing = kw["playing"]
                if self._playing and self._ended:
                    self._ended = False
                    self._pos = self.start
                    self._discontinuity = True
            if "speed" in kw:
                self._speed = kw["speed"]
            if "loop" in kw:
                self._loop = kw["loop"]
            if "seek" in kw:
                f = kw["seek"]
                if not self.start <= f < self.end:
                    raise ValueError(f"seek to frame {f} outside [{self.start}, {self.end})")
                self._pos = f
                self._discontinuity = True
                self._ended = False
            if "step" in kw and self._pos < self.end:
                self._pending_steps += kw["step"]
                self._ended = False
            self._reset_pacing()
            if self.state not in (SourceState.CLOSED,):
                self.state = SourceState.STREAMING if self._playing else SourceState.PAUSED
            self._cond.notify_all()

    def _state(self) -> dict[str, Any]:
        with self._cond:
            return {
                "playing": self._playing,
                "speed": self._speed,
                "loop": self._loop,
                "position": self._pos,
                "start": self.start,
                "end": self.end,
                "n_frames": self.rec.n_frames,
                "mode": self.mode,
                "loops": self._loops,
                "ended": self._ended,
                "rate_hz": self.info.rate_hz,
            }

    def counters(self) -> dict[str, int]:
        return {
            "frames_delivered": self.frames_delivered,
            "replay_behind_frames": self.frames_skipped,
            "loops": self._loops,
        }

    # -- data -----------------------------------------------------------------------------
    def read_block(self, timeout: float = 0.5) -> Block | None:
        deadline = self._now() + max(0.0, timeout)
        with self._cond:
            while True:
                if self.state == SourceState.CLOSED:
                    return None
                if self._ended and self._pending_steps == 0:
                    raise SourceEnded(f"{self.info.name}: end of recording")
                now = self._now()
                remaining = deadline - now
                if self._pending_steps > 0:
                    n = min(self._pending_steps, self.block_frames, self.end - self._pos)
                    self._pending_steps -= n
                    return self._emit(n, 0)
                if not self._playing:
                    if remaining <= 0:
                        return None
                    self._cond.wait(remaining)
                    continue
                n = min(self.block_frames, self.end - self._pos)
                if self.mode == "fast":
                    return self._emit(n, 0)
                rate = self.info.rate_hz * self._speed
                due = self._t_ref + (self._clock + n - self._clock_ref) / rate
                if due > now:
                    if remaining <= 0:
                        return None
                    self._cond.wait(min(due - now, remaining))
                    continue
                skipped = 0
                behind = now - due
                if behind > self.max_lag_s:
                    # the reader cannot keep up: jump to the schedule, as a camera FIFO would
                    skipped = int(behind * rate)
                    self._advance(skipped)
                    n = min(self.block_frames, self.end - self._pos)
                return self._emit(n, skipped)

    def _advance(self, k: int) -> None:
        """Skip ``k`` frames of content (the clock jumps too)."""
        self._clock += k
        self.frames_skipped += k
        span = self.end - self.start
        off = self._pos - self.start + k
        if self._loop:
            self._loops += off // span
            self._pos = self.start + off % span
        else:
            self._pos = min(self.end - 1, self.start + off)

    def _emit(self, n: int, skipped: int) -> Block:
        flags = BlockFlags.NONE
        if self._discontinuity:
            flags |= BlockFlags.DISCONTINUITY
            self._discontinuity = False
        if skipped:
            flags |= BlockFlags.LOSS
        data = self.rec.packed(self._pos, self._pos + n)
        blk = Block(index=self._clock, data=data, flags=flags, lost_before=skipped)
        self._clock += n
        self._pos += n
        self.frames_delivered += n
        if self._pos >= self.end:
            if self._loop:
                self._pos = self.start
                self._loops += 1
            else:
                self._pos = self.end
                self._ended = True
                blk.flags |= BlockFlags.END
        return blk
