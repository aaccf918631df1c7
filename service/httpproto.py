"""The HTTP/1.1 protocol the server runs: uvicorn's h11 protocol with a deadline on the request
head and a cap on open connections; and a rate limit on the server's repeated log lines.

uvicorn times out an idle keep-alive connection, but not one that has sent part of a request
head (``GET / HTTP/1.1\\r\\nX-Slow: ``) and then nothing: each such connection holds a socket
and a parser for ever, and a few thousand of them exhaust the server's descriptors (the classic
"slowloris"). Here a connection whose request line and headers are not complete within
``header_timeout`` seconds of its first byte (or of its opening) is closed. A body or a
WebSocket, once the head is in, is not limited by it (the body has its own deadline,
:mod:`cfsr_live.service.body`).

A connection opened while :attr:`HeadTimeoutH11Protocol.max_connections` are open is closed at
once, before anything is read: the server then never runs out of descriptors (where asyncio
logs an ``accept()`` error many times a second and answers nobody, ``/healthz`` included).
``cfsr serve`` sets the cap below its open-file limit (:func:`connection_cap`).
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from cfsr_live.service.settings import DEFAULT_MAX_CONNECTIONS

__all__ = [
    "ACCEPT_BATCH",
    "LISTEN_QUEUE",
    "DEFAULT_MAX_CONNECTIONS",
    "HEADER_TIMEOUT_S",
    "HeadTimeoutH11Protocol",
    "RepeatedLogFilter",
    "connection_cap",
    "install_log_rate_limit",
    "widen_listen_queue",
    "raise_open_file_limit",
]

#: seconds a client has to send a whole request head (a browser sends it in one packet)
HEADER_TIMEOUT_S = 10.0
# open connections at most by default (cfsr_live.service.settings, where `cfsr serve --help`
# reads it without importing uvicorn); fewer where the open-file limit is lower
# (:func:`connection_cap`)
#: connections accepted in one go (uvicorn's ``backlog``: asyncio accepts up to this many per
#: wake-up, before any of them is counted against the cap)
ACCEPT_BATCH = 16
#: connections the kernel queues before they are accepted (they hold no descriptor of ours
#: there); set on the listening sockets after start (:func:`widen_listen_queue`), so that a
#: burst is queued, not dropped (a dropped connection retries after 1 s, then 3 s)
LISTEN_QUEUE = 2048
#: descriptors kept free beyond those open at start and the cap: accept batches taken in
#: the loop's turns before their connections are counted (measured: up to 5 in a burst), plus
#: the server's own (recordings, listings, worker pipes)
_FD_RESERVE = 8 * ACCEPT_BATCH + 32


class HeadTimeoutH11Protocol(H11Protocol):
    """:class:`H11Protocol` that closes a connection whose request head does not complete
    within :attr:`header_timeout` seconds."""

    header_timeout: float = HEADER_TIMEOUT_S
    #: open connections at most; one more is closed as soon as it is accepted
    max_connections: int = DEFAULT_MAX_CONNECTIONS

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
        if len(self.connections) > self.max_connections:
            self.logger.warning("closing a new connection: %d are open, the most the server "
                                "keeps (--max-connections)", self.max_connections)
            transport.abort()  # frees the descriptor now; connection_lost forgets it
            return
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


def widen_listen_queue(sockets, queue: int = LISTEN_QUEUE) -> None:
    """Give each listening socket a kernel queue of ``queue`` connections (asyncio set it to
    the accept batch, :data:`ACCEPT_BATCH`)."""
    import socket

    for ts in sockets:
        with socket.socket(fileno=os.dup(ts.fileno())) as s:
            s.listen(queue)


def raise_open_file_limit(want: int = 65536) -> int:
    """Raise this process's soft open-file limit towards its hard limit (at most ``want``);
    the soft limit now in force. A server's connections are descriptors: a soft limit of 1,024
    (a common default) is reached by a thousand idle sockets."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = want if hard == resource.RLIM_INFINITY else min(want, hard)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    return soft


def connection_cap(requested: int, soft_limit: int) -> int:
    """The connection cap in force: ``requested``, lowered to leave :data:`_FD_RESERVE`
    descriptors free beyond those open now under ``soft_limit`` (at least 16)."""
    try:
        open_now = len(os.listdir("/proc/self/fd"))
    except OSError:
        open_now = 64
    return max(16, min(requested, soft_limit - open_now - _FD_RESERVE))


class RepeatedLogFilter(logging.Filter):
    """Lets a log line through once per ``window_s`` seconds per (logger, message template);
    the next one let through says how many were held back. A client that makes the server fail
    the same way thousands of times a second (EMFILE on ``accept()``, a bad WebSocket frame)
    must not fill the disk with the same traceback."""

    def __init__(self, window_s: float = 10.0) -> None:
        super().__init__()
        self.window_s = window_s
        self._seen: dict[tuple[str, str], tuple[float, int]] = {}
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        level = next((lv for text, lv in _QUIETED if str(record.msg).startswith(text)), None)
        if record.exc_info and level is not None:
            # handled where it happens (the connection closed, the accept retried): one
            # line at its level, not an ERROR with a traceback
            record.exc_info = record.exc_text = None
            record.levelno, record.levelname = level, logging.getLevelName(level)
            if not logging.getLogger(record.name).isEnabledFor(level):
                return False
        key = (record.name, str(record.msg)[:200])
        now = time.monotonic()
        with self._lock:
            last, held = self._seen.get(key, (-1e18, 0))
            if now - last < self.window_s:
                self._seen[key] = (last, held + 1)
                return False
            if len(self._seen) > 1024:  # bounded: forget the oldest half
                for k in sorted(self._seen, key=lambda k: self._seen[k][0])[:512]:
                    del self._seen[k]
            self._seen[key] = (now, 0)
        if held:
            record.msg = f"{record.msg} [{held} more like this in the last {now - last:.0f} s]"
        return True


#: log messages logged as ERROR with a traceback for something handled, and their level:
#: a client's invalid UTF-8 (uvicorn closes with 1007), and descriptors running out during a
#: burst (asyncio pauses accepting for 1 s; the connection cap then catches up)
_QUIETED = (("Invalid UTF-8 sequence received from client", logging.INFO),
            ("socket.accept() out of system resource", logging.WARNING))

#: loggers whose lines a client can make repeat: asyncio's accept loop, uvicorn's protocols
_RATE_LIMITED = ("asyncio", "uvicorn.error", "websockets", "websockets.server",
                 "websockets.protocol", "cfsr.app")


def install_log_rate_limit(window_s: float = 10.0) -> RepeatedLogFilter:
    """Attach one :class:`RepeatedLogFilter` to each logger a client can make repeat."""
    flt = RepeatedLogFilter(window_s)
    for name in _RATE_LIMITED:
        logging.getLogger(name).addFilter(flt)
    return flt
