"""One clean stop for every signal that ends the server.

A closed terminal (SIGHUP), Ctrl+C (SIGINT), Ctrl+\\ (SIGQUIT) and ``kill`` (SIGTERM) all run the
same stop: the recording's sidecar is written, the source, worker, ring and frame slot are
closed, and the process leaves through Python's normal exit, whose handlers release the
multiprocessing queues' semaphores. (uvicorn handles only SIGINT and SIGTERM, and after its
graceful stop it re-raises the signal under the default handler, which kills the process
before those exit handlers run: "There appear to be 6 leaked semaphore objects"; SIGHUP and
SIGQUIT killed the process at once, leaving the ring and slot in ``/dev/shm`` and the
recording without its sidecar.)

A signal that arrives before the server runs (the demo being simulated, the worker starting)
raises :class:`Stopped` in the main thread, which unwinds the start through its clean-up. The
process exits with status 128 + the signal's number, as a shell reports a signal's end.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

__all__ = ["ENDING_SIGNALS", "Stopped", "ignore_ending_signals", "raise_on_ending_signals",
           "start_resource_tracker", "trap_ending_signals"]

ENDING_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, n)
)


class Stopped(KeyboardInterrupt):
    """An ending signal arrived while the server was starting."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum: int, frame) -> None:
    raise Stopped(signum)


def raise_on_ending_signals() -> None:
    """Until the server runs: an ending signal raises :class:`Stopped` in the main thread."""
    if threading.current_thread() is threading.main_thread():
        for s in ENDING_SIGNALS:
            signal.signal(s, _raise_stopped)


def ignore_ending_signals() -> None:
    """While the service stops: a second signal must not cut the stop short."""
    if threading.current_thread() is threading.main_thread():
        for s in ENDING_SIGNALS:
            signal.signal(s, signal.SIG_IGN)


@contextlib.contextmanager
def trap_ending_signals(handler) -> Iterator[None]:
    """Every ending signal calls ``handler(signum, frame)`` inside the block (the server's
    graceful stop); the previous handlers come back after it, and nothing is re-raised."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, handler) for s in ENDING_SIGNALS}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def start_resource_tracker() -> None:
    """Start multiprocessing's resource tracker now, deaf to SIGHUP and SIGQUIT.

    A closed terminal sends SIGHUP to the whole process group; the tracker ignores only
    SIGINT and SIGTERM, so it died with the terminal, and the server's clean stop that
    followed found no tracker to release its semaphores to. Dispositions set to "ignore"
    survive the tracker's exec, so it is started while they are set here."""
    from multiprocessing import resource_tracker

    deaf = [s for s in ENDING_SIGNALS if s not in (signal.SIGINT, signal.SIGTERM)]
    if threading.current_thread() is not threading.main_thread():
        resource_tracker.ensure_running()
        return
    old = {s: signal.signal(s, signal.SIG_IGN) for s in deaf}
    try:
        resource_tracker.ensure_running()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
