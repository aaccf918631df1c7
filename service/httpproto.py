"""The HTTP/1.1 protocol the server runs: uvicorn's h11 protocol with a deadline on the request
head.

uvicorn times out an idle keep-alive connection, but not one that has sent part of a request
head (``GET / HTTP/1.1\\r\\nX-Slow: ``) and then nothing: each such connection holds a socket
and a parser for ever, and a few thousand of them exhaust the server's descriptors (the classic
"slowloris"). Here a connection whose request line and headers are not complete within
``header_timeout`` seconds of its first byte (or of its opening) is closed. A body or a
WebSocket, once the head is in, is not limited by it.
"""

from __future__ import annotations

import asyncio
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

__all__ = ["HEADER_TIMEOUT_S", "HeadTimeoutH11Protocol"]

#: seconds a client has to send a whole request head (a browser sends it in one packet)
HEADER_TIMEOUT_S = 10.0


class HeadTimeoutH11Protocol(H11Protocol):
    """:class:`H11Protocol` that closes a connection whose request head does not complete
    within :attr:`header_timeout` seconds."""

    header_timeout: float = HEADER_TIMEOUT_S

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self._head_timer: asyncio.TimerHandle | None = None

    def _arm_head_timer(self) -> None:
        if self._head_timer is None:
            self._head_timer = self.loop.call_later(self.header_timeout, self._head_timed_out)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.logger.info("closing a connection whose request head did not come within "
                             "%g s", self.header_timeout)
            self.transport.close()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_head_timer()

    def data_received(self, data: bytes) -> None:
        if self.conn.their_state is h11.IDLE:
            self._arm_head_timer()  # a new request begins (also on a kept-alive connection)
        super().data_received(data)
        if self.conn.their_state is not h11.IDLE:
            self._cancel_head_timer()

    def on_response_complete(self) -> None:
        # an idle kept-alive connection is uvicorn's keep-alive timeout's business
        self._cancel_head_timer()
        super().on_response_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)
