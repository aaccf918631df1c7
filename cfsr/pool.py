"""Several reconstructions at once: a pool of processes, each on its own output steps.

One CFSR frame keeps both cores of a small machine only partly busy (the second numba thread
adds 1.47x, not 2x: much of a frame is serial Python, OpenCV's MOG and short parallel
kernels), so frames run faster side by side than one after the other on all threads. A
:class:`FramePool` holds ``workers`` processes of ``threads`` numba/OpenCV threads each; the
caller hands it a window of packed frames and the steps to reconstruct in it (a *task*), and
gets the :class:`~cfsr.methods.registry.Output` back, in the order it asks for them.

Both users of the pool go through it, so both get the same numbers as one process:

* the live worker (``cfsr_live.service.worker``) copies the window of its newest step out of its
  streaming buffer into a free process's region and publishes the results in step order;
* :func:`pool_outputs` (behind :func:`cfsr.reconstruct` and ``cfsr reconstruct``) cuts a
  recording's output steps into groups and runs each group in one process.

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
import signal
import tempfile
import threading
import time
import traceback
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cfsr.config import MethodConfig
from cfsr.layout import Layout
from cfsr.methods.registry import Output

if TYPE_CHECKING:
    from cfsr._jit import CompileActivity

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
    "pool_outputs",
    "shared_pool",
    "start_compile_beat",
    "close_shared_pool",
]

log = logging.getLogger("cfsr.pool")

#: how long a process waits for a task before it checks that its parent still lives (s)
_PARENT_CHECK_S = 1.0


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


@dataclass(frozen=True)
class PoolResult:
    """The answer to one task: its ``tag``, the ``(t, Output)`` of each step asked for, in
    order, and the wall time each took in the process (ms, per step)."""

    tag: Any
    outputs: list[tuple[int, Output]]
    compute_ms: list[float]
    worker: int


@dataclass(frozen=True)
class CompileBeat:
    """A pool process's report of a kernel compile in progress, sent every
    :data:`COMPILE_BEAT_S` while it lasts and once when it ends.

    ``kernel``: the kernel compiled, or waited for while another process compiles it
    (``waiting``); None once the compile ended. ``kernels``: kernels compiled or loaded from
    the cache since the process's current task began; ``cpu_s``: CPU seconds the process
    spent since then."""

    kernel: str | None
    waiting: bool
    kernels: int
    cpu_s: float

    @property
    def busy(self) -> bool:
        return self.kernel is not None


@dataclass(frozen=True)
class _Task:
    tag: Any
    config: MethodConfig
    layout: Layout
    start: int  # absolute step of the region's first frame
    n_frames: int  # frames in the region
    spans: tuple[tuple[int, int, int], ...]  # (a, b, t) per output, absolute steps
    carry: bool  # one memo for the task's outputs (carried work), else a fresh one each
    delay: float = 0.0  # test hook: seconds to wait first (as a compile does)


class _RegionView:
    """What :meth:`Method.run_window` reads: ``packed``/``frames``/``layout`` over the region."""

    def __init__(self, frames: np.ndarray, start: int, layout: Layout) -> None:
        self._frames, self._start, self.layout = frames, start, layout

    def packed(self, a: int, b: int) -> np.ndarray:
        return self._frames[a - self._start : b - self._start]

    def frames(self, a: int, b: int) -> np.ndarray:
        from cfsr._bits import unpack_layout

        return unpack_layout(self.packed(a, b), self.layout)


def _limit_threads(threads: int) -> None:
    """Run this process's numba kernels and OpenCV on ``threads`` threads."""
    import numba

    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    try:
        import cv2

        cv2.setNumThreads(int(threads))
    except ImportError:  # pragma: no cover - OpenCV is a base dependency
        pass


