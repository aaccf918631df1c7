"""A shared-memory ring of bit-packed spike blocks between acquisition and consumers.

One producer (the acquisition thread) writes blocks of packed frames into fixed slots of a
memory-mapped file (in ``/dev/shm`` when it has room, so it lives in RAM); any number of
consumers in other processes (the reconstruction worker, a recorder) map the same file and
read at their own pace.

* The producer **never blocks** (unless a test asks for the deterministic ``blocking`` mode):
  it overwrites the oldest slot.
* Every block carries a sequence number, its first step index, flags, and the cumulative frame
  count before it, so a consumer that was overrun *detects* it, skips to fresh data, and counts
  exactly how many frames it lost (:attr:`RingReader.lost_frames`).
* Each slot is guarded by the package's seqlock (:mod:`cfsr_live.shm.seqlock`): its sequence number
is the block number, invalidated before the payload is touched and set after, so a consumer
  re-checks it after using the data and discards a torn read.
"""

from __future__ import annotations

import mmap
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cfsr_live.shm.files import attach_shared_file, create_shared_file, release_shared_file
from cfsr_live.shm.seqlock import WRITING, Seqlock

__all__ = ["DEFAULT_MAX_BYTES", "RING_PREFIX", "RingBlock", "RingReader", "SpikeRing"]

#: the default cap on one ring's size, bytes (1 GiB: 2 s of a 400 x 250 sensor at 40 kHz). A
#: ring is sized from a source's rate and geometry, which may come from a file anyone can put
#: in the data folder; without a cap a sidecar claiming 10 MHz asked for tens of GB.
DEFAULT_MAX_BYTES = 1 << 30

#: name prefix of the spike ring's shared-memory file
RING_PREFIX = "cfsr-ring"

_MAGIC = 0x474E4952_4B505343  # "CSPKRING"
_VERSION = 2  # 2: slot sequence words follow shm.seqlock
_HEADER_BYTES = 4096
_SLOT_HEADER = 64  # 8 x int64
_MAX_CONSUMERS = 8
# header fields (int64 index)
_H_MAGIC, _H_VERSION, _H_NSLOTS, _H_SLOTFRAMES, _H_FRAMEBYTES = 0, 1, 2, 3, 4
_H_HEAD, _H_FRAMES, _H_BLOCKING, _H_WAITS, _H_CLOSED = 5, 6, 7, 8, 9
_H_CPOS, _H_CACTIVE, _H_CPID = 16, 16 + _MAX_CONSUMERS, 16 + 2 * _MAX_CONSUMERS
# slot header fields
_S_SEQ, _S_INDEX, _S_NFRAMES, _S_FLAGS, _S_LOST, _S_CUM, _S_THOST = 0, 1, 2, 3, 4, 5, 6


@dataclass
class RingBlock:
    """One block read from the ring; ``data`` is a view into shared memory (see RingReader)."""

    seq: int
    index: int
    n_frames: int
    flags: int
    lost_before: int
    cum_before: int
    t_host: float
    data: np.ndarray


