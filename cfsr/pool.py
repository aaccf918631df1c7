"""Several reconstructions at once: a pool of processes, each on its own output steps.

One CFSR frame keeps both cores of a small machine only partly busy (the second numba thread
adds 1.47x, not 2x: much of a frame is serial Python, OpenCV's MOG and short parallel
kernels), so frames run faster side by side than one after the other on all threads. A
:class:`FramePool` holds ``workers`` processes of ``threads`` numba/OpenCV threads each; the
caller hands it a window of packed frames and the steps to reconstruct in it (a *task*), and
gets the :class:`~cfsr.methods.registry.Output` back, in the order it asks for them.

Both users of the pool go through it, so both get the same numbers as one process:

* the live worker (``cfsr_live.service.frame_worker``) copies the window of its newest step out
  of its streaming buffer into a free process's region and publishes the results in step order;
* :func:`cfsr.offline.pool_outputs` (behind :func:`cfsr.reconstruct` and ``cfsr
  reconstruct``) cuts a recording's output steps into groups and runs each group in one
  process.

A task's output is computed by :meth:`Method.run_window` on exactly the bytes and window
bounds the single-process path uses (a reconstruction is a pure function of its window, its
parameters and its first step), so a frame is the same whichever process computes it; the
tests check that bit for bit.

Transport: each process has its own region of shared memory (a file in ``/dev/shm``, or the
temporary folder where there is none) into which the caller copies the task's packed frames
(12.9 MB for a default CFSR frame of a 400 x 250 sensor, about 2 ms); the file is unlinked as
soon as the process has mapped it, so nothing is left behind whatever way the processes end.
Results (rates and masks, 0.5 MB a frame) come back pickled on one queue.
"""

from __future__ import annotations

import atexit
import logging
import mmap
import multiprocessing as mp
import os
import queue
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np

from cfsr._pool_process import CompileBeat, PoolResult, _pool_main, _Task
from cfsr.config import MethodConfig
from cfsr.layout import Layout
from cfsr.procs import (
    COMPILE_BEAT_S,
    ignore_stop_signals,
    release_queue,
    spawn_without_main,
    start_compile_beat,
    stop_signals_blocked,
)

if TYPE_CHECKING:
    pass

__all__ = [
    "FramePool",
    "PoolError",
    "PoolResult",
    "CompileBeat",
    "TaskError",
    "default_workers",
    "release_queue",
    "ignore_stop_signals",
    "stop_signals_blocked",
    "borrowed_pool",
    "shared_pool",
    "start_compile_beat",
    "close_shared_pool",
]

log = logging.getLogger("cfsr.pool")

class PoolError(RuntimeError):
    """A pool process failed: it died, or did not start."""


