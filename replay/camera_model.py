"""The emulated spike camera's *device side*: sensor clock, FIFO, block framing of our wire
protocol (``docs/protocol.md``), vendor control requests and fault injection.

One class shared by every emulation tier, so they cannot disagree: the fake pyusb backend
(:mod:`cfsr_live.replay.fake_usb`, unit tests) and the usbdevfs emulator under umockdev
(:mod:`cfsr_live.replay.umockdev_camera`, real libusb + pyusb). Frames come from a recording
(memory-mapped ``.dat``), looped; the device's frame counter keeps counting.

Rules reproduced from the real Linux USB stack (``notes/usb-emulation.md`` section 4.3): an IN
read whose length is not a multiple of the 1024-byte packet while the stream continues ends in
babble (``-EOVERFLOW``) with the stream advanced to the packet boundary; reads above 16 MiB are
refused with ``ENOMEM`` (checked by the transports, at submit time).

Paced mode (``paced=True``): the sensor makes ``rate_hz`` frames per second of the given clock
into a FIFO of ``fifo_frames``; a block is released when its last frame exists; when the host
does not read fast enough the FIFO overflows and the oldest frames are dropped (counted in
``dropped_total``; the next block's index jumps and carries ``BF_DEVICE_OVERFLOW``). Unpaced,
a block is ready whenever the host asks (as fast as it reads).

Faults (``inject(kind, ...)``, consumed by the next bulk IN transfer):

``stall``        the endpoint halts (-EPIPE) until the host clears it; the block is lost.
``overflow``     babble mid-block: half a block arrives with -EOVERFLOW and the rest of it
                 arrives at the start of the next read, so the host must resynchronise.
``short``        a short packet ends the transfer early; the rest of the block is dropped.
``timeout``      the device sends nothing for ``seconds`` (its sensor paused: no loss).
``corrupt``      one payload byte of the next block is flipped (payload CRC fails).
``corrupt_header``  one header byte of the next block is flipped (header CRC fails).
``unplug``       the device is gone for ``seconds`` (every request fails with ENODEV); the
                 sensor keeps running, so frames made meanwhile are lost.
``unplug_eio``   the same, but the transfer in flight fails with a protocol error first
                 (libusb reports errno 5, EIO), as the real kernel sometimes does.

``expected_loss`` is what an honest host must count as lost: device drops plus the frames of
blocks destroyed in transit.
"""

from __future__ import annotations

import ctypes
import errno
import threading
import time
import zlib
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cfsr.layout import STEP_RATE_HZ
from cfsr.spikes import SpikeRecording
from cfsr_live.driver import protocol as P

__all__ = ["CameraModel", "FAULTS"]

FAULTS = ("stall", "overflow", "short", "timeout", "corrupt", "corrupt_header", "unplug",
          "unplug_eio")


@dataclass
class _Block:
    segments: list[tuple[int, int]]  # (address, length)
    length: int
    frames: int
    keep: list[Any] = field(default_factory=list)  # keeps the buffers behind the addresses
    mangled: bool = False  # already counted as destroyed in transit


