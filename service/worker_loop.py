"""The worker process: :func:`worker_main`, spawned by
:class:`~cfsr_live.service.supervisor.WorkerSupervisor`, runs the loop over commands, ring
blocks and frames of a :class:`~cfsr_live.service.frame_worker.FrameWorker`.

The worker applies each configuration all or nothing and answers every version: applied, or
rejected with the reason while the previous configuration keeps running. Only this process
imports the reconstruction (numba kernels, the pool); the web process imports the messages
(:mod:`cfsr_live.service.worker_messages`) and the supervisor.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue
import time
from typing import Any

from cfsr._heap import keep_freed_memory
from cfsr.layout import Layout
from cfsr.pool import PoolError, TaskError
from cfsr.procs import ignore_stop_signals, start_compile_beat
from cfsr_live.service.config import WorkerConfig
from cfsr_live.service.frame_worker import FrameWorker
from cfsr_live.service.worker_messages import (
    Attach,
    Configure,
    HoldStep,
    Inject,
    Ready,
    Stop,
    Viewers,
    WorkerError,
)

__all__ = ["worker_main"]

log = logging.getLogger("cfsr.worker")


def worker_main(
    ring_path: str,
    slot_path: str,
    layout: Layout,
    config: WorkerConfig,
    cmd_q: Any,
    evt_q: Any,
    workers: int = 1,
    threads: int = 1,
) -> None:
    """Entry point of the worker process (spawned by :class:`WorkerSupervisor`): the loop
    over ring blocks, commands and frames, and ``workers`` pool processes of ``threads``
    threads that reconstruct."""
    # Ctrl+C, a closed terminal, Ctrl+\ and a kill of the process group reach us too: the
    # supervisor stops us (and our pool, releasing its semaphores and regions), not the
    # signal; it kills us (SIGKILL) when a stop does not end us.
    ignore_stop_signals()
    keep_freed_memory()  # frames reuse the last frame's large arrays (no page faults)

    # We are a daemon of the web process (ended with it), and multiprocessing forbids a
    # daemon children of its own; our pool's processes are daemons of ours and also leave by
    # themselves within a second of our end (cfsr.pool checks its parent), so nothing lingers.
    mp.current_process()._config["daemon"] = False  # type: ignore[attr-defined]

    # at exit, do not wait to hand over events nobody may read any more (a supervisor that
    # died leaves the queue's pipe full, and the exit would block on it for ever)
    evt_q.cancel_join_thread()
    w: FrameWorker | None = None
    try:
        w = FrameWorker(slot_path, config, evt_q, workers, threads)
        # a kernel this process compiles itself (the fallback's TFP, a first CSR rung) holds
        # the loop; the beat keeps the heartbeat fresh meanwhile, so the supervisor never
        # takes a compile for a hang
        beat_w = w
        start_compile_beat(lambda act: beat_w.put("heartbeat", time.monotonic()))
        w.attach(ring_path, layout)
        evt_q.put(Ready(os.getpid()))
        consecutive_errors = 0
        parent = os.getppid()
        loops = 0
        while True:
            w.put("heartbeat", time.monotonic())
            loops += 1
            if loops % 200 == 0 and os.getppid() != parent:
                return  # the service died without stopping us (SIGKILL): do not linger
            try:
                while True:
                    cmd = cmd_q.get_nowait()
                    if isinstance(cmd, Stop):
                        return
                    if isinstance(cmd, Configure):
                        w.configure(cmd.config)
                    elif isinstance(cmd, HoldStep):
                        w.hold_at(cmd.step)
                    elif isinstance(cmd, Viewers):
                        w.watch(cmd.count)
                    elif isinstance(cmd, Attach):
                        w.attach(cmd.ring_path, cmd.layout)
                    elif isinstance(cmd, Inject) and cmd.fault == "slow_first":
                        w.slow_first = cmd.seconds
                    elif isinstance(cmd, Inject) and cmd.fault == "crash":
                        os._exit(cmd.code)  # test hook: die like a segfault would
                    elif isinstance(cmd, Inject):  # test hook: an uncaught Python error
                        raise RuntimeError(cmd.message)
                    else:
                        log.error("unknown worker command %r ignored", cmd)
            except queue.Empty:
                pass
            try:
                pushed = w.ingest()
                produced = w.maybe_output()
                consecutive_errors = 0
            except PoolError as exc:
                if not isinstance(exc, TaskError):
                    raise  # a pool process died: the supervisor restarts us, pool and all
                consecutive_errors += 1
                w.bump("errors")
                evt_q.put(WorkerError(str(exc)))
                time.sleep(min(1.0, 0.05 * consecutive_errors))
                continue
            except Exception as exc:  # noqa: BLE001 - a method failure must not kill the worker
                consecutive_errors += 1
                w.bump("errors")
                evt_q.put(WorkerError.of(exc))
                time.sleep(min(1.0, 0.05 * consecutive_errors))
                continue
            if not pushed and not produced:
                time.sleep(0.001)
    except BaseException as exc:  # noqa: BLE001 - report before dying
        try:
            evt_q.put(WorkerError.of(exc, fatal=True))
            time.sleep(0.1)
        finally:
            raise
    finally:
        if w is not None:
            w.close()