class TaskError(PoolError):
    """A task's reconstruction raised in its process (the message carries the traceback);
    the process goes on with the next task. ``tag`` is the task's."""

    def __init__(self, tag: Any, message: str) -> None:
        super().__init__(message)
        self.tag = tag


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the system tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def default_workers(threads: int = 1) -> int:
    """Processes of ``threads`` threads each that the usable cores allow (at least 1)."""
    return max(1, usable_cores() // max(1, int(threads)))


def _shm_folder() -> str:
    return "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()


class FramePool:
    """``workers`` processes of ``threads`` threads, each reconstructing the tasks it is given.

    Parameters
    ----------
    workers : int, optional
        Processes (default :func:`default_workers`: the usable cores / ``threads``).
    threads : int
        numba and OpenCV threads per process.
    region_bytes : int
        Bytes of packed frames one task may carry (the window of its outputs). The region is
        a sparse file: only the bytes a task writes take memory. A larger task restarts the
        pool with a region that fits it.
    wait : bool
        Return once every process has started (True), or at once (False: tasks submitted
        meanwhile wait in their process's queue; a process that fails to start is reported by
        :meth:`collect`, as a dead one is).
    nice : int
        Added to the processes' nice value (0: as the caller). The live service runs its
        reconstruction below acquisition this way; what compiles kernels beside it (the
        background warm-up) must run at the same value, or a compile it holds the lock of
        would crawl while these processes wait for it.

    Use it as a context manager, or call :meth:`close`. Not thread-safe: one owner submits
    and collects.
    """

    def __init__(
        self,
        workers: int | None = None,
        threads: int = 1,
        *,
        region_bytes: int = 64 << 20,
        wait: bool = True,
        nice: int = 0,
    ) -> None:
        self.threads = max(1, int(threads))
        self.workers = default_workers(self.threads) if workers is None else int(workers)
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.region_bytes = int(region_bytes)
        #: the size asked for: a region grown past it for a large task gives the pages beyond
        #: it back after each task (a large window once must not stay resident)
        self.base_bytes = self.region_bytes
        self._ctx = mp.get_context("spawn")
        self._procs: list[Any] = []
        self._task_qs: list[Any] = []
        self._regions: list[np.ndarray] = []
        self._maps: list[mmap.mmap] = []
        self._busy: dict[int, Any] = {}  # worker -> tag of the task it runs
        self._result_q: Any = None
        self._wait = bool(wait)
        self.nice = int(nice)
        #: per process: (when heard, what it reported) of its latest compile heartbeat
        self._compiles: dict[int, tuple[float, CompileBeat]] = {}
        self._start()

    # -- lifecycle ---------------------------------------------------------------------------
    def _start(self) -> None:
        folder = _shm_folder()
        self._result_q = self._ctx.Queue()
        paths: list[str] = []
        self._paths = paths  # unlinked by close() too, should a start fail half-way
        try:
            for k in range(self.workers):
                fd, path = tempfile.mkstemp(prefix=f"cfsr-pool-{os.getpid()}-{k}-", dir=folder)
                try:
                    os.ftruncate(fd, self.region_bytes)
                    mm = mmap.mmap(fd, self.region_bytes)
                finally:
                    os.close(fd)
                paths.append(path)
                self._maps.append(mm)
                self._regions.append(np.frombuffer(mm, np.uint8))
                tq = self._ctx.Queue()
                self._task_qs.append(tq)
                p = self._ctx.Process(
                    target=_pool_main,
                    args=(k, path, self.region_bytes, self.threads, tq, self._result_q,
                          os.getpid(), self.nice),
                    name=f"cfsr-pool-{k}",
                    daemon=True,
                )
                with stop_signals_blocked(), spawn_without_main():
                    p.start()
                self._procs.append(p)
            log.info("cfsr pool: %d process(es) of %d thread(s), started with 'spawn' "
                     "(the caller's __main__ is not re-run in them)", self.workers, self.threads)
            self.pids = [0] * self.workers
            self._unready = set(range(self.workers))
            end = time.monotonic() + 120.0
            while self._wait and self._unready:
                try:
                    kind, k, pid = self._result_q.get(timeout=0.2)
                except queue.Empty:
                    self._check_alive()
                    if time.monotonic() > end:
                        raise PoolError("pool processes did not start within 120 s") from None
                    continue
                self._ready_msg(kind, k, pid)
        except BaseException:
            self.close()
            raise
        finally:
            if self._wait or not getattr(self, "_unready", None):
                self._unlink_regions()

    def _ready_msg(self, kind: str, k: int, pid: Any) -> None:
        if kind == "compiling":
            self._compiles[k] = (time.monotonic(), pid)
        elif kind == "ready":
            self.pids[k] = pid
            self._unready.discard(k)
            if not self._unready:
                self._unlink_regions()  # mapped by every process now

    def _unlink_regions(self) -> None:
        """Remove the regions' names: every process has mapped them (or failed), so nothing
        is left behind however the processes end."""
        for path in getattr(self, "_paths", []):
            try:
                os.unlink(path)
            except OSError:
                pass
        self._paths = []

    def close(self, timeout: float = 2.0) -> None:
        """Stop the processes and release the regions (idempotent).

        A process busy with a frame reads its stop only after the frame (seconds while its
        kernels compile), so those still running ``timeout`` seconds after the stop are
        killed: nothing they would return is wanted, and the whole close stays bounded (the
        owner's own stop must not outlast its supervisor's patience, or the owner is killed
        half-way through releasing its semaphores)."""
        for q in self._task_qs:
            try:
                q.put(None)
            except (OSError, ValueError):
                pass
        end = time.monotonic() + timeout
        for p in self._procs:
            p.join(max(0.0, end - time.monotonic()))
        for p in self._procs:
            if p.is_alive():
                p.kill()  # SIGTERM is ignored there (see _pool_main)
                p.join(2)
        for q in [*self._task_qs, self._result_q]:
            if q is not None:
                release_queue(q)
        self._unlink_regions()
        self._regions.clear()
        for mm in self._maps:
            try:
                mm.close()
            except BufferError:  # a view still alive: the mapping goes with the process
                pass
        self._procs, self._task_qs, self._maps, self._busy = [], [], [], {}
        self._result_q = None

    def __enter__(self) -> FramePool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_alive(self) -> None:
        for k, p in enumerate(self._procs):
            if not p.is_alive():
                raise PoolError(f"pool process {k} (pid {p.pid}) exited with code {p.exitcode}")

    def grow(self, nbytes: int) -> None:
        """Make every region hold ``nbytes`` (restarts the processes: call it with no task
        pending; ValueError otherwise)."""
        if self._busy:
            raise ValueError("the pool's regions can grow only while no task runs")
        if nbytes <= self.region_bytes:
            return
        self.close()
        self.region_bytes = max(int(nbytes), 2 * self.region_bytes)
        self._start()

    def shrink(self) -> None:
        """Give the regions back their :attr:`base_bytes` size after a large task (restarts
        the processes: call it with no task pending; ValueError otherwise)."""
        if self._busy:
            raise ValueError("the pool's regions can shrink only while no task runs")
        if self.region_bytes > self.base_bytes:
            self.close()
            self.region_bytes = self.base_bytes
            self._start()

    def _release(self, k: int) -> None:
        """Give back the pages of process ``k``'s region beyond :attr:`base_bytes` (its task
        is done, so nobody reads them)."""
        extra = self.region_bytes - self.base_bytes
        if extra > 0 and hasattr(mmap, "MADV_REMOVE") and k < len(self._maps):
            try:
                self._maps[k].madvise(mmap.MADV_REMOVE, self.base_bytes, extra)
            except (OSError, ValueError):  # pragma: no cover - a kernel without it
                pass

    # -- compiles ----------------------------------------------------------------------------
    def compiling(self, k: int, stale_s: float = 10 * COMPILE_BEAT_S) -> CompileBeat | None:
        """What process ``k`` reported it compiles (or waits for) now, or None: it reported
        no compile in progress, or its last beat is older than ``stale_s`` (a process stuck
        elsewhere stops beating). Beats are read by :meth:`collect`."""
        got = self._compiles.get(k)
        if got is None or not got[1].busy or time.monotonic() - got[0] > stale_s:
            return None
        return got[1]

    def compile_ended(self, k: int) -> float:
        """When process ``k`` was last heard compiling (``time.monotonic()``; 0 if never): a
        task's time spent compiling is not a hang's."""
        got = self._compiles.get(k)
        return got[0] if got is not None else 0.0

    def compile_report(self) -> dict[int, CompileBeat]:
        """The latest compile report of each process that sent one."""
        return {k: a for k, (_, a) in self._compiles.items()}

    # -- tasks -------------------------------------------------------------------------------
    @property
    def idle(self) -> list[int]:
        """Processes without a task."""
        return [k for k in range(self.workers) if k not in self._busy]

    @property
    def pending(self) -> int:
        """Tasks submitted and not collected."""
        return len(self._busy)

    def submit(
        self,
        tag: Any,
        config: MethodConfig,
        layout: Layout,
        packed: np.ndarray,
        start: int,
        spans: Sequence[tuple[int, int, int]],
        *,
        carry: bool = False,
        delay: float = 0.0,
    ) -> int:
        """Give an idle process the frames ``packed`` (``(n, frame_bytes)`` uint8, the first
        being step ``start``) and the outputs ``spans`` = ``(a, b, t)``: step ``t`` from
        frames ``[a, b)``, all inside the given frames. ``carry``: the outputs share one memo
        (carried work), else each starts from nothing. Returns the process's index; raises
        PoolError when none is idle."""
        idle = self.idle
        if not idle:
            raise PoolError("no idle pool process")
        packed = np.asarray(packed, np.uint8)
        if packed.ndim != 2 or packed.shape[1] != layout.frame_bytes:
            raise ValueError(f"packed frames must be (n, {layout.frame_bytes}), got {packed.shape}")
        n = len(packed)
        for a, b, t in spans:
            if not (start <= a <= t < b <= start + n):
                raise ValueError(f"output {t} from [{a}, {b}) is outside frames "
                                 f"[{start}, {start + n})")
        if packed.nbytes > self.region_bytes:
            self.grow(packed.nbytes)  # ValueError while tasks run
            idle = self.idle
        k = idle[0]
        self._regions[k][: packed.nbytes].reshape(packed.shape)[:] = packed
        self._busy[k] = tag
        self._task_qs[k].put(
            _Task(tag, config, layout, int(start), n, tuple(map(tuple, spans)), bool(carry),
                  float(delay))
        )
        return k

    def collect(self, timeout: float | None = None) -> PoolResult | None:
        """The next finished task (any order), or None after ``timeout`` seconds (None: wait
        as long as it takes). Raises PoolError when a task failed or a process died."""
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = 0.2 if end is None else max(0.0, min(0.2, end - time.monotonic()))
            try:
                kind, k, payload = self._result_q.get(timeout=wait)
            except queue.Empty:
                self._check_alive()
                if end is not None and time.monotonic() >= end:
                    return None
                continue
            if kind in ("ready", "compiling"):
                self._ready_msg(kind, k, payload)
                continue
            if kind == "done":
                self._busy.pop(k, None)
                self._release(k)
                return payload
            if kind == "error":
                self._busy.pop(k, None)
                self._release(k)
                tag, msg = payload
                raise TaskError(tag, f"reconstruction of task {tag!r} failed in pool "
                                f"process {k}: {msg}")


# ----------------------------------------------------------------------------------------------
# one pool per process, reused by every call
# ----------------------------------------------------------------------------------------------
_shared: FramePool | None = None
_shared_lock = threading.Lock()  # held by the call using the shared pool


def shared_pool(workers: int | None = None, threads: int = 1) -> FramePool:
    """This process's pool of ``workers`` processes of ``threads`` threads, started at its
    first use and kept for later calls (closed at exit, or by :func:`close_shared_pool`): a
    second :func:`cfsr.reconstruct` pays no process start and no kernel load. A call asking
    for another shape restarts it. Not thread-safe: use it through :func:`borrowed_pool`."""
    global _shared
    want = default_workers(threads) if workers is None else int(workers)
    if _shared is not None and (
        _shared.workers != want or _shared.threads != max(1, int(threads)) or not _shared._procs
    ):
        _drop_shared()
    if _shared is None:
        _shared = FramePool(want, threads)
        # registered now, after multiprocessing registered its own exit function (when the
        # first process started): exit functions run last-registered first, and
        # multiprocessing's joins every child with no timeout, after a SIGTERM that pool
        # processes ignore (their owner stops them), so it must find them closed already
        atexit.unregister(close_shared_pool)
        atexit.register(close_shared_pool)
    return _shared


def shared_pool_running(threads: int = 1) -> bool:
    """True when this process's shared pool runs with ``threads`` threads per process (a
    call on it pays no start)."""
    return _shared is not None and bool(_shared._procs) and _shared.threads == max(1, threads)


def _drop_shared() -> None:
    global _shared
    if _shared is not None:
        _shared.close()
        _shared = None


def close_shared_pool() -> None:
    """Stop this process's shared pool (a later call starts a new one)."""
    with _shared_lock:
        _drop_shared()


@contextmanager
def borrowed_pool(
    workers: int | None, threads: int, tasks: int, region_bytes: int
) -> Iterator[FramePool]:
    """This process's shared pool (:func:`shared_pool`) for the body, or, while another
    thread uses it, a pool of its own for ``tasks`` tasks, closed after. A body that does not
    finish (an error, a generator left half-way) drops the shared pool: its processes may
    still be computing that body's tasks."""
    if not _shared_lock.acquire(blocking=False):
        want = max(1, min(default_workers(threads) if workers is None else workers, tasks))
        with FramePool(want, threads, region_bytes=max(region_bytes, 1 << 20)) as own:
            yield own
        return
    try:
        pool = shared_pool(workers, threads)
        try:
            yield pool
        except BaseException:
            _drop_shared()
            raise
    finally:
        _shared_lock.release()