class SpikeRing:
    """The ring itself. Create in the producer with :meth:`create`, map elsewhere with
    :meth:`attach` (by path).

    Parameters (of :meth:`create`)
    ------------------------------
    n_slots : int
        Number of blocks held.
    slot_frames : int
        Frames per slot (blocks larger than this are split).
    frame_bytes : int
        Bytes per packed frame (12,500 for 400 x 250).
    """

    def __init__(self, path: Path, mm: mmap.mmap, owner: bool) -> None:
        self.path = path
        self._mm = mm
        self.owner = owner
        self._hdr = np.frombuffer(mm, np.int64, _HEADER_BYTES // 8, 0)
        if self._hdr[_H_MAGIC] != _MAGIC or self._hdr[_H_VERSION] != _VERSION:
            raise ValueError(f"{path}: not a spike ring (bad magic/version)")
        self.n_slots = int(self._hdr[_H_NSLOTS])
        self.slot_frames = int(self._hdr[_H_SLOTFRAMES])
        self.frame_bytes = int(self._hdr[_H_FRAMEBYTES])
        n = self.n_slots
        self._shdr = np.frombuffer(mm, np.int64, n * 8, _HEADER_BYTES).reshape(n, 8)
        self._sthost = self._shdr.view(np.float64)
        self._lock = Seqlock(self._shdr[:, _S_SEQ])
        off = _HEADER_BYTES + n * _SLOT_HEADER
        off = (off + 4095) // 4096 * 4096
        self._data = np.frombuffer(
            mm, np.uint8, n * self.slot_frames * self.frame_bytes, off
        ).reshape(n, self.slot_frames, self.frame_bytes)
        self.producer_waits = 0

    # -- construction -----------------------------------------------------------------------
    @staticmethod
    def nbytes_for(n_slots: int, slot_frames: int, frame_bytes: int) -> int:
        off = (_HEADER_BYTES + n_slots * _SLOT_HEADER + 4095) // 4096 * 4096
        return off + n_slots * slot_frames * frame_bytes

    @classmethod
    def slots_for(
        cls, frames: float, slot_frames: int, frame_bytes: int, *, max_bytes: int,
        min_slots: int = 8,
    ) -> int:
        """Slots for a ring of at least ``frames`` frames (and ``min_slots`` slots), fewer
        where that would be over ``max_bytes`` bytes: the cap wins over the wished duration.

        Raises
        ------
        ValueError
            Even ``min_slots`` slots are over ``max_bytes`` (one line with both numbers).
        """
        want = max(min_slots, -(-int(min(frames, 1 << 62)) // slot_frames))
        per_slot = _SLOT_HEADER + slot_frames * frame_bytes  # page rounding of headers aside
        fit = max(0, (max_bytes - _HEADER_BYTES - 4096) // per_slot)
        if fit < min_slots:
            need = cls.nbytes_for(min_slots, slot_frames, frame_bytes)
            raise ValueError(
                f"a ring of {min_slots} blocks of {slot_frames} frames x {frame_bytes} bytes "
                f"needs {need} bytes, over the ring's cap of {max_bytes} bytes"
            )
        return min(want, fit)

    @classmethod
    def create(
        cls,
        n_slots: int,
        slot_frames: int,
        frame_bytes: int,
        *,
        directory: str | os.PathLike | None = None,
        blocking: bool = False,
        max_bytes: int = DEFAULT_MAX_BYTES,
    ) -> SpikeRing:
        """A new ring of ``n_slots`` slots of ``slot_frames`` frames of ``frame_bytes`` bytes;
        ValueError (before any file is made) if it would be over ``max_bytes`` bytes."""
        if n_slots < 2 or slot_frames < 1 or frame_bytes < 1:
            raise ValueError(
                f"ring needs n_slots >= 2, slot_frames >= 1, frame_bytes >= 1; got "
                f"{n_slots}, {slot_frames}, {frame_bytes}"
            )
        size = cls.nbytes_for(n_slots, slot_frames, frame_bytes)
        if size > max_bytes:
            raise ValueError(f"a ring of {size} bytes is over the ring's cap of {max_bytes} bytes")
        path, mm = create_shared_file(RING_PREFIX, size, directory)
        # every page faulted in now (the file reads as zeros: a zero written per page), not
        # during the stream's first lap, where each block took 8 ms instead of under 1 and a
        # paced replay fell 0.1 s behind at every start
        np.frombuffer(mm, np.uint8)[:: mmap.PAGESIZE] = 0
        hdr = np.frombuffer(mm, np.int64, _HEADER_BYTES // 8, 0)
        hdr[_H_NSLOTS], hdr[_H_SLOTFRAMES], hdr[_H_FRAMEBYTES] = n_slots, slot_frames, frame_bytes
        hdr[_H_BLOCKING] = int(blocking)
        hdr[_H_VERSION] = _VERSION
        hdr[_H_MAGIC] = _MAGIC
        shdr = np.frombuffer(mm, np.int64, n_slots * 8, _HEADER_BYTES).reshape(n_slots, 8)
        Seqlock(shdr[:, _S_SEQ]).reset()
        del hdr, shdr
        return cls(path, mm, owner=True)

    @classmethod
    def attach(cls, path: str | os.PathLike) -> SpikeRing:
        """Map the ring another process created (consumers)."""
        return cls(Path(path), attach_shared_file(path), owner=False)

    def close(self) -> None:
        """Unmap (and, in the creating process, say :meth:`finish` and delete the file)."""
        if self._mm is None:
            return
        if self.owner:
            self.finish()
        self._hdr = self._shdr = self._sthost = self._data = None  # type: ignore[assignment]
        self._lock = None  # type: ignore[assignment]
        release_shared_file(self._mm, self.path, self.owner)
        self._mm = None  # type: ignore[assignment]

    # -- state ------------------------------------------------------------------------------
    @property
    def head(self) -> int:
        """Blocks published so far (the next block gets this sequence number)."""
        return int(self._hdr[_H_HEAD])

    @property
    def frames_published(self) -> int:
        """Frames written since the ring was created (the next block's ``cum_before``)."""
        return int(self._hdr[_H_FRAMES])

    @property
    def finished(self) -> bool:
        """True once the producer said no more blocks will come (:meth:`finish`), so a
        consumer in another process can drain the backlog and stop."""
        return self._hdr is None or bool(self._hdr[_H_CLOSED])

    def finish(self) -> None:
        """Producer: tell consumers that nothing more will be written (the ring stays
        mapped; :meth:`close` in the creating process says it too)."""
        self._hdr[_H_CLOSED] = 1

    @property
    def blocking(self) -> bool:
        return bool(self._hdr[_H_BLOCKING])

    @blocking.setter
    def blocking(self, value: bool) -> None:
        self._hdr[_H_BLOCKING] = int(value)

    @property
    def capacity_frames(self) -> int:
        return self.n_slots * self.slot_frames

    # -- producer ---------------------------------------------------------------------------
    def write(
        self,
        index: int,
        data: np.ndarray,
        *,
        flags: int = 0,
        lost_before: int = 0,
        t_host: float | None = None,
        stop_waiting: Callable[[], bool] | None = None,
    ) -> int:
        """Publish packed frames ``data`` (n, frame_bytes) starting at step ``index``.

        Returns the number of slots written. Never waits, except in ``blocking`` mode, where it
        waits (polling) until every registered consumer has room, or ``stop_waiting()`` is true.
        """
        data = np.asarray(data)
        if data.ndim != 2 or data.shape[1] != self.frame_bytes:
            raise ValueError(f"block must be (n, {self.frame_bytes}), got {data.shape}")
        th = time.monotonic() if t_host is None else t_host
        n = data.shape[0]
        written = 0
        for a in range(0, n, self.slot_frames):
            part = data[a : a + self.slot_frames]
            k = int(self._hdr[_H_HEAD])
            if self._hdr[_H_BLOCKING]:
                self._wait_room(k, stop_waiting)
            s = k % self.n_slots
            sh = self._shdr[s]
            self._lock.begin_write(s)
            m = part.shape[0]
            self._data[s, :m] = part
            sh[_S_INDEX] = index + a
            sh[_S_NFRAMES] = m
            sh[_S_FLAGS] = flags if a == 0 else 0
            sh[_S_LOST] = lost_before if a == 0 else 0
            sh[_S_CUM] = self._hdr[_H_FRAMES]
            self._sthost[s, _S_THOST] = th
            self._lock.end_write(s, k)
            self._hdr[_H_FRAMES] += m
            self._hdr[_H_HEAD] = k + 1
            written += 1
        return written

    def _wait_room(self, k: int, stop_waiting: Callable[[], bool] | None) -> None:
        hdr = self._hdr
        waited = False
        checked = time.monotonic()
        while True:
            act = hdr[_H_CACTIVE : _H_CACTIVE + _MAX_CONSUMERS]
            pos = hdr[_H_CPOS : _H_CPOS + _MAX_CONSUMERS]
            lag = [k - int(p) for p, a in zip(pos, act, strict=True) if a]
            if not lag or max(lag) < self.n_slots - 1:
                break
            if stop_waiting is not None and stop_waiting():
                break
            if time.monotonic() - checked > 0.1:
                self._drop_dead_consumers()
                checked = time.monotonic()
            waited = True
            time.sleep(0.0005)
        if waited:
            self.producer_waits += 1
            hdr[_H_WAITS] += 1

    def _drop_dead_consumers(self) -> None:
        """A registered consumer whose process died must not hold the producer forever."""
        hdr = self._hdr
        for i in range(_MAX_CONSUMERS):
            if hdr[_H_CACTIVE + i]:
                pid = int(hdr[_H_CPID + i])
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    hdr[_H_CACTIVE + i] = 0
                except PermissionError:
                    pass

    # -- consumers --------------------------------------------------------------------------
    def reader(
        self, *, start: str = "latest", register: bool = False, keep: int = 1
    ) -> RingReader:
        """A reader at the newest block (``start="latest"``) or the oldest held (``"oldest"``).

        ``register=True`` makes the producer honour this reader in ``blocking`` mode.
        ``keep`` is how many of the newest blocks an overrun reader resumes from.
        """
        return RingReader(self, start=start, register=register, keep=keep)


class RingReader:
    """A consumer's position in a :class:`SpikeRing`.

    Use ``blk = reader.poll()``, consume ``blk.data`` (a view into shared memory), then
    ``reader.release(blk)``, which returns False if the producer overwrote the slot meanwhile
    (the data you used was torn: discard it; its frames are counted lost).

    Attributes
    ----------
    lost_frames : int
        Frames this reader never got because the producer overwrote them.
    lost_blocks, overruns : int
        Blocks lost likewise, and how many times the reader found itself overrun.
    skipped_frames : int
        Frames passed over on purpose by :meth:`skip_to_latest` (not losses: the consumer
        chose to show newer data).
    frames_read : int
        Frames delivered valid.
    """

    def __init__(self, ring: SpikeRing, *, start: str, register: bool, keep: int) -> None:
        self.ring = ring
        self.keep = max(1, int(keep))
        head = ring.head
        if start == "latest":
            self.pos = head
        elif start == "oldest":
            self.pos = max(0, head - ring.n_slots + 1)
        else:
            raise ValueError(f"start must be 'latest' or 'oldest', got {start!r}")
        # A reader that starts at the head owns every frame from there on: frames lapped
        # before its first poll are lost to it, and counted (head is read before the frame
        # count, which the producer advances first, so a write in between can only hide a
        # loss, never invent one). Started behind the head, it counts from its first block.
        self._next_cum: int | None = ring.frames_published if self.pos == head else None
        self._skip_from: int | None = None  # _next_cum when skip_to_latest last jumped
        self.skipped_frames = 0
        self.lost_frames = 0
        self.lost_blocks = 0
        self.overruns = 0
        self.torn = 0
        self.frames_read = 0
        self._cid: int | None = None
        if register:
            hdr = ring._hdr
            for i in range(_MAX_CONSUMERS):
                if not hdr[_H_CACTIVE + i]:
                    hdr[_H_CPOS + i] = self.pos
                    hdr[_H_CPID + i] = os.getpid()
                    hdr[_H_CACTIVE + i] = 1
                    self._cid = i
                    break
            else:
                raise RuntimeError(f"more than {_MAX_CONSUMERS} registered ring consumers")

    def close(self) -> None:
        if self._cid is not None and self.ring._hdr is not None:
            self.ring._hdr[_H_CACTIVE + self._cid] = 0
        self._cid = None

    @property
    def backlog(self) -> int:
        """Blocks published but not yet read."""
        return max(0, self.ring.head - self.pos)

    def skip_to_latest(self, keep: int | None = None) -> None:
        """Jump to the newest ``keep`` blocks.

        The frames jumped over are counted in :attr:`skipped_frames` (when the next block is
        released), not in :attr:`lost_frames`: skipping is the consumer's choice, a loss is
        the producer's overrun.
        """
        head = self.ring.head
        k = self.keep if keep is None else max(1, keep)
        if head - self.pos > k:
            self.pos = head - k
            if self._next_cum is not None:
                self._skip_from = self._next_cum
            self._next_cum = None

    def poll(self) -> RingBlock | None:
        """The next block, or None if there is nothing new. Detects and counts overruns."""
        ring = self.ring
        while True:
            head = ring.head
            if self.pos >= head:
                return None
            if head - self.pos > ring.n_slots - 1:
                # the slot we want has been (or is being) reused: skip to fresh data
                self.overruns += 1
                self.pos = max(self.pos, head - self.keep)
            s = self.pos % ring.n_slots
            sh = ring._shdr[s]
            seq = ring._lock.read(s)
            if seq != self.pos:
                if seq == WRITING or seq > self.pos:
                    self.overruns += 1
                    self.pos = max(self.pos + 1, ring.head - self.keep)
                    continue
                return None  # not published yet (cannot happen with head > pos)
            nf = int(sh[_S_NFRAMES])
            blk = RingBlock(
                seq=seq,
                index=int(sh[_S_INDEX]),
                n_frames=nf,
                flags=int(sh[_S_FLAGS]),
                lost_before=int(sh[_S_LOST]),
                cum_before=int(sh[_S_CUM]),
                t_host=float(ring._sthost[s, _S_THOST]),
                data=ring._data[s, :nf],
            )
            return blk

    def release(self, blk: RingBlock) -> bool:
        """Finish with ``blk``; False if it was overwritten while in use (then discard it)."""
        ring = self.ring
        s = blk.seq % ring.n_slots
        valid = ring._lock.unchanged(s, blk.seq)
        if self._skip_from is not None:
            self.skipped_frames += max(0, blk.cum_before - self._skip_from)
            self._skip_from = None
        if self._next_cum is not None and blk.cum_before > self._next_cum:
            gap = blk.cum_before - self._next_cum
            self.lost_frames += gap
            self.lost_blocks += max(1, -(-gap // ring.slot_frames))
        self._next_cum = blk.cum_before + blk.n_frames
        self.pos = blk.seq + 1
        if self._cid is not None:
            ring._hdr[_H_CPOS + self._cid] = self.pos
        if valid:
            self.frames_read += blk.n_frames
        else:
            self.torn += 1
            self.lost_frames += blk.n_frames
            self.lost_blocks += 1
        return valid

    def read(self, out: np.ndarray | None = None) -> tuple[RingBlock, np.ndarray] | None:
        """Poll and copy: ``(block, copy_of_data)``, skipping torn blocks; None if nothing new."""
        while True:
            blk = self.poll()
            if blk is None:
                return None
            n = blk.n_frames
            if out is None:
                buf = blk.data.copy()
            else:
                buf = out[:n]
                buf[...] = blk.data
            if self.release(blk):
                blk.data = buf
                return blk, buf

    def wait(self, timeout: float, *, poll_s: float = 0.001) -> RingBlock | None:
        """Like :meth:`poll` but waits up to ``timeout`` seconds for a block."""
        end = time.monotonic() + timeout
        while True:
            blk = self.poll()
            if blk is not None or time.monotonic() >= end:
                return blk
            time.sleep(poll_s)
