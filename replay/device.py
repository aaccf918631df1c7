"""The replay device: a ``.dat`` recording played back as if it were the camera.

Frames of a file are read block by block with bounds-checked ``preadv`` calls
(:class:`cfsr.datfile.DatReader`), not through the memory map: the file may be truncated or
rewritten while a long-running service replays it, and touching a map past the file's new end
kills the whole process with SIGBUS. A read that comes up short ends the replay instead: the
source goes to the ``error`` state with ``last_error`` naming the file and what happened.
Seek stays O(1) (frame ``n`` is at byte ``n * frame_bytes``). Two modes:

``paced``
    Frames are released on the sensor's schedule, 25 us per step divided by ``speed``,
    measured against the monotonic clock from the frame index (never fixed sleeps). If the
    consumer of ``read_block`` falls more than ``max_lag_s`` behind, the device skips ahead
    like a camera whose FIFO overflowed: the index jumps and the skipped frames are counted
    (``replay_behind``).
``unpaced``
    Deterministic, as fast as the consumer reads (no pacing, nothing skipped); used by tests
    together with a blocking ring so every frame reaches the worker. (Formerly ``fast``,
    still accepted with a DeprecationWarning: the name read like CFSR's fast quality tier.)

The block index is the device's step clock: it keeps counting across loops (the content
wraps, the clock does not), jumps when frames are skipped, and a seek is flagged
``DISCONTINUITY``. The file position is reported by ``ReplayControl.state()``. A looping
range shorter than one block is repeated inside the block (a 1-frame file comes as blocks of
``block_frames`` copies), so tiny files cost one wake-up per block like any other.
"""

from __future__ import annotations

import logging
import mmap
import os
import threading
import time
from typing import Any

import numpy as np

from cfsr.datfile import DatReader, FileShrankError
from cfsr.spikes import SpikeRecording
from cfsr_live.driver.source import (
    Block,
    BlockFlags,
    ReplayControl,
    ReplayMode,
    Source,
    SourceCounters,
    SourceEnded,
    SourceInfo,
    SourceState,
)

__all__ = ["ReplayDevice", "MAX_SPEED", "MIN_SPEED"]

MIN_SPEED = 1e-4
MAX_SPEED = 1000.0

log = logging.getLogger("cfsr.replay")


