"""The latest-frame slot: shared memory from the worker process to the web process.

Holds exactly one frame (the newest): the 8-bit display image, one plane per mask name, and
the metadata of the step, behind the seqlock of :mod:`cfsr_live.shm.seqlock` (the sequence
number is the frame number, so a reader asks for "newer than the one I have" and retries if
the writer was busy). A second region holds the worker's live counters, one record of
:data:`~cfsr_live.service.schema.COUNTER_DTYPE` the worker updates in place: single words,
read without the lock, because each one is meaningful on its own. The mask names
(:func:`~cfsr_live.service.schema.display_masks`) are written into the header by the process
that creates the slot, so the worker that attaches publishes under the same names and in the
same order as the web process reads them.
"""

from __future__ import annotations

import mmap
import os
import time
from pathlib import Path

import numpy as np

from cfsr_live.service.schema import (
    COUNTER_DTYPE,
    MASK_NAME_BYTES,
    MAX_MASKS,
    METHOD_NAME_BYTES,
    QUALITY_TIERS,
    SlotFrame,
    WorkerCounters,
    display_masks,
    quality_code,
)
from cfsr_live.shm.files import attach_shared_file, create_shared_file, release_shared_file
from cfsr_live.shm.seqlock import EMPTY, WRITING, Seqlock

__all__ = ["FRAME_PREFIX", "FrameSlot", "SlotFrame"]

#: name prefix of the latest-frame slot's shared-memory file
FRAME_PREFIX = "cfsr-frame"

_MAGIC = 0x544F4C53_4D415248  # "HRAMSLOT": version 3, mask names in the header
_HDR = 1024
_STATS_OFF = 1024
_PAYLOAD_OFF = 4096
# int64 header words
_M, _SEQ, _MAXPIX, _W, _H, _STEP, _FRAMENO, _FLAGS, _NMASKS, _QUALITY = (
    0, 1, 2, 3, 4, 5, 6, 7, 13, 14)
# float64 header words (same array viewed as float64)
_TPUB, _TARR, _COMPUTE, _GAIN, _LAT = 8, 9, 10, 11, 12
_NAME_OFF = 256  # method name, ASCII, METHOD_NAME_BYTES
_MASKS_OFF = 512  # mask names, ASCII, MASK_NAME_BYTES each, MAX_MASKS at most
assert _MASKS_OFF + MAX_MASKS * MASK_NAME_BYTES <= _HDR
assert _STATS_OFF + COUNTER_DTYPE.itemsize <= _PAYLOAD_OFF


