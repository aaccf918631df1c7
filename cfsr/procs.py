"""Child processes of cfsr and of the live service: how they are spawned, how they leave the
stop signals to their owner, how their queues are released, and the heartbeat a process sends
while numba compiles in it.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from cfsr._jit import activity

__all__ = [
    "COMPILE_BEAT_S",
    "STOP_SIGNALS",
    "ignore_stop_signals",
    "release_queue",
    "spawn_without_main",
    "start_compile_beat",
    "stop_signals_blocked",
]


#: seconds between two reports of a compile in progress (the pool process's heartbeat)
COMPILE_BEAT_S = 1.0


def start_compile_beat(send: Any, every: float = COMPILE_BEAT_S) -> threading.Thread:
    """In a process that may compile kernels: a daemon thread that calls ``send(activity)``
    (a :class:`cfsr._jit.CompileActivity`) every ``every`` seconds while numba compiles one of
    cfsr's kernels here or waits for another process's compile of one, and once when that
    ends. The compile holds the process's main thread for as long as it takes (minutes on a
    busy machine); this beat is how its owner tells it from a hung one."""
    def beat() -> None:
        was_busy = False
        while True:
            act = activity()
            if act.busy or was_busy:
                try:
                    send(act)
                except (OSError, ValueError):  # the owner is gone
                    return
            was_busy = act.busy
            time.sleep(every)

    th = threading.Thread(target=beat, name="cfsr-compile-beat", daemon=True)
    th.start()
    return th


#: the signals that end a process group (Ctrl+C, a closed terminal, Ctrl+\, kill): a
#: child process leaves them to its owner, which stops it cleanly
STOP_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGHUP", "SIGQUIT", "SIGTERM") if hasattr(signal, n)
)


@contextmanager
def stop_signals_blocked() -> Iterator[None]:
    """Block :data:`STOP_SIGNALS` in this thread while child processes start: the mask is
    inherited across the spawn, so a child importing its modules cannot be ended half-way
    (with semaphores and shared memory left behind) before it calls
    :func:`ignore_stop_signals`."""
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - not POSIX
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def ignore_stop_signals() -> None:
    """In a child process: ignore :data:`STOP_SIGNALS` (its owner stops it), then unblock
    them (:func:`stop_signals_blocked`; one that came meanwhile is dropped)."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


def release_queue(q: Any, timeout: float = 1.0) -> None:
    """Close a multiprocessing queue this process created, so that its semaphores are
    released by this thread, not by the queue's feeder thread.

    The feeder thread (started by the first ``put``) holds the queue's write lock and
    semaphore until it ends; when it ends after the owner dropped the queue, it is the
    feeder that runs the semaphores' release (unlink, then tell the resource tracker). A
    process leaving right then kills the daemon feeder between the two, and the tracker
    reports "1 leaked semaphore" for a name that is already gone. So the feeder is given
    ``timeout`` seconds to flush and end (microseconds normally; a pipe that nobody drains
    would keep it for ever, hence the bound and no wait at exit)."""
    q.close()
    q.cancel_join_thread()
    feeder = getattr(q, "_thread", None)  # CPython's QueueFeederThread; None before a put
    if feeder is not None:
        feeder.join(timeout)


_spawn_lock = threading.Lock()


@contextmanager
def spawn_without_main() -> Iterator[None]:
    """Start processes that do not re-run the caller's ``__main__``.

    A spawned process normally imports the parent's main module first (``spawn`` re-runs a
    script as ``__mp_main__``), which crashes a script with no ``if __name__ ==
    "__main__":`` guard (its pool start runs again, inside the bootstrapping child) and one
    read from stdin (the child looks for a file named ``<stdin>``). A pool process needs
    nothing of the caller's main module: its target and every task are cfsr's own objects,
    pickled by reference. So the preparation data the child receives leaves the main module
    out, whatever the caller is: a script with or without a guard, stdin, the REPL, a
    notebook."""
    import multiprocessing.spawn as mp_spawn

    with _spawn_lock:
        original = mp_spawn.get_preparation_data

        def without_main(name: str) -> dict[str, Any]:
            d = original(name)
            d.pop("init_main_from_path", None)
            d.pop("init_main_from_name", None)
            return d

        mp_spawn.get_preparation_data = without_main
        try:
            yield
        finally:
            mp_spawn.get_preparation_data = original
