"""Fan-out of the newest frame to browser clients, each behind a latest-only queue.

The hub polls the worker's latest-frame slot, encodes the WebSocket message once per frame,
and offers it to every client. A client's queue holds at most one message: a new frame
replaces an unsent one (counted as a drop for that client), so a slow tab never slows the
others and never grows memory.

WebSocket message (binary, little-endian)::

    offset size  field
    0      4     magic b"CFSR"
    4      2     version (1)
    6      2     header length in bytes (64)
    8      8     step index t of the frame (int64; 1 step = 25 us)
    16     4     frame number (uint32, counts published frames)
    20     2     width W
    22     2     height H
    24     1     mask flags: bit0 coarse present, bit1 fine present
    25     3     reserved
    28     4     gain (float32, spikes/step shown as 255)
    32     4     compute time (float32, ms)
    36     4     latency (float32, ms: newest spike used -> published)
    40     24    method name (ASCII, NUL padded)
    64     W*H   8-bit image, row-major, upright
    then         coarse mask, ceil(W*H/8) bytes, bit p%8 of byte p//8 (LSB first)
    then         fine mask, same layout (zeros when absent)
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import struct
import time
from collections import deque
from typing import Any

import numpy as np

from cfsr_live.service.status import ClientDrops, HubStatus
from cfsr_live.shm.frameslot import FrameSlot, SlotFrame

__all__ = ["FrameHub", "ClientQueue", "encode_ws_message", "decode_ws_message", "WS_HEADER"]

log = logging.getLogger("cfsr.hub")

WS_MAGIC = b"CFSR"
WS_VERSION = 1
WS_HEADER = struct.Struct("<4sHHqIHHB3xfff24s")
assert WS_HEADER.size == 64


def encode_ws_message(f: SlotFrame) -> bytes:
    n = f.width * f.height
    flags = 0
    parts = []
    for k, name in enumerate(("coarse", "fine")):
        m = f.masks.get(name)
        if m is not None:
            flags |= 1 << k
            parts.append(np.packbits(m.reshape(-1) != 0, bitorder="little").tobytes())
        else:
            parts.append(bytes((n + 7) // 8))
    head = WS_HEADER.pack(
        WS_MAGIC,
        WS_VERSION,
        WS_HEADER.size,
        f.step,
        f.frame_no & 0xFFFFFFFF,
        f.width,
        f.height,
        flags,
        f.gain,
        f.compute_ms,
        f.latency_ms,
        f.method.encode("ascii", "replace")[:24],
    )
    return b"".join([head, f.image.tobytes(), *parts])


def decode_ws_message(msg: bytes) -> dict[str, Any]:
    """Inverse of :func:`encode_ws_message` (used by tests and Python clients)."""
    (magic, ver, hlen, step, frame_no, w, h, flags, gain, comp, lat, name) = WS_HEADER.unpack_from(
        msg
    )
    if magic != WS_MAGIC:
        raise ValueError(f"not a CFSR frame message (magic {magic!r})")
    n = w * h
    img = np.frombuffer(msg, np.uint8, n, hlen).reshape(h, w)
    nb = (n + 7) // 8
    masks = {}
    for k, nm in enumerate(("coarse", "fine")):
        raw = np.frombuffer(msg, np.uint8, nb, hlen + n + k * nb)
        if flags & (1 << k):
            masks[nm] = np.unpackbits(raw, bitorder="little")[:n].reshape(h, w).astype(bool)
    return {
        "version": ver,
        "step": step,
        "frame_no": frame_no,
        "width": w,
        "height": h,
        "gain": gain,
        "compute_ms": comp,
        "latency_ms": lat,
        "method": name.rstrip(b"\0").decode(),
        "image": img,
        "masks": masks,
    }


class ClientQueue:
    """A latest-only queue for one client; ``dropped`` counts replaced, never-sent frames."""

    _ids = itertools.count(1)

    def __init__(self, kind: str, *, max_fps: float | None = None, peer: str = "") -> None:
        self.id = next(self._ids)
        self.kind = kind
        self.peer = peer
        self.max_fps = max_fps
        self.created = time.monotonic()
        self.sent = 0
        self.dropped = 0
        self._item: Any = None
        self._event = asyncio.Event()

    def offer(self, item: Any) -> None:
        if self._item is not None:
            self.dropped += 1
        self._item = item
        self._event.set()

    async def get(self) -> Any:
        while self._item is None:
            self._event.clear()
            await self._event.wait()
        item, self._item = self._item, None
        self._event.clear()
        return item

    @property
    def pending(self) -> int:
        return 0 if self._item is None else 1

    @property
    def connected_s(self) -> float:
        """Seconds since the client connected (ms resolution)."""
        return round(time.monotonic() - self.created, 3)

    def status(self) -> ClientDrops:
        """This client's counters (one row of ``drops.per_client`` in ``GET /api/status``),
        read from its attributes of the same names."""
        return ClientDrops.model_validate(self, from_attributes=True)


class FrameHub:
    """Polls the slot, keeps the newest frame, feeds client queues."""

    def __init__(self, slot: FrameSlot, *, poll_s: float = 0.004) -> None:
        self.slot = slot
        self.poll_s = poll_s
        self.clients: dict[int, ClientQueue] = {}
        self.latest: SlotFrame | None = None
        self.latest_msg: bytes | None = None
        self._seq: int | None = None  # sequence number of self.latest
        self._times: deque[float] = deque(maxlen=512)
        self.frames_seen = 0
        self.closed_clients_dropped = 0
        self.closed_clients_sent = 0
        self.errors = 0  # fan-out failures (logged; the loop goes on)
        self.last_error: str | None = None
        self._new = asyncio.Event()

    def add(self, client: ClientQueue) -> ClientQueue:
        self.clients[client.id] = client
        if self.latest is not None:
            client.offer(self.latest_msg if client.kind == "ws" else self.latest)
        return client

    def remove(self, client: ClientQueue) -> None:
        if self.clients.pop(client.id, None) is not None:
            self.closed_clients_dropped += client.dropped
            self.closed_clients_sent += client.sent

    def poll_once(self) -> bool:
        f = self.slot.read(since=self._seq)
        if f is None:
            return False
        self._seq = f.seq
        self.latest = f
        self.latest_msg = encode_ws_message(f)
        self.frames_seen += 1
        self._times.append(time.monotonic())
        for c in list(self.clients.values()):
            c.offer(self.latest_msg if c.kind == "ws" else f)
        self._new.set()
        self._new = asyncio.Event()
        return True

    async def wait_frame(self, timeout: float) -> SlotFrame | None:
        ev = self._new
        try:
            await asyncio.wait_for(ev.wait(), timeout)
        except TimeoutError:
            return None
        return self.latest

    async def run(self) -> None:
        last_logged = ""
        while True:
            try:
                self.poll_once()
            except Exception as exc:  # noqa: BLE001 - never let the fan-out die, but say why
                text = f"{type(exc).__name__}: {exc}"
                self.last_error = text
                self.errors += 1
                if text != last_logged:  # once per distinct error, not 10 times a second
                    log.exception("frame fan-out failed: %s", text)
                    last_logged = text
                await asyncio.sleep(0.1)
            await asyncio.sleep(self.poll_s)

    def fps(self, window: float = 2.0) -> float:
        now = time.monotonic()
        ts = [t for t in self._times if now - t <= window]
        if len(ts) < 2:
            return 0.0
        span = max(now - ts[0], 1e-6)
        return (len(ts) - 1) / span if span < window else len(ts) / window

    def status(self) -> HubStatus:
        """The hub's report: output rate, newest frame, and every client's counters (the
        drops total also counts clients that are gone)."""
        clients = [c.status() for c in list(self.clients.values())]
        latest = self.latest
        return HubStatus(
            output_fps=self.fps(),
            frame_step=None if latest is None else latest.step,
            clients=clients,
            client_drops=self.closed_clients_dropped + sum(c.dropped for c in clients),
        )