class FrameSlot:
    """Create with :meth:`create` (web process), :meth:`attach` by path (worker)."""

    def __init__(self, path: Path, mm: mmap.mmap, owner: bool) -> None:
        self.path, self._mm, self.owner = path, mm, owner
        self._i = np.frombuffer(mm, np.int64, _HDR // 8, 0)
        self._f = self._i.view(np.float64)
        self._lock = Seqlock(self._i[_SEQ : _SEQ + 1])
        if self._i[_M] != _MAGIC:
            raise ValueError(f"{path}: not a frame slot")
        self.max_pixels = int(self._i[_MAXPIX])
        self._stats = np.frombuffer(mm, COUNTER_DTYPE, 1, _STATS_OFF)
        names = []
        for k in range(int(self._i[_NMASKS])):
            at = _MASKS_OFF + k * MASK_NAME_BYTES
            raw = bytes(mm[at : at + MASK_NAME_BYTES])
            names.append(raw.split(b"\0")[0].decode("ascii"))
        #: the names of the mask planes, in the order the WebSocket message carries them
        self.mask_names: tuple[str, ...] = tuple(names)
        mp = self.max_pixels
        self._img = np.frombuffer(mm, np.uint8, mp, _PAYLOAD_OFF)
        self._masks = {
            name: np.frombuffer(mm, np.uint8, mp, _PAYLOAD_OFF + (k + 1) * mp)
            for k, name in enumerate(self.mask_names)
        }

    @classmethod
    def create(cls, max_pixels: int = 1024 * 1024, directory: str | None = None,
               mask_names: tuple[str, ...] | None = None) -> FrameSlot:
        """A new slot for frames of at most ``max_pixels`` and the masks ``mask_names``
        (default: every mask a registered method declares)."""
        names = display_masks() if mask_names is None else tuple(mask_names)
        if len(names) > MAX_MASKS:
            raise ValueError(f"{len(names)} masks; a frame carries {MAX_MASKS}")
        size = _PAYLOAD_OFF + (1 + len(names)) * max_pixels
        path, mm = create_shared_file(FRAME_PREFIX, size, directory)
        for k, name in enumerate(names):
            raw = name.encode("ascii")
            if not 0 < len(raw) < MASK_NAME_BYTES:
                raise ValueError(f"mask name {name!r}: 1-{MASK_NAME_BYTES - 1} characters")
            at = _MASKS_OFF + k * MASK_NAME_BYTES
            mm[at : at + MASK_NAME_BYTES] = raw.ljust(MASK_NAME_BYTES, b"\0")
        hdr = np.frombuffer(mm, np.int64, _HDR // 8, 0)
        hdr[_MAXPIX] = max_pixels
        hdr[_NMASKS] = len(names)
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
        quality: str = "",
    ) -> None:
        """Write the newest frame; ``quality``: the tier that made it ("" for none)."""
        h, w = image.shape
        if h * w > self.max_pixels:
            raise ValueError(f"frame {w} x {h} exceeds the slot ({self.max_pixels} pixels)")
        i, f = self._i, self._f
        frame_no = int(i[_FRAMENO]) + 1
        self._lock.begin_write(0)
        self._img[: h * w] = image.reshape(-1)
        flags = 0
        unknown = set(masks) - set(self.mask_names)
        if unknown:  # a method's mask that no plane holds would vanish on its way to the viewer
            raise ValueError(f"masks {sorted(unknown)} are not among the slot's "
                             f"{list(self.mask_names)}")
        for k, name in enumerate(self.mask_names):
            m = masks.get(name)
            if m is not None:
                self._masks[name][: h * w] = np.asarray(m, np.uint8).reshape(-1)
                flags |= 1 << k
        i[_W], i[_H], i[_STEP], i[_FLAGS] = w, h, step, flags
        i[_FRAMENO], i[_QUALITY] = frame_no, quality_code(quality)
        f[_TPUB], f[_TARR], f[_COMPUTE], f[_GAIN], f[_LAT] = (
            time.monotonic(),
            t_arrival,
            compute_ms,
            gain,
            latency_ms,
        )
        name = method.encode("ascii", "replace")[:METHOD_NAME_BYTES]
        self._mm[_NAME_OFF : _NAME_OFF + METHOD_NAME_BYTES] = name.ljust(METHOD_NAME_BYTES, b"\0")
        self._lock.end_write(0, frame_no)

    def counters(self) -> np.ndarray:
        """The worker's counters as a writable one-element record array of
        :data:`~cfsr_live.service.schema.COUNTER_DTYPE` in shared memory: the worker updates
        its fields in place (``c["frames_out"] += 1``), one word at a time."""
        return self._stats

    # -- reader (web process) -------------------------------------------------------------------
    @property
    def seq(self) -> int:
        """Sequence number of the newest frame (negative: none yet, or being written)."""
        return self._lock.read(0)

    def stats(self) -> WorkerCounters:
        """A copy of the worker's counters."""
        return WorkerCounters.from_record(self._stats[0])

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
                for k, name in enumerate(self.mask_names)
                if flags & (1 << k)
            }
            meta = (int(i[_FRAMENO]), float(f[_TPUB]), float(f[_TARR]), float(f[_COMPUTE]))
            gain, lat, tier = float(f[_GAIN]), float(f[_LAT]), int(i[_QUALITY])
            raw = bytes(self._mm[_NAME_OFF : _NAME_OFF + METHOD_NAME_BYTES])
            name = raw.split(b"\0")[0].decode()
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
                    quality=QUALITY_TIERS[tier] if 0 <= tier < len(QUALITY_TIERS) else "",
                )
        return None
