"""The latest-frame slot: shared memory from the worker process to the web process.

Holds exactly one frame (the newest): the 8-bit display image, the coarse and fine masks, and
the metadata of the step, behind the package's seqlock (:mod:`cfsr_live.shm.seqlock`; the sequence
number is the frame number, so a reader asks for "newer than the one I have" and retries if
the writer was busy). A second region holds the worker's live counters (heartbeat, timings,
drops) as float64 words the worker updates in place: single words, read without the lock,
because each one is meaningful on its own.
"""

from __future__ import annotations

import mmap
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cfsr_live.shm.files import attach_shared_file, create_shared_file, release_shared_file
from cfsr_live.shm.seqlock import EMPTY, WRITING, Seqlock

__all__ = ["FRAME_PREFIX", "STAT_FIELDS", "FrameSlot", "SlotFrame"]

#: name prefix of the latest-frame slot's shared-memory file
FRAME_PREFIX = "cfsr-frame"

_MAGIC = 0x544F4C53_4D415247  # "GRAMSLOT": version 2, the sequence word follows shm.seqlock
_HDR = 1024
_STATS_OFF = 1024
_PAYLOAD_OFF = 4096
# int64 header words
_M, _SEQ, _MAXPIX, _W, _H, _STEP, _FRAMENO, _FLAGS = 0, 1, 2, 3, 4, 5, 6, 7
# float64 header words (same array viewed as float64)
_TPUB, _TARR, _COMPUTE, _GAIN, _LAT = 8, 9, 10, 11, 12
_NAME_OFF, _NAME_LEN = 256, 32  # method name, ASCII

#: worker counters, in order, stored as float64 words in the stats region
STAT_FIELDS = (
    "heartbeat",  # time.monotonic() of the last loop
    "pid",
    "frames_out",
    "steps_ingested",
    "worker_skip_frames",
    "ring_lost_frames",
    "ring_overruns",
    "ring_torn",
    "gaps",
    "errors",
    "compute_ms",  # EMA
    "latency_ms",  # EMA, arrival of the newest step used -> publish
    "config_version",
    "started",
    # time.monotonic() when the first frame under the current config began computing, 0 when
    # none is pending: on a machine's first use that frame waits on numba's compiler
    "first_frame_since",
    "workers",  # reconstruction processes in the worker's pool
    "threads",  # numba/OpenCV threads per process
    "q_full",  # frames shown at CFSR's full quality tier (every frame of other methods)
    "q_fast",  # frames shown at CFSR's fast tier
    "dropped_late",  # frames computed but not shown: too late, or under a replaced config
    "dropped_order",  # frames computed but not shown: a newer step was shown first
    "fallback",  # 1 while TFP frames stand in for a first frame that is compiling
    "fallback_frames",  # TFP frames shown that way
)


@dataclass
class SlotFrame:
    """A consistent copy of the slot's frame (``seq`` is its sequence number)."""

    seq: int
    step: int
    frame_no: int
    width: int
    height: int
    method: str
    gain: float
    t_publish: float
    t_arrival: float
    compute_ms: float
    latency_ms: float
    image: np.ndarray
    masks: dict[str, np.ndarray] = field(default_factory=dict)


