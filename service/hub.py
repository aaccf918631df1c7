"""Fan-out of the newest frame to browser clients, each behind a latest-only queue.

The hub polls the worker's latest-frame slot, encodes the WebSocket message once per frame,
and offers it to every client. A client's queue holds at most one message: a new frame
replaces an unsent one (counted as a drop for that client), so a slow tab never slows the
others and never grows memory.

The WebSocket message is :mod:`cfsr_live.service.schema`'s (the frame header, then the image
and one bit plane per mask name of the slot).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from cfsr_live.service import schema
from cfsr_live.service.frameslot import FrameSlot, SlotFrame
from cfsr_live.service.status import ClientDrops, HubStatus

__all__ = [
    "FrameHub",
    "ClientQueue",
    "MAX_CLIENT_MESSAGE_BYTES",
    "MAX_CLIENT_MESSAGES_QUEUED",
    "encode_ws_message",
    "decode_ws_message",
]

log = logging.getLogger("cfsr.hub")

#: the largest WebSocket message a client may send, bytes, fragments together: a client only
#: ever sends ``{"max_fps": N}`` (a few dozen bytes). A larger one closes the connection (1009)
#: as it arrives, so 60 clients sending 15 MB fragments hold kilobytes, not a gigabyte.
MAX_CLIENT_MESSAGE_BYTES = 1024
#: client messages the server buffers per connection before it stops reading the socket
MAX_CLIENT_MESSAGES_QUEUED = 4

def encode_ws_message(f: SlotFrame, mask_names: tuple[str, ...]) -> bytes:
    """The frame as the binary WebSocket message (:func:`cfsr_live.service.schema.
    encode_ws_message`)."""
    return schema.encode_ws_message(f, mask_names)


def decode_ws_message(msg: bytes, mask_names: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Inverse of :func:`encode_ws_message` (tests and Python clients); ``mask_names``
    default to every mask the registered methods declare, as a server's slot holds them."""
    names = schema.display_masks() if mask_names is None else mask_names
    return schema.decode_ws_message(msg, names)


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

    def __init__(
        self, slot: FrameSlot, *, poll_s: float = 0.004,
        on_viewers: Callable[[int], None] | None = None,
    ) -> None:
        self.slot = slot
        #: told the number of clients when it changes (and once now): the worker computes
        #: for viewers only
        self.on_viewers = on_viewers
        self.poll_s = poll_s
        self.clients: dict[int, ClientQueue] = {}
        self.latest: SlotFrame | None = None
        self.latest_msg: bytes | None = None
        self._seq: int | None = None  # sequence number of self.latest
        self._times: deque[float] = deque(maxlen=512)
        self._since = time.monotonic()  # watching since: the rate's span is never longer
        self.frames_seen = 0
        self.closed_clients_dropped = 0
        self.closed_clients_sent = 0
        self.errors = 0  # fan-out failures (logged; the loop goes on)
        self.last_error: str | None = None
        self._new = asyncio.Event()
        self._tell_viewers()

    def _tell_viewers(self) -> None:
        if self.on_viewers is not None:
            self.on_viewers(len(self.clients))

    def add(self, client: ClientQueue) -> ClientQueue:
        self.clients[client.id] = client
        self._tell_viewers()
        if self.latest is not None:
            client.offer(self.latest_msg if client.kind == "ws" else self.latest)
        return client

    def remove(self, client: ClientQueue) -> None:
        if self.clients.pop(client.id, None) is not None:
            self.closed_clients_dropped += client.dropped
            self.closed_clients_sent += client.sent
            self._tell_viewers()

    def poll_once(self) -> bool:
        f = self.slot.read(since=self._seq)
        if f is None:
            return False
        self._seq = f.seq
        self.latest = f
        self.latest_msg = encode_ws_message(f, self.slot.mask_names)
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

    def fps(self, window: float = 2.0, longest: float = 10.0) -> float:
        """Frames delivered per second: the frames of the last ``window`` seconds over that
        span, or at a slow rate (under 3 frames a ``window`` over the last ``longest``
        seconds) those of the last ``longest`` seconds; never over more time than the hub has
        watched (at least a second). At one frame a second it reads 1, and a stream that
        stopped reads lower each poll.

        A count over a span, not the mean interval between the frames in it: frames come in
        bursts (pool processes side by side finish close together), and the intervals of the
        few frames of a slow stream read it 15-65 % high, or low on a hub that just started.
        """
        now = time.monotonic()
        span = min(longest, max(now - self._since, 1.0))
        n = sum(1 for t in self._times if now - t < span)
        if n * window < 3 * span:
            return n / span
        span = min(window, span)
        return sum(1 for t in self._times if now - t < span) / span

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