def _pool_main(
    index: int, path: str, size: int, threads: int, task_q: Any, result_q: Any, parent: int,
    nice: int = 0,
) -> None:
    """Entry point of a pool process: map the region, answer tasks until told to stop."""
    from cfsr._heap import keep_freed_memory
    from cfsr._jit import activity, waiting_for

    # Ctrl+C, a closed terminal, Ctrl+\ and a kill of the process group reach us too: the
    # pool's owner stops us (and releases what we share) rather than the signal half-way
    ignore_stop_signals()
    keep_freed_memory()
    _limit_threads(threads)
    if nice:
        os.nice(nice)
    # at exit, do not wait to hand over results nobody may read any more (an owner that died
    # leaves the queue's pipe full, and the exit would block on it for ever)
    result_q.cancel_join_thread()
    fd = os.open(path, os.O_RDWR)
    try:
        region = mmap.mmap(fd, size)
    finally:
        os.close(fd)
    result_q.put(("ready", index, os.getpid()))
    base = [0, 0.0]  # kernels compiled or loaded, and CPU seconds, when the task began

    def report(act: CompileActivity) -> None:
        beat = CompileBeat(act.kernel, act.waiting, act.compiled + act.loaded - base[0],
                           time.process_time() - base[1])
        result_q.put(("compiling", index, beat))

    start_compile_beat(report)
    buf = np.frombuffer(region, np.uint8)
    while True:
        try:
            task = task_q.get(timeout=_PARENT_CHECK_S)
        except queue.Empty:
            if os.getppid() != parent:
                return  # the owner died without stopping us: do not linger
            continue
        if task is None:
            return
        act = activity()
        base[:] = [act.compiled + act.loaded, time.process_time()]
        try:
            if task.delay:  # test hook: a first frame held as by another process's compile
                with waiting_for("(injected delay)"):
                    time.sleep(task.delay)
            m = task.config.spec
            fb = task.layout.frame_bytes
            frames = buf[: task.n_frames * fb].reshape(task.n_frames, fb)
            view = _RegionView(frames, task.start, task.layout)
            memo: dict[str, Any] = {}
            outs, ms = [], []
            for a, b, t in task.spans:
                t0 = time.perf_counter()
                if not task.carry:
                    memo = {}
                outs.append((t, m.run_window(view, a, b, t, task.config.params, memo)))
                ms.append((time.perf_counter() - t0) * 1e3)
            result_q.put(("done", index, PoolResult(task.tag, outs, ms, index)))
        except Exception as exc:  # noqa: BLE001 - reported to the owner, which decides
            msg = f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"
            result_q.put(("error", index, (task.tag, msg)))


#: seconds between two reports of a compile in progress (the pool process's heartbeat)
COMPILE_BEAT_S = 1.0


def start_compile_beat(send: Any, every: float = COMPILE_BEAT_S) -> threading.Thread:
    """In a process that may compile kernels: a daemon thread that calls ``send(activity)``
    (a :class:`cfsr._jit.CompileActivity`) every ``every`` seconds while numba compiles one of
    cfsr's kernels here or waits for another process's compile of one, and once when that
    ends. The compile holds the process's main thread for as long as it takes (minutes on a
    busy machine); this beat is how its owner tells it from a hung one."""
    from cfsr._jit import activity

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
def _spawn_without_main() -> Iterator[None]:
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
                with stop_signals_blocked(), _spawn_without_main():
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
    for another shape restarts it. Not thread-safe: :func:`pool_outputs` uses it under a
    lock (another thread meanwhile gets a pool of its own)."""
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




# ----------------------------------------------------------------------------------------------
# offline: a recording's output steps, group by group
# ----------------------------------------------------------------------------------------------
def pool_outputs(
    recording: Any,
    config: MethodConfig,
    groups: Iterable[Sequence[int]],
    *,
    workers: int | None = None,
    threads: int = 1,
    carry: bool = False,
    pool: FramePool | None = None,
) -> Iterator[tuple[int, Output]]:
    """Yield ``(t, Output)`` for every step of ``groups``, in the order given, computed on a
    :class:`FramePool` (one group per task).

    ``recording`` is anything with ``packed(a, b)``, ``n_frames`` and ``layout`` (a
    :class:`~cfsr.spikes.SpikeRecording`). Each output's window is ``[t - before, t + after]``
    clipped to the recording, as in :func:`cfsr.reconstruct`, so the numbers are the same as
    one process's. With ``carry`` the outputs of a group continue one memo (carried work);
    a group's first output always starts from nothing, so the result does not depend on the
    number of processes.
    """
    before, after = config.window
    n = int(recording.n_frames)
    layout = recording.layout
    tasks = []
    for g in groups:
        spans = [(max(0, t - before), min(n, t + after + 1), int(t)) for t in g]
        if spans:
            a0, b0 = min(s[0] for s in spans), max(s[1] for s in spans)
            tasks.append((a0, b0, spans))
    need = max((b - a for a, b, _ in tasks), default=0) * layout.frame_bytes
    own = shared = False
    if pool is None:
        # this process's shared pool, unless another thread is using it right now
        shared = _shared_lock.acquire(blocking=False)
        if shared:
            try:
                pool = shared_pool(workers, threads)
            except BaseException:
                _shared_lock.release()
                raise
        else:
            own = True
            want = max(1, min(default_workers(threads) if workers is None else workers,
                              len(tasks)))
            pool = FramePool(want, threads, region_bytes=max(need, 1 << 20))
    assert pool is not None
    finished = False
    try:
        if need > pool.region_bytes:
            pool.grow(need)
        done: dict[int, PoolResult] = {}
        nxt = 0  # next group to yield
        sub = 0  # next group to submit
        while nxt < len(tasks):
            while sub < len(tasks) and pool.idle:
                a0, b0, spans = tasks[sub]
                pool.submit(sub, config, layout, recording.packed(a0, b0), a0, spans,
                            carry=carry)
                sub += 1
            while nxt not in done:
                r = pool.collect()
                assert r is not None
                done[r.tag] = r
            yield from done.pop(nxt).outputs
            nxt += 1
        finished = True
    finally:
        if own:
            pool.close()
        elif shared:
            if not finished:  # abandoned or failed half-way: tasks may still run there
                _drop_shared()
            _shared_lock.release()