class FrameSlot:
    """Create with :meth:`create` (web process), :meth:`attach` by path (worker)."""

    MASK_NAMES = ("coarse", "fine")

    def __init__(self, path: Path, mm: mmap.mmap, owner: bool) -> None:
        self.path, self._mm, self.owner = path, mm, owner
        self._i = np.frombuffer(mm, np.int64, _HDR // 8, 0)
        self._f = self._i.view(np.float64)
        self._lock = Seqlock(self._i[_SEQ : _SEQ + 1])
        if self._i[_M] != _MAGIC:
            raise ValueError(f"{path}: not a frame slot")
        self.max_pixels = int(self._i[_MAXPIX])
        self._stats = np.frombuffer(mm, np.float64, len(STAT_FIELDS), _STATS_OFF)
        mp = self.max_pixels
        self._img = np.frombuffer(mm, np.uint8, mp, _PAYLOAD_OFF)
        self._masks = {
            name: np.frombuffer(mm, np.uint8, mp, _PAYLOAD_OFF + (k + 1) * mp)
            for k, name in enumerate(self.MASK_NAMES)
        }

    @classmethod
    def create(cls, max_pixels: int = 1024 * 1024, directory: str | None = None) -> FrameSlot:
        size = _PAYLOAD_OFF + 3 * max_pixels
        path, mm = create_shared_file(FRAME_PREFIX, size, directory)
        hdr = np.frombuffer(mm, np.int64, _HDR // 8, 0)
        hdr[_MAXPIX] = max_pixels
        Seqlock(hdr[_SEQ : _SEQ + 1]).reset()
        hdr[_M] = _MAGIC
        del hdr
        return cls(path, mm, owner=True)

    @classmethod
    def attach(cls, path: str | os.PathLike) -> FrameSlot:
        return cls(Path(path), attach_shared_file(path), owner=False)

    def close(self) -> None:
        if self._mm is None:
            return
        self._i = self._f = self._stats = self._img = None  # type: ignore[assignment]
        self._masks = {}
        self._lock = None  # type: ignore[assignment]
        release_shared_file(self._mm, self.path, self.owner)
        self._mm = None  # type: ignore[assignment]

    # -- writer (worker) ----------------------------------------------------------------------
    def publish(
        self,
        *,
        step: int,
        image: np.ndarray,
        masks: dict[str, np.ndarray],
        method: str,
        gain: float,
        t_arrival: float,
        compute_ms: float,
        latency_ms: float,
    ) -> None:
        h, w = image.shape
        if h * w > self.max_pixels:
            raise ValueError(f"frame {w} x {h} exceeds the slot ({self.max_pixels} pixels)")
        i, f = self._i, self._f
        frame_no = int(i[_FRAMENO]) + 1
        self._lock.begin_write(0)
        self._img[: h * w] = image.reshape(-1)
        flags = 0
        for k, name in enumerate(self.MASK_NAMES):
            m = masks.get(name)
            if m is not None:
                self._masks[name][: h * w] = np.asarray(m, np.uint8).reshape(-1)
                flags |= 1 << k
        i[_W], i[_H], i[_STEP], i[_FLAGS] = w, h, step, flags
        i[_FRAMENO] = frame_no
        f[_TPUB], f[_TARR], f[_COMPUTE], f[_GAIN], f[_LAT] = (
            time.monotonic(),
            t_arrival,
            compute_ms,
            gain,
            latency_ms,
        )
        name = method.encode("ascii", "replace")[: _NAME_LEN - 1]
        self._mm[_NAME_OFF : _NAME_OFF + _NAME_LEN] = name.ljust(_NAME_LEN, b"\0")
        self._lock.end_write(0, frame_no)

    def stats_array(self) -> np.ndarray:
        """The worker's counters (:data:`STAT_FIELDS`, in order) as a writable float64 view
        into shared memory: the worker updates them in place, one word at a time."""
        return self._stats

    # -- reader (web process) -------------------------------------------------------------------
    @property
    def seq(self) -> int:
        """Sequence number of the newest frame (negative: none yet, or being written)."""
        return self._lock.read(0)

    def stats(self) -> dict[str, float]:
        """A copy of the worker's counters by name."""
        return {k: float(v) for k, v in zip(STAT_FIELDS, self._stats, strict=True)}

    def read(self, *, since: int | None = None, retries: int = 50) -> SlotFrame | None:
        """A consistent copy of the newest frame, or None if there is none, it is the one
        numbered ``since`` (the reader has it already), or the writer kept it busy for all
        ``retries``."""
        i, f = self._i, self._f
        lock = self._lock
        for _ in range(retries):
            s1 = lock.read(0)
            if s1 == EMPTY or s1 == since:
                return None
            if s1 == WRITING:
                time.sleep(0.0002)
                continue
            w, h, step, flags = int(i[_W]), int(i[_H]), int(i[_STEP]), int(i[_FLAGS])
            img = self._img[: h * w].copy().reshape(h, w)
            masks = {
                name: self._masks[name][: h * w].copy().reshape(h, w)
                for k, name in enumerate(self.MASK_NAMES)
                if flags & (1 << k)
            }
            meta = (int(i[_FRAMENO]), float(f[_TPUB]), float(f[_TARR]), float(f[_COMPUTE]))
            gain, lat = float(f[_GAIN]), float(f[_LAT])
            name = bytes(self._mm[_NAME_OFF : _NAME_OFF + _NAME_LEN]).split(b"\0")[0].decode()
            if lock.unchanged(0, s1):
                return SlotFrame(
                    seq=s1,
                    step=step,
                    frame_no=meta[0],
                    width=w,
                    height=h,
                    method=name,
                    gain=gain,
                    t_publish=meta[1],
                    t_arrival=meta[2],
                    compute_ms=meta[3],
                    latency_ms=lat,
                    image=img,
                    masks=masks,
                )
        return None