class CameraModel:
    """See the module notes.

    Parameters
    ----------
    recording : SpikeRecording
        Frames the sensor "sees" (looped).
    paced : bool
        Real-time sensor clock and FIFO (True) or as fast as the host reads (False).
    rate_hz : float
        Sensor frames per second in paced mode (40,000).
    fifo_frames : int
        Device FIFO capacity in frames.
    clock : callable
        Monotonic seconds (tests may pass a fake clock).
    """

    def __init__(
        self,
        recording: SpikeRecording,
        *,
        paced: bool = False,
        rate_hz: float = float(STEP_RATE_HZ),
        fifo_frames: int = 16384,
        serial: str = "EMU00001",
        firmware: str = "emu-1",
        clock=time.monotonic,
    ) -> None:
        self.rec = recording
        lay = recording.layout
        self.layout = lay
        self.fb = lay.frame_bytes
        self.packed = np.ascontiguousarray(recording.packed_frames)
        self.flat = self.packed.reshape(-1)
        self._base = self.packed.ctypes.data
        self.n_frames = recording.n_frames
        self.paced = paced
        self.rate = float(rate_hz)
        self.fifo_frames = int(fifo_frames)
        self.serial, self.firmware = serial, firmware
        self.clock = clock
        self.lock = threading.RLock()
        self.align = P.frame_alignment(self.fb)
        self.default_fpb = self.align * max(1, 256 // self.align)
        self.info = P.DeviceInfo(
            width=lay.width,
            height=lay.height,
            stored_width=lay.stored_width,
            layout_flags=(P.LF_FLIPUD if lay.flipud else 0) | (P.LF_FLIPLR if lay.fliplr else 0),
            frame_bytes=self.fb,
            rate_hz=int(round(self.rate)),
            max_block_bytes=P.MAX_TRANSFER_BYTES,
            packet_bytes=P.PACKET_BYTES,
            ep_in=P.EP_IN,
            serial=serial,
            firmware=firmware,
            default_frames_per_block=self.default_fpb,
        )
        self._zeros = np.zeros(P.PACKET_BYTES, np.uint8)
        # sensor clock: frame index = _i0 + (now - _t0) * rate
        self._t0 = clock()
        self._i0 = 0
        self.streaming = False
        self.fpb = self.default_fpb
        self.block_bytes = P.block_bytes(self.fpb, self.fb)
        self.next_index = 0
        self.dropped_total = 0
        self.mangled_frames = 0
        self.blocks_sent = 0
        self.frames_sent = 0
        self.starts = 0
        self._seq = 0
        self._queue: deque[_Block] = deque()
        self._off = 0
        self._overflow_flag = False
        self._session_start = False
        self._interrupted = False
        self._crc_cache: dict[int, int] = {}
        self.faults: deque[tuple[str, float]] = deque()
        self._corrupt_next: str | None = None
        self.halted = False
        self._quiet_until = 0.0
        self._unplugged_until: float | None = None
        self.events: list[str] = []

    # -- faults -----------------------------------------------------------------------------
    def inject(self, kind: str, seconds: float = 0.2) -> None:
        if kind not in FAULTS:
            raise ValueError(f"unknown fault {kind!r}; faults: {', '.join(FAULTS)}")
        with self.lock:
            self.faults.append((kind, float(seconds)))

    @property
    def expected_loss(self) -> int:
        return self.dropped_total + self.mangled_frames

    def unplug(self, seconds: float | None = None) -> None:
        """Disconnect now (for ``seconds``, or until :meth:`replug`)."""
        with self.lock:
            now = self.clock()
            self._unplugged_until = float("inf") if seconds is None else now + seconds
            if self.streaming:
                self._update(now)
                lost = sum(b.frames for b in self._queue if not b.mangled)
                self.dropped_total += lost
                self._queue.clear()
                self._off = 0
                self._interrupted = True
            self.streaming = False
            self.halted = False
            self.events.append("unplug")

    def replug(self) -> None:
        with self.lock:
            self._unplugged_until = None
            self.events.append("replug")

    def unplugged(self) -> bool:
        with self.lock:
            u = self._unplugged_until
            if u is None:
                return False
            if self.clock() >= u:
                self._unplugged_until = None
                self.events.append("replug")
                return False
            return True

    def clear_halt(self) -> None:
        with self.lock:
            self.halted = False

    # -- sensor and FIFO ----------------------------------------------------------------------
    def sensor_index(self, now: float) -> int:
        if not self.paced:
            return self.next_index + self.fpb * 1_000_000
        return self._i0 + int((now - self._t0) * self.rate)

    def _update(self, now: float) -> None:
        if not (self.paced and self.streaming):
            return
        # frames made but not yet packaged (blocks are packaged only when the host reads)
        backlog = self.sensor_index(now) - self.next_index
        if backlog > self.fifo_frames:
            skip = backlog - self.fifo_frames
            self.next_index += skip
            self.dropped_total += skip
            self._overflow_flag = True

    def _ready(self, now: float) -> bool:
        if now < self._quiet_until:
            return False
        return self.sensor_index(now) >= self.next_index + self.fpb

    def next_ready_in(self) -> float:
        """Seconds until the next block is due (0 when ready, small when unknown)."""
        with self.lock:
            now = self.clock()
            if not self.streaming or self.halted:
                return 0.005
            if now < self._quiet_until:
                return self._quiet_until - now
            if not self.paced:
                return 0.0
            missing = self.next_index + self.fpb - self.sensor_index(now)
            return max(0.0, missing / self.rate)

    def _payload_crc(self, pos: int, count: int) -> int:
        key = pos
        c = self._crc_cache.get(key)
        if c is None:
            fb, n = self.fb, self.n_frames
            first = min(count, n - pos)
            c = zlib.crc32(self.flat[pos * fb : (pos + first) * fb])
            rest = count - first
            while rest > 0:
                k = min(rest, n)
                c = zlib.crc32(self.flat[: k * fb], c)
                rest -= k
            if len(self._crc_cache) < 65536:
                self._crc_cache[key] = c
        return c

    def _make_block(self) -> _Block:
        fb, n, count = self.fb, self.n_frames, self.fpb
        idx = self.next_index
        pos = idx % n
        flags = 0
        if self._overflow_flag:
            flags |= P.BF_DEVICE_OVERFLOW
            self._overflow_flag = False
        if self._session_start:
            flags |= P.BF_SESSION_START
            self._session_start = False
        lay = self.layout
        hdr = P.BlockHeader(
            first_index=idx,
            frame_count=count,
            frames_per_block=count,
            width=lay.width,
            height=lay.height,
            stored_width=lay.stored_width,
            layout_flags=self.info.layout_flags,
            frame_bytes=fb,
            flags=flags,
            block_bytes=self.block_bytes,
            payload_crc=self._payload_crc(pos, count),
            device_dropped=self.dropped_total,
            sequence=self._seq,
        )
        hbuf = np.zeros(P.HEADER_BYTES, np.uint8)
        hbuf[:64] = np.frombuffer(P.pack_header(hdr), np.uint8)
        segs = [(hbuf.ctypes.data, P.HEADER_BYTES)]
        keep: list[Any] = [hbuf]
        left, p = count, pos
        while left > 0:
            k = min(left, n - p)
            segs.append((self._base + p * fb, k * fb))
            left -= k
            p = 0
        pad = self.block_bytes - P.HEADER_BYTES - count * fb
        if pad:
            segs.append((self._zeros.ctypes.data, pad))
        blk = _Block(segs, self.block_bytes, count, keep)
        if self._corrupt_next is not None:
            buf = np.empty(self.block_bytes, np.uint8)
            self._copy(blk, 0, buf.ctypes.data, self.block_bytes)
            at = 20 if self._corrupt_next == "corrupt_header" else P.HEADER_BYTES + 100
            buf[at] ^= 0x5A
            blk = _Block([(buf.ctypes.data, self.block_bytes)], self.block_bytes, count, [buf])
            self._mangle(blk)
            self._corrupt_next = None
        self.next_index += count
        self._seq += 1
        self.blocks_sent += 1
        self.frames_sent += count
        return blk

    @staticmethod
    def _copy(blk: _Block, off: int, dst: int, n: int) -> None:
        done = 0
        pos = 0
        for addr, length in blk.segments:
            if off >= pos + length:
                pos += length
                continue
            start = max(0, off - pos)
            k = min(length - start, n - done)
            if k <= 0:
                break
            ctypes.memmove(dst + done, addr + start, k)
            done += k
            pos += length
            if done >= n:
                break

    def _mangle(self, blk: _Block) -> None:
        if not blk.mangled:
            blk.mangled = True
            self.mangled_frames += blk.frames

    def _available(self) -> int:
        return sum(b.length for b in self._queue) - self._off

    def _ensure(self, now: float, n: int) -> bool:
        """Queue blocks until ``n`` bytes are ready; False if the sensor has not made them."""
        while self._available() < n:
            if not self._ready(now):
                return False
            self._queue.append(self._make_block())
        return True

    def _fill(self, addr: int, n: int) -> None:
        done = 0
        while done < n:
            blk = self._queue[0]
            k = min(n - done, blk.length - self._off)
            self._copy(blk, self._off, addr + done, k)
            done += k
            self._off += k
            if self._off == blk.length:
                self._queue.popleft()
                self._off = 0

    # -- bulk IN -------------------------------------------------------------------------------
    def bulk_in(self, addr: int, n: int) -> tuple[int, int] | None:
        """Serve one bulk IN transfer of ``n`` bytes into memory at ``addr``.

        Returns ``(status, nbytes)`` with status 0 or a negative errno, or None when no data
        is ready yet (the transport waits or times out).
        """
        with self.lock:
            now = self.clock()
            if self.halted:
                return -errno.EPIPE, 0
            if not self.streaming:
                return None
            self._update(now)
            while self.faults:
                kind, secs = self.faults[0]
                if kind in ("corrupt", "corrupt_header"):
                    self.faults.popleft()
                    self._corrupt_next = kind
                    continue
                if kind == "timeout":
                    self.faults.popleft()
                    self._quiet_until = now + secs
                    self._t0 += secs  # the sensor pauses too: nothing is lost
                    self.events.append("timeout")
                    return None
                if kind in ("unplug", "unplug_eio"):
                    self.faults.popleft()
                    self.unplug(secs)
                    return (-errno.ESHUTDOWN if kind == "unplug" else -errno.EPROTO), 0
                # stall / overflow / short act on the next whole block
                if not self._ensure(now, self.block_bytes - self._off if self._off else 1):
                    return None
                self.faults.popleft()
                self.events.append(kind)
                blk = self._queue[0]
                if kind == "stall":
                    self._queue.popleft()
                    self._off = 0
                    self._mangle(blk)
                    self.halted = True
                    return -errno.EPIPE, 0
                if kind == "short":
                    # ends in a short packet
                    k = max(1, min(n - 1, blk.length - self._off - 1, blk.length // 2 + 100))
                    self._copy(blk, self._off, addr, k)
                    self._queue.popleft()
                    self._off = 0
                    self._mangle(blk)
                    return 0, k
                if kind == "overflow":
                    k = min(n, (blk.length // 2) // P.PACKET_BYTES * P.PACKET_BYTES)
                    self._mangle(blk)
                    self._fill(addr, k)  # the rest of this block comes in the next read
                    return -errno.EOVERFLOW, k
            if now < self._quiet_until:
                return None
            mps = P.PACKET_BYTES
            want = -(-n // mps) * mps
            if not self._ensure(now, want):
                return None
            self._fill(addr, n)
            if want != n:
                # the stream continues past a partial packet: babble; skip to the boundary
                self._skip(want - n)
                return -errno.EOVERFLOW, n
            return 0, n

    def _skip(self, k: int) -> None:
        while k > 0 and self._queue:
            blk = self._queue[0]
            s = min(k, blk.length - self._off)
            self._off += s
            k -= s
            if self._off == blk.length:
                self._queue.popleft()
                self._off = 0

    # -- control requests ---------------------------------------------------------------------
    def control_in(self, request: int, value: int, index: int, length: int) -> bytes:
        with self.lock:
            if request == P.REQ_GET_INFO:
                return P.pack_info(self.info)[:length]
            if request == P.REQ_GET_STATUS:
                now = self.clock()
                self._update(now)
                fifo = 0
                if self.paced and self.streaming:
                    fifo = max(0, self.sensor_index(now) - self.next_index)
                st = P.DeviceStatus(
                    streaming=self.streaming,
                    frames_per_block=self.fpb,
                    next_index=self.next_index,
                    dropped_total=self.dropped_total,
                    fifo_frames=fifo,
                )
                return P.pack_status(st)[:length]
        raise ValueError(f"unknown vendor IN request 0x{request:02x}")

    def control_out(self, request: int, value: int, index: int, data: bytes = b"") -> None:
        with self.lock:
            if request == P.REQ_START:
                fpb = int(value) or self.default_fpb
                if fpb % self.align:
                    raise ValueError(f"frames per block {fpb} not a multiple of {self.align}")
                self.block_bytes = P.block_bytes(fpb, self.fb)
                if fpb != self.fpb:
                    self._crc_cache.clear()
                self.fpb = fpb
                now = self.clock()
                s = self.sensor_index(now) if self.paced else self.next_index
                if self._interrupted:
                    # frames the sensor made while the host was away never reach it
                    self.dropped_total += max(0, s - self.next_index)
                    self._interrupted = False
                self.next_index = max(self.next_index, s)
                self._queue.clear()
                self._off = 0
                self.streaming = True
                self.halted = False
                self._session_start = True
                self.starts += 1
                self.events.append(f"start {fpb}")
                return
            if request == P.REQ_STOP:
                self.streaming = False
                self._queue.clear()
                self._off = 0
                self.events.append("stop")
                return
        raise ValueError(f"unknown vendor OUT request 0x{request:02x}")
