"""The worker's supervisor, in the web process: :class:`WorkerSupervisor` starts the worker
process (:mod:`cfsr_live.service.worker_loop`), forwards configuration changes, and restarts
it after a crash (reported, with backoff) without taking the service down. The worker answers
every config version: applied, or rejected with the reason while the previous configuration
keeps running (:meth:`WorkerSupervisor.wait_config`).

It talks to the worker only through the messages of :mod:`cfsr_live.service.worker_messages`
and the shared counters of the latest-frame slot, so the web process never imports the
reconstruction's pool or kernels.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import queue
import threading
import time
from collections import OrderedDict, deque
from dataclasses import replace
from typing import Any, Literal

from cfsr.layout import Layout
from cfsr.procs import release_queue, stop_signals_blocked
from cfsr_live.service.config import WorkerConfig
from cfsr_live.service.frameslot import FrameSlot
from cfsr_live.service.schema import DEFECT_STATES, QUALITY_TIERS, WorkerCounters
from cfsr_live.service.status import (
    CompileProgress,
    DefectMapStatus,
    QualityShare,
    RateMeter,
    WorkerReport,
    WorkerStatus,
    real_time_factor,
)
from cfsr_live.service.worker_messages import (
    RUNG_NAMES,
    Attach,
    Compiling,
    ConfigAck,
    ConfigAnswer,
    Configure,
    DefectMapFound,
    HoldStep,
    Inject,
    Ready,
    Stop,
    Viewers,
    WorkerError,
)

__all__ = ["WorkerSupervisor"]

log = logging.getLogger("cfsr.worker")

#: seconds of frames the quality shares in the status count (since the last config change)
SHARE_WINDOW_S = 10.0

def _worker_entry(*args: Any) -> None:
    """The worker process's entry point (runs in the spawned child): the one import of the
    worker's module, at the process boundary, so the web process, which only supervises,
    never loads the reconstruction (pool, kernels)."""
    # deferred: the worker's modules load in the spawned worker only, never in the web process
    from cfsr_live.service.worker_loop import worker_main

    worker_main(*args)


class WorkerSupervisor:
    """Run the worker (:func:`~cfsr_live.service.worker_loop.worker_main`) in a child process;
    restart it when it dies.

    Parameters
    ----------
    slot : FrameSlot
        The latest-frame slot (created by the web process).
    config : WorkerConfig
        The first configuration (its ``version`` starts the count); changed with
        :meth:`configure`.
    hang_timeout : float
        Seconds without a heartbeat after which the worker is considered hung and restarted.
        A compile in the worker itself does not count: its compile heartbeat keeps the
        heartbeat fresh meanwhile (:func:`cfsr.procs.start_compile_beat`).
    """

    def __init__(
        self,
        slot: FrameSlot,
        config: WorkerConfig,
        *,
        hang_timeout: float = 120.0,
        workers: int = 1,
        threads: int = 1,
    ) -> None:
        if int(workers) < 1 or int(threads) < 1:
            raise ValueError(f"workers and threads must be >= 1, got {workers} x {threads}")
        self.slot = slot
        #: reconstruction processes, and numba/OpenCV threads in each
        self.workers, self.threads = int(workers), int(threads)
        #: the configuration asked for (the newest sent, or the last confirmed after a
        #: rejection): what a restarted worker starts with
        self.config = config
        self.hang_timeout = hang_timeout
        #: what the first frame under the config waits on, as the worker last reported
        self.compiling: CompileProgress | None = None
        #: the defect map the worker corrects with, as it last reported it (JSON form of
        #: cfsr.defects.DefectMap), kept in a live recording's sidecar; None: none yet
        self.defect_map: dict[str, Any] | None = None
        self._ctx = mp.get_context("spawn")
        self._proc: mp.process.BaseProcess | None = None
        self._cmd_q = None
        self._evt_q = None
        self._ring_path: str | None = None
        self._layout: Layout | None = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.restarts = 0
        self.crashes: deque[dict[str, Any]] = deque(maxlen=20)
        self.errors: deque[dict[str, Any]] = deque(maxlen=20)
        self.ready = threading.Event()
        self.applied_version = -1
        # config versions: issued here, answered by the worker (ConfigAnswer)
        self._version = config.version
        self._applied_config = config  # the last version the worker confirmed
        self._sent: dict[int, WorkerConfig] = {}  # versions sent, not answered yet
        self._answers: OrderedDict[int, ConfigAck] = OrderedDict()
        self._started_at = 0.0
        self._last_message: str | None = None
        self._counter_base: dict[str, int] = {}
        self._ingest = RateMeter()  # steps ingested per second, sampled by :meth:`sample`
        self._viewers: int | None = None  # clients watching, as last told (None: not told)
        self._hold: int | None = None  # the step the worker computes at instead of the newest
        #: (time, config version, frames shown full, fast) sampled by :meth:`sample`
        self._shares: deque[tuple[float, int, int, int]] = deque()

    # -- lifecycle --------------------------------------------------------------------------------
    def start(self, ring_path: str, layout: Layout) -> None:
        """Spawn the worker on the ring at ``ring_path`` and watch it."""
        self._ring_path, self._layout = ring_path, layout
        self._spawn()
        self._thread = threading.Thread(target=self._monitor, name="cfsr-supervisor", daemon=True)
        self._thread.start()

    def _spawn(self) -> None:
        with self._lock:
            self.ready.clear()
            for q in (self._cmd_q, self._evt_q):  # a restart: the dead worker's queues
                if q is not None:
                    release_queue(q)
            self._cmd_q = self._ctx.Queue()
            self._evt_q = self._ctx.Queue()
            self._proc = self._ctx.Process(
                target=_worker_entry,
                args=(
                    self._ring_path,
                    str(self.slot.path),
                    self._layout,
                    self.config,
                    self._cmd_q,
                    self._evt_q,
                    self.workers,
                    self.threads,
                ),
                name="cfsr-worker",
                daemon=True,
            )
            with stop_signals_blocked():  # until the worker ignores them (worker_main)
                self._proc.start()
            if self._viewers is not None:  # a restarted worker knows who watches
                self._cmd_q.put(Viewers(self._viewers))
            if self._hold is not None:
                self._cmd_q.put(HoldStep(self._hold))
            self._started_at = time.monotonic()
            self._last_message = None

    def stop(self, timeout: float = 10.0) -> None:
        """Ask the worker to stop; kill it after ``timeout`` seconds.

        The worker closes its pool within about 2 s (``FramePool.close``) and then releases
        its queues' semaphores at exit; the kill is for a worker that hangs, as one killed
        during that release leaves a semaphore reported leaked. (SIGTERM is ignored there.)"""
        self._stop.set()
        with self._lock:
            proc = self._proc
            if proc is not None and proc.is_alive():
                try:
                    self._cmd_q.put(Stop())
                except (OSError, ValueError):
                    pass
                proc.join(timeout)
                if proc.is_alive():
                    proc.kill()
                    proc.join(2)
        if self._thread is not None:
            self._thread.join(2)
        for q in (self._cmd_q, self._evt_q):
            if q is not None:
                release_queue(q)

    # -- control ----------------------------------------------------------------------------------
    def configure(self, config: WorkerConfig) -> int:
        """Send ``config`` to the worker under a new version, returned (see
        :meth:`wait_config`; the version ``config`` carries is replaced).

        ``self.config`` is the configuration asked for; when the worker rejects the newest
        version, it goes back to the last one the worker confirmed (so a restarted worker
        starts with a configuration that works).
        """
        with self._lock:
            self._version += 1
            v = self._version
            self.config = replace(config, version=v)
            self._sent[v] = self.config
            self._send(Configure(self.config))
            return v

    def wait_config(self, version: int, timeout: float) -> ConfigAck:
        """The worker's answer to config ``version``, waiting at most ``timeout`` seconds.

        Returns ``ConfigAck("applied")``, ``ConfigAck("rejected", reason)`` or
        ``ConfigAck("pending")`` when
        no answer came in time (the worker is busy, e.g. compiling a method's kernels on
        first use; it answers later, see ``applied_version`` and ``last_errors``).
        """
        end = time.monotonic() + timeout
        while True:
            self._drain()  # not only the monitor's 0.1 s tick: answer as soon as we can
            with self._lock:
                if version in self._answers:
                    return self._answers[version]
            if time.monotonic() >= end:
                return ConfigAck("pending")
            time.sleep(0.005)

    def _answer(
        self, version: int, state: Literal["applied", "rejected"], reason: str | None = None
    ) -> None:
        """Record the worker's answer to ``version`` (called with ``self._lock`` held)."""
        self._answers[version] = ConfigAck(state, reason)
        while len(self._answers) > 256:
            self._answers.popitem(last=False)
        cfg = self._sent.pop(version, None)
        if state == "applied":
            if cfg is not None:
                self._applied_config = cfg
            for v in [v for v in self._sent if v < version]:  # answered before, in order
                self._sent.pop(v)
            return
        self.errors.append({"time": time.time(), "message": f"config {version} {reason}"})
        log.warning("worker config %d not applied: %s", version, reason)
        if version == self.config.version:
            # nothing newer was asked for: fall back to what the worker runs
            self.config = self._applied_config

    def attach(self, ring_path: str, layout: Layout) -> None:
        """Make the worker read a new ring (the source changed geometry or block size)."""
        with self._lock:
            self._ring_path, self._layout = ring_path, layout
            self.defect_map = None  # another source's sensor: the worker learns it afresh
            self._send(Attach(ring_path, layout))

    def set_viewers(self, count: int) -> None:
        """``count`` clients watch the frames: with none the worker computes one frame a
        second, and resumes ``max_fps`` as soon as one connects."""
        with self._lock:
            if count != self._viewers:
                self._viewers = count
                self._send(Viewers(count))

    def hold_step(self, step: int | None) -> None:
        """Make the worker compute at ``step`` instead of the newest one while its buffer
        holds that step (None: the newest again); see :class:`HoldStep`."""
        with self._lock:
            self._hold = step
            self._send(HoldStep(step))

    def inject(self, fault: Literal["crash", "raise", "slow_first"], **kw: Any) -> None:
        """Test hooks: ``crash`` (hard exit, ``code=``), ``raise`` (uncaught Python
        exception, ``message=``) or ``slow_first`` (the next first frame under a config
        takes ``seconds=`` longer)."""
        self._send(Inject(fault, **kw))

    def _send(self, cmd: Configure | Attach | Inject | Stop) -> None:
        if self._cmd_q is not None:
            self._cmd_q.put(cmd)

    @property
    def pid(self) -> int | None:
        p = self._proc
        return p.pid if p is not None and p.is_alive() else None

    @property
    def alive(self) -> bool:
        p = self._proc
        return p is not None and p.is_alive()

    # -- monitor thread ---------------------------------------------------------------------------
    def _drain(self) -> None:
        # Under the lock: the monitor thread and :meth:`wait_config` both drain, and events
        # must be handled one at a time, in order.
        with self._lock:
            self._drain_locked()

    def _drain_locked(self) -> None:
        q = self._evt_q
        while q is not None:
            try:
                ev = q.get_nowait()
            except (queue.Empty, OSError, ValueError, EOFError):
                return
            if isinstance(ev, Ready):
                self.ready.set()
            elif isinstance(ev, ConfigAnswer) and ev.applied:
                self.applied_version = ev.version
                self._answer(ev.version, "applied")
            elif isinstance(ev, ConfigAnswer):
                reason = (ev.reason or "")[:4000]
                self._answer(ev.version, "rejected", f"rejected by the worker: {reason}")
            elif isinstance(ev, WorkerError) and ev.fatal:
                self._last_message = ev.message[:4000]  # reported with the crash
            elif isinstance(ev, WorkerError):
                self.errors.append({"time": time.time(), "message": ev.message[:4000]})
                log.warning("worker error: %s", ev.message.splitlines()[0])
            elif isinstance(ev, Compiling):
                self.compiling = ev.progress
            elif isinstance(ev, DefectMapFound):
                self.defect_map = ev.map

    def _monitor(self) -> None:
        backoff = 0.5
        while not self._stop.wait(0.1):
            self._drain()
            self._sample_tiers()
            with self._lock:
                proc = self._proc
                if proc is None:
                    continue
                alive = proc.is_alive()
                st = self.slot.stats()
                hb = st.heartbeat
                hung = (
                    alive
                    and self.ready.is_set()
                    and hb > 0
                    and time.monotonic() - hb > self.hang_timeout
                )
                if alive and not hung:
                    if time.monotonic() - self._started_at > 30:
                        backoff = 0.5
                    continue
                if self._stop.is_set():
                    return
                if hung:
                    proc.kill()
                    proc.join(2)
                self._drain()
                for v in sorted(self._sent):
                    # never replay into a fresh worker a config the old one did not confirm:
                    # it may be what killed it
                    self._answer(v, "rejected", "not applied: the worker exited first")
                self._carry_counters()
                crash = {
                    "time": time.time(),
                    "exitcode": proc.exitcode,
                    "reason": "hung (no heartbeat)" if hung else "exited",
                    "message": self._last_message,
                }
                self.crashes.append(crash)
                log.error("worker died (%s, exit code %s); restarting", crash["reason"],
                          proc.exitcode)
            if self._stop.wait(backoff):
                return
            backoff = min(5.0, backoff * 2)
            with self._lock:
                self.restarts += 1
                self._spawn()

    #: counters that add up over the worker's restarts (a new worker starts from zero)
    CUMULATIVE = ("frames_out", "steps_ingested", "worker_skip_frames", "ring_lost_frames",
                  "ring_overruns", "ring_torn", "gaps", "errors", "shown_full", "shown_fast",
                  "dropped_late", "dropped_order", "fallback_frames")

    def _carry_counters(self) -> None:
        """Keep cumulative counters across restarts (the new worker starts from zero)."""
        st = self.slot.stats()
        for k in self.CUMULATIVE:
            self._counter_base[k] = self._counter_base.get(k, 0) + getattr(st, k)
        self.slot.counters()[:] = 0

    def stats(self) -> WorkerCounters:
        """The worker's counters, the cumulative ones summed over its restarts."""
        st = self.slot.stats()
        return replace(
            st, **{k: getattr(st, k) + base for k, base in self._counter_base.items()})

    def heartbeat_age(self) -> float:
        """Seconds since the worker's last loop (``inf`` before its first)."""
        hb = self.slot.stats().heartbeat
        return (time.monotonic() - hb) if hb else math.inf

    def sample(self) -> None:
        """Take one sample of the steps ingested (for :meth:`status`'s ``steps_per_s``);
        called on a clock by the runtime's sampler, so the rate does not depend on how often
        the status is read."""
        self._ingest.add(self.stats().steps_ingested)

    def _sample_tiers(self) -> None:
        """Take one sample of the frames shown per tier (for the status's quality shares);
        the monitor thread's tick."""
        st = self.stats()
        now = time.monotonic()
        with self._lock:
            if self._shares and self._shares[-1][1] != st.config_version:
                self._shares.clear()  # a change of mode: its shares start again
            self._shares.append((now, st.config_version, st.shown_full, st.shown_fast))
            while now - self._shares[0][0] > SHARE_WINDOW_S:
                self._shares.popleft()

    def _recent_tiers(self, st: WorkerCounters) -> tuple[int, int]:
        """Frames shown at each tier (full, fast) in the last :data:`SHARE_WINDOW_S` seconds
        under the running config (none before its first sample)."""
        with self._lock:
            if not self._shares or self._shares[0][1] != st.config_version:
                return 0, 0
            _, _, full, fast = self._shares[0]
        return max(0, st.shown_full - full), max(0, st.shown_fast - fast)

    def _quality(self, st: WorkerCounters) -> QualityShare:
        """CFSR's tier mode and the frames shown at each tier lately (:meth:`_recent_tiers`)."""
        full, fast = self._recent_tiers(st)
        mode = self.config.quality if "quality" in self.config.method.params else None
        shown = QUALITY_TIERS[st.shown_tier] if 0 < st.shown_tier < len(QUALITY_TIERS) else None
        return QualityShare(mode=mode, shown=shown if mode else None, full=full, fast=fast)

    def status(self, rate_hz: float) -> WorkerReport:
        """The supervisor's report: the worker's state (``worker`` in ``GET /api/status``)
        and the figures it measures; ``rate_hz`` is the sensor rate the ingest rate is a
        fraction of."""
        st = self.stats()
        age = self.heartbeat_age()
        first = st.first_frame_since
        steps_per_s = self._ingest.rate()
        return WorkerReport(
            status=WorkerStatus(
                alive=self.alive,
                ready=self.ready.is_set(),
                pid=self.pid,
                restarts=self.restarts,
                crashes=list(self.crashes),
                last_errors=list(self.errors)[-3:],
                config_version=self.config.version,
                applied_version=self.applied_version,
                heartbeat_age_s=None if math.isinf(age) else age,
                first_frame_s=(time.monotonic() - first) if first else None,
                steps_per_s=steps_per_s,
                real_time_factor=real_time_factor(steps_per_s, rate_hz),
                frames_out=st.frames_out,
                gaps=st.gaps,
                dropped_late=st.dropped_late,
                dropped_order=st.dropped_order,
                fallback_frames=st.fallback_frames,
                workers=self.workers,
                threads_per_worker=self.threads,
                quality=self._quality(st),
                reconstruction_nice=st.pool_nice,
                defects=DefectMapStatus(
                    state=DEFECT_STATES[st.defects_state]
                    if 0 <= st.defects_state < len(DEFECT_STATES) else "off",
                    hot=st.defects_hot, dead=st.defects_dead,
                    confidence=st.defects_confidence, gain=bool(st.defects_gain)),
                fallback_method=RUNG_NAMES.get(int(st.fallback)) if first else None,
                compiling=self.compiling if first else None,
            ),
            latency_ms=st.latency_ms,
            compute_ms=st.compute_ms,
            ring_lost_frames=st.ring_lost_frames,
            skipped_frames=st.worker_skip_frames,
        )
