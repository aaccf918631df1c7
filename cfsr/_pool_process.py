"""What runs in a pool process of :class:`cfsr.pool.FramePool`: the task it is handed, the view of
its shared region a reconstruction reads, and its loop (map the region, answer tasks, report
compiles through the heartbeat, leave when the owner says so or is gone).
"""

from __future__ import annotations

import mmap
import os
import queue
import time
import traceback
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cfsr._bits import unpack_layout
from cfsr._heap import keep_freed_memory
from cfsr._jit import activity, waiting_for
from cfsr.config import MethodConfig
from cfsr.layout import Layout
from cfsr.methods.registry import Output
from cfsr.procs import ignore_stop_signals, start_compile_beat

if TYPE_CHECKING:
    from cfsr._jit import CompileActivity

__all__ = ["CompileBeat", "PoolResult"]

#: how long a process waits for a task before it checks that its parent still lives (s)
_PARENT_CHECK_S = 1.0


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