def _file_region(rec: SpikeRecording) -> tuple[str, int] | None:
    """``(file, byte offset of frame 0)`` when ``rec`` maps a file, else None (in memory).

    Only a map made by ``np.memmap`` itself qualifies (its ``base`` is the ``mmap``): a slice
    of one inherits ``offset`` from its parent, which would point at the wrong frames.
    """
    pf = rec.packed_frames
    if isinstance(pf, np.memmap) and isinstance(pf.base, mmap.mmap) and pf.filename:
        return pf.filename, int(pf.offset)
    return None


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
    """Play a recording through the :class:`~cfsr_live.driver.source.Source` interface.

    Parameters
    ----------
    recording : SpikeRecording or path-like
        What to play (``.dat`` files are opened with :func:`cfsr.read_dat`, which checks them
        and their sidecar; frames are then read from the file, bounds-checked, per block).
    speed : float
        Playback speed relative to real time (1.0 = 40,000 steps/s).
    loop : bool
        Start again at ``start`` after ``end``.
    mode : {"paced", "unpaced"}
        See the module notes (:class:`~cfsr_live.driver.source.ReplayMode`).
    block_frames : int
        Frames per block (256 = 6.4 ms at 40 kHz).
    start, end : int
        File frame range played (``end`` exclusive; default the whole file).
    max_lag_s : float
        In paced mode, how far behind schedule (seconds of wall time) the reader may fall
        before frames are skipped.
    kind : str
        The source kind's name in the registry (``SourceInfo.kind``): ``replay`` (default),
        ``demo``, ``sim`` for synthetic in-memory recordings, or a camera package's.
    clock : callable
        Monotonic clock in seconds (tests pass a fake one to check pacing exactly).
    """

    def __init__(
        self,
        recording: SpikeRecording | str | os.PathLike,
        *,
        speed: float = 1.0,
        loop: bool = True,
        mode: ReplayMode | str = ReplayMode.PACED,
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
        mode = ReplayMode.of(mode)
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
        #: host time the schedule counts from (None: from the next read, see :meth:`open`)
        self._t_ref: float | None = None
        self._clock_ref = 0
        self._ended = False
        self._loops = 0
        self._failed = False  # the file lost frames under us: ended for good, see last_error
        self.frames_delivered = 0
        self.frames_skipped = 0  # replay_behind
        region = _file_region(recording)
        self._region = region
        self._reader: DatReader | None = None
        if region is not None:
            self._reader = DatReader(region[0], recording.layout.frame_bytes, offset=region[1])
        self._facilities = {ReplayControl: _ReplayControl(self)}

    # -- lifecycle ------------------------------------------------------------------------
    def open(self) -> None:
        with self._cond:
            if self._region is not None and (self._reader is None or self._reader.closed):
                self._reader = DatReader(
                    self._region[0], self.rec.layout.frame_bytes, offset=self._region[1]
                )
            # the schedule starts at the first read, not here: what the service does between
            # opening a source and reading it (its ring, its threads) is no reader's lag
            self._t_ref = None
            if self._failed:
                self.state = SourceState.ERROR
            else:
                self.state = SourceState.STREAMING if self._playing else SourceState.PAUSED

    def close(self) -> None:
        with self._cond:
            self.state = SourceState.CLOSED
            if self._reader is not None:
                self._reader.close()
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
                    self._restart()
            if "speed" in kw:
                self._speed = kw["speed"]
            if "loop" in kw:
                self._loop = kw["loop"]
                if self._loop and self._ended and self._playing:
                    # looping an ended replay plays it again, as if it had looped all along
                    self._restart()
            if "seek" in kw:
                f = kw["seek"]
                if not self.start <= f < self.end:
                    raise ValueError(f"seek to frame {f} outside [{self.start}, {self.end})")
                self._pos = f
                self._discontinuity = True
                self._ended = self._failed
            if "step" in kw and self._pos < self.end and not self._failed:
                self._pending_steps += kw["step"]
                self._ended = False
            self._reset_pacing()
            if self._failed:
                pass  # a file that lost frames stays in ERROR until the source is reopened
            elif self.state not in (SourceState.CLOSED,):
                self.state = SourceState.STREAMING if self._playing else SourceState.PAUSED
            self._cond.notify_all()

    def _restart(self) -> None:
        """Play again from ``start`` after the end (not after a file failure)."""
        if self._failed:
            return
        self._ended = False
        self._pos = self.start
        self._discontinuity = True

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

    def counters(self) -> SourceCounters:
        """Frames delivered, skipped by the paced schedule, and loops (a file has no link:
        ``lost_frames`` is None)."""
        return SourceCounters(frames_delivered=self.frames_delivered,
                              replay_behind_frames=self.frames_skipped, loops=self._loops)

    # -- data -----------------------------------------------------------------------------
    def read_block(self, timeout: float = 0.5) -> Block | None:
        deadline = self._now() + max(0.0, timeout)
        with self._cond:
            while True:
                if self.state == SourceState.CLOSED:
                    return None
                if self._ended and self._pending_steps == 0:
                    raise SourceEnded(self.last_error or f"{self.info.name}: end of recording")
                now = self._now()
                remaining = deadline - now
                if self._pending_steps > 0:
                    n = min(self._pending_steps, self.block_frames, self.end - self._pos)
                    blk = self._emit(n, 0)
                    self._pending_steps -= n
                    return blk
                if not self._playing:
                    if remaining <= 0:
                        return None
                    self._cond.wait(remaining)
                    continue
                n = self._next_len()
                if self.mode is ReplayMode.UNPACED:
                    return self._emit(n, 0)
                rate = self.info.rate_hz * self._speed
                if self._t_ref is None:
                    self._reset_pacing()
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
                    n = self._next_len()
                return self._emit(n, skipped)

    def _next_len(self) -> int:
        """Frames in the next block: ``block_frames``, or fewer up to the end of the range.

        A looping range shorter than a block, started at its beginning, is repeated whole as
        many times as fit: a 1-frame file then comes in blocks of ``block_frames`` copies (one
        wake-up per 6.4 ms at 256 frames) instead of a 1-frame block every 25 us, which spun
        the acquisition thread and flooded the ring.
        """
        left = self.end - self._pos
        if self._loop and left < self.block_frames and self._pos == self.start:
            return left * (self.block_frames // left)
        return min(self.block_frames, left)

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

    def _read(self, a: int, n: int) -> np.ndarray:
        """Packed file frames ``a..a+n-1``: bounds-checked from the file, or a view in memory."""
        if self._reader is None:
            return self.rec.packed(a, a + n)
        try:
            return self._reader.read(a, n)
        except (FileShrankError, OSError) as exc:
            # the file was truncated or rewritten (or the disk failed) under the replay: end
            # it here, for good, and say why; the service and its other parts stay up
            self._failed = True
            self._ended = True
            self._pending_steps = 0
            self.state = SourceState.ERROR
            self.last_error = f"replay ended: {exc}"
            log.warning("%s", self.last_error)
            raise SourceEnded(self.last_error) from exc

    def _emit(self, n: int, skipped: int) -> Block:
        """Deliver ``n`` frames from the current position (``n`` may hold several whole passes
        over a short looping range, see :meth:`_next_len`)."""
        left = self.end - self._pos
        passes, k = (n // left, left) if n > left else (1, n)
        data = self._read(self._pos, k)  # first: a failed read changes no counter
        if passes > 1:
            data = np.tile(data, (passes, 1))
        flags = BlockFlags.NONE
        if self._discontinuity:
            flags |= BlockFlags.DISCONTINUITY
            self._discontinuity = False
        if skipped:
            flags |= BlockFlags.LOSS
        blk = Block(index=self._clock, data=data, flags=flags, lost_before=skipped)
        self._clock += n
        self._pos += k
        self.frames_delivered += n
        if self._pos >= self.end:
            if self._loop:
                self._pos = self.start
                self._loops += passes
            else:
                self._pos = self.end
                self._ended = True
                blk.flags |= BlockFlags.END
        return blk
