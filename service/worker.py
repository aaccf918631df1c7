"""The reconstruction worker process and its supervisor.

The worker maps the spike ring and the latest-frame slot, feeds ring blocks into the single
:class:`cfsr.StreamingReconstructor`, and publishes the newest reconstruction (8-bit image,
coarse and fine masks, timings) at most ``max_fps`` times a second. It never waits for anyone:
when it falls behind it skips the backlog it does not need (counted as ``worker_skip``), and if
the ring overran it, the ring reader counts those frames (``ring_lost``).

The :class:`WorkerSupervisor` (in the web process) starts it, forwards configuration changes,
and restarts it after a crash (reported, with backoff) without taking the service down. The
worker applies each configuration all or nothing and answers every version: applied, or
rejected with the reason while the previous configuration keeps running
(:meth:`WorkerSupervisor.wait_config`).

Everything that crosses the process boundary is a small frozen dataclass (pickled by the
queues): commands :class:`Configure`, :class:`Attach`, :class:`Inject`, :class:`Stop` to the
worker; events :class:`Ready`, :class:`ConfigAnswer`, :class:`WorkerError` (a failed frame,
or a fatal error) back. A :class:`~cfsr_live.service.config.WorkerConfig` was validated where it was
made (in the web process) and is applied as is.
"""

from __future__ import annotations

import functools
import logging
import math
import multiprocessing as mp
import os
import queue
import threading
import time
import traceback
from collections import OrderedDict, deque
from dataclasses import dataclass, replace
from typing import Any, Literal, NamedTuple

from cfsr.layout import Layout
from cfsr_live.service.config import WorkerConfig
from cfsr_live.service.frameslot import FrameSlot
from cfsr_live.service.kernels import RECONSTRUCTION_NICE
from cfsr_live.service.schema import WorkerCounters
from cfsr_live.service.status import (
    CompileProgress,
    QualityShare,
    RateMeter,
    WorkerReport,
    WorkerStatus,
    real_time_factor,
)

__all__ = [
    "Attach",
    "Compiling",
    "ConfigAck",
    "ConfigAnswer",
    "Configure",
    "Inject",
    "Ready",
    "Stop",
    "WorkerError",
    "WorkerSupervisor",
    "pick_tier",
    "worker_main",
]

log = logging.getLogger("cfsr.worker")


# ----------------------------------------------------------------------------------------------
# messages between the supervisor and the worker (pickled by the multiprocessing queues)
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Configure:
    """Run ``config`` from now on (or reject it and keep the running one)."""

    config: WorkerConfig


@dataclass(frozen=True)
class Attach:
    """Read the ring at ``ring_path`` (a new source made a new ring) of frames ``layout``."""

    ring_path: str
    layout: Layout


@dataclass(frozen=True)
class Inject:
    """Test hook: ``crash`` exits like a segfault (status ``code``); ``raise`` raises;
    ``slow_first`` makes the next first frame under a config take ``seconds`` longer (as a
    first use's compilation does)."""

    fault: Literal["crash", "raise", "slow_first"]
    code: int = 3
    message: str = "injected worker failure"
    seconds: float = 0.0


@dataclass(frozen=True)
class Stop:
    """Leave the loop and exit."""


@dataclass(frozen=True)
class Ready:
    """The worker mapped the ring and the slot and runs its first configuration."""

    pid: int


@dataclass(frozen=True)
class ConfigAnswer:
    """The worker's one answer to config ``version``: applied, or rejected with ``reason``
    (the previous configuration keeps running)."""

    version: int
    applied: bool
    reason: str | None = None


@dataclass(frozen=True)
class WorkerError:
    """An exception in the worker, ``message`` with its traceback: a frame failed and the
    worker goes on, or (``fatal``) it is dying of it (the supervisor restarts it)."""

    message: str
    fatal: bool = False

    @classmethod
    def of(cls, exc: BaseException, *, fatal: bool = False) -> WorkerError:
        """The event for ``exc``, being handled now (its traceback is the current one)."""
        return cls(f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}", fatal)


@dataclass(frozen=True)
class Compiling:
    """What the first frame under the config waits on: ``progress`` (a
    :class:`~cfsr_live.service.status.CompileProgress`), or None once no compile holds it."""

    progress: CompileProgress | None


class ConfigAck(NamedTuple):
    """:meth:`WorkerSupervisor.wait_config`'s answer (a tuple: ``state, reason = ...``)."""

    state: Literal["applied", "rejected", "pending"]
    reason: str | None = None


# ----------------------------------------------------------------------------------------------
# worker process
# ----------------------------------------------------------------------------------------------
class _Task(NamedTuple):
    """A frame handed to the pool: its step, when its newest spike arrived, the tier, the
    config version it was computed under, when and to which process it went, whether it
    is that process's first frame of its method and tier (which may wait on the compiler),
    the step clock its step counts on (:meth:`_Worker._restart_clock`), and whether it is a
    rung of the ladder shown while the config's first frame compiles."""

    step: int
    arrival: float
    quality: str
    version: int
    submitted: float
    process: int
    method: str
    cold: bool
    clock: int
    rung: bool = False  # a stand-in of the ladder (CSR while CFSR compiles), not the config's


#: the rung of the ladder shown while a method's first frame waits on its compile, computed
#: by an idle pool process (TFP, the first rung, is computed by the worker itself)
LADDER = {"cfsr": "csr"}
#: most stand-in frames a second (TFP, CSR) while a first frame compiles: enough to see the
#: scene move, and the CPU goes to the compile the user waits for
STAND_IN_FPS = 5.0
#: the ``fallback`` counter's values: which rung stands in
RUNG_CODES = {"tfp": 1, "csr": 2}
_RUNG_NAMES = {v: k for k, v in RUNG_CODES.items()}


#: a frame whose newest spike arrived longer ago than this is not shown (counted late) when a
#: newer frame of its config is computing
LATE_S = 1.0
#: seconds the first frame under a config may be pending before the worker shows frames of a
#: ready method (TFP) meanwhile: on a first use that frame waits on numba's compiler
FALLBACK_AFTER_S = 1.0
#: a pool task pending longer than this, not counting the time its process spent compiling
#: kernels (or waiting for another process's compile of them), is taken for a hang
TASK_HANG_S = 120.0


class _Worker:
    """The worker process's state: the ring reader, the streaming buffer, and the pool of
    processes that reconstruct (:class:`cfsr.pool.FramePool`).

    The loop ingests ring blocks into the buffer, hands the newest computable step to an idle
    pool process whenever ``max_fps`` allows, and publishes finished frames in step order:
    a result older than one already shown is dropped (``dropped_order``), one whose spikes
    arrived more than :data:`LATE_S` ago while a newer frame of its config computes, or
    computed under a replaced config, too (``dropped_late``). With ``workers`` processes
    several frames are computed at once, each on a different step, so the rate is up to
    ``workers`` times one process's.

    CFSR's ``quality = auto`` (the live default) picks a tier per frame: ``full`` while the
    measured cost of a full frame lets the pool keep ``max_fps``, else as many ``full``
    frames as the rate allows and ``fast`` ones between them.
    """

    def __init__(
        self, slot_path: str, config: WorkerConfig, evt_q: Any, workers: int = 1,
        threads: int = 1,
    ) -> None:
        from cfsr.pool import FramePool

        self.slot = FrameSlot.attach(slot_path)
        self.evt_q = evt_q
        self.config = config
        self.ring = None
        self.reader = None
        self.rec = None
        self.layout = None
        counters = self.slot.counters()
        counters[:] = 0
        # the record in shared memory (indexing a structured array gives a view): a counter
        # is a field of the schema, so a misspelt name raises instead of reading 0
        self.st = counters[0]
        self.st["pid"] = os.getpid()
        self.st["started"] = time.monotonic()
        self._lost_base = self._overrun_base = self._torn_base = self._gaps_base = 0
        self._skip_base = 0
        self._next_out = 0.0
        #: (end step, host time) of the blocks ingested, on the current step clock
        self._arrival: deque[tuple[int, float]] = deque(maxlen=4096)
        self._clock = 0  # how many times the step clock started again
        self.slow_first = 0.0  # test hook (Inject "slow_first")
        # not waiting for the processes to start: the heartbeat and the first frames of the
        # loop do not wait on their imports
        self.pool = FramePool(workers, threads, wait=False, nice=RECONSTRUCTION_NICE)
        self.put("workers", self.pool.workers)
        self.put("threads", self.pool.threads)
        self._tasks: dict[int, _Task] = {}
        self._compile_key: tuple[Any, ...] | None = None  # the compile last reported
        #: (process, method) pairs that returned a frame: their kernels are loaded
        self._warm: set[tuple[int, str]] = set()
        self._tag = 0
        self._tiers: dict[str, Any] = {}
        self._reset_output()

    def _reset_output(self) -> None:
        """Forget what was submitted and shown under the previous config."""
        self._last_submit: int | None = None
        self._last_shown: int | None = None
        self._first_since: float | None = None  # first task under this config submitted at
        self._first_pending = True
        self._ready: dict[int, tuple[_Task, Any, float]] = {}  # results waiting for older ones
        self._fallback_next = 0.0
        self._rung = 0  # the highest rung of the ladder shown for this config (RUNG_CODES)
        self._ema: dict[str, float] = {}
        self._credit = 0.0
        self.put("fallback", 0.0)

    def _restart_clock(self) -> None:
        """The step clock started again (another source, or a camera that restarted its
        counter): forget all that is keyed by the old clock's steps. Kept, the new frames
        waited until the new clock passed the old one, for as long as the old source had
        played (up to the arrival log's 13 s): dropped as late (their arrival looked up
        among the old steps), not submitted (older than the last submitted step) or dropped
        as out of order (older than the last shown). Frames still computing on the old clock
        are dropped when they come back."""
        self._clock += 1
        self._arrival.clear()
        self._last_submit = self._last_shown = None
        if self._ready:
            self.bump("dropped_late", len(self._ready))
            self._ready.clear()

    def _current(self, task: _Task) -> bool:
        """Whether ``task`` was computed under the running config and step clock."""
        return task.version == self.config.version and task.clock == self._clock

    def bump(self, name: str, by: float = 1.0) -> None:
        self.st[name] += by

    def put(self, name: str, value: float) -> None:
        self.st[name] = value

    def close(self) -> None:
        self.pool.close()

    # -- configuration ------------------------------------------------------------------------
    def attach(self, ring_path: str, layout: Layout) -> None:
        from cfsr_live.shm.ring import SpikeRing

        if self.reader is not None:
            self._lost_base += self.reader.lost_frames
            self._skip_base += self.reader.skipped_frames
            self._overrun_base += self.reader.overruns
            self._torn_base += self.reader.torn
            self.reader.close()
        if self.ring is not None:
            self.ring.close()
        self.ring = SpikeRing.attach(ring_path)
        self.layout = layout
        self._restart_clock()  # a new ring is a new source: its steps count from its own start
        self.reader = self.ring.reader(start="latest", register=self.config.deterministic, keep=1)
        self._build()

    def _build(self, cfg: WorkerConfig | None = None) -> None:
        """Make the reconstructor run ``cfg`` (default: the current config), all or nothing.

        The new state is built completely before it replaces the running one
        (:meth:`StreamingReconstructor.set_method` is itself atomic; the buffer holds the
        longest window of the config's tiers); on any failure this raises with the old
        configuration and reconstructor untouched. On success the config becomes current and
        its version is acknowledged to the supervisor.
        """
        from cfsr.streaming import StreamingReconstructor

        cfg = self.config if cfg is None else cfg
        tiers = _tiers(cfg)
        widest = max(tiers.values(), key=lambda m: sum(m.window))
        if self.rec is None or self.rec.layout != self.layout:
            rec = StreamingReconstructor(widest, self.layout, slack=1024)
            if self.rec is not None:
                self._gaps_base += self.rec.gaps
            self.rec = rec
        else:
            self.rec.set_method(widest)
        self.config = cfg
        self._tiers = tiers
        self._reset_output()
        self.put("config_version", cfg.version)
        self.evt_q.put(ConfigAnswer(cfg.version, applied=True))

    def configure(self, cfg: WorkerConfig) -> None:
        """Apply config ``cfg`` or reject it, keeping the old one.

        Every version gets exactly one :class:`ConfigAnswer` on the event queue: applied, or
        rejected with the reason (the running reconstruction goes on unchanged, so frames
        keep coming).
        """
        if self.layout is None:  # not attached yet: the config is used when it is
            self.config = cfg
            return
        try:
            self._build(cfg)
        except Exception as exc:  # noqa: BLE001 - any failure rejects this version only
            reason = f"{type(exc).__name__}: {exc}"
            self.evt_q.put(ConfigAnswer(cfg.version, applied=False, reason=reason))
        else:
            self._next_out = 0.0  # publish under the new config at once, not at the old pace

    # -- main loop ------------------------------------------------------------------------------
    def needed_frames(self) -> int:
        rec = self.rec
        return rec.before + rec.after + 1

    def ingest(self) -> int:
        """Move new ring blocks into the reconstructor; returns frames pushed."""
        reader, rec, ring = self.reader, self.rec, self.ring
        if reader is None or rec is None:
            return 0
        pushed = 0
        if not self.config.deterministic:
            need_blocks = -(-self.needed_frames() // ring.slot_frames) + 1
            if reader.backlog > need_blocks + 1:
                reader.skip_to_latest(need_blocks)  # counted in reader.skipped_frames
        budget = time.monotonic() + 0.05
        while True:
            blk = reader.poll()
            if blk is None:
                break
            from cfsr_live.driver.source import BlockFlags

            if self._arrival and blk.index < self._arrival[-1][0]:
                self._restart_clock()  # a step clock never goes back: it started again
            if blk.flags & BlockFlags.DISCONTINUITY:
                rec.reset(blk.index)
            rec.push(blk.data, blk.index)
            ok = reader.release(blk)
            self.put("worker_skip_frames", self._skip_base + reader.skipped_frames)
            self.put("ring_lost_frames", self._lost_base + reader.lost_frames)
            self.put("ring_overruns", self._overrun_base + reader.overruns)
            self.put("ring_torn", self._torn_base + reader.torn)
            if not ok:
                rec.reset(blk.index + blk.n_frames)  # the data we pushed was torn
                continue
            self.put("gaps", self._gaps_base + rec.gaps)
            self._arrival.append((blk.index + blk.n_frames, blk.t_host))
            pushed += blk.n_frames
            if time.monotonic() > budget:
                break
        self.bump("steps_ingested", pushed)
        return pushed

    def _arrival_of(self, step: int) -> float:
        for end, t in self._arrival:
            if end > step:
                return t
        return self._arrival[-1][1] if self._arrival else time.monotonic()

    def _quality(self) -> str:
        """The tier of the next frame (:func:`pick_tier` on the measured costs)."""
        if len(self._tiers) < 2:
            return next(iter(self._tiers))
        # seconds of pool time one frame may take for the pool to keep max_fps
        budget_ms = 1e3 * self.pool.workers / self.config.max_fps
        tier, self._credit = pick_tier(
            self._ema.get("full"), self._ema.get("fast"), budget_ms, self._credit
        )
        return tier

    def _compiling_first(self) -> tuple[_Task, Any] | None:
        """The pending task of the config and its process's compile report, while the
        config's first frame waits on a compile (or on another process's compile)."""
        if not self._first_pending:
            return None
        for task in self._tasks.values():
            if not task.rung and self._current(task):
                beat = self.pool.compiling(task.process)
                if beat is not None:
                    return task, beat
        return None

    def _submit(self) -> bool:
        """Hand the newest computable step to an idle pool process, if the pace allows;
        while the config's first frame compiles, the next rung of the ladder instead."""
        rec = self.rec
        now = time.monotonic()
        if rec is None or now < self._next_out or not self.pool.idle:
            return False
        t = rec.latest_step()
        if t is None:
            return False
        if self._compiling_first() is not None:
            return self._submit_rung(t, now)
        if self._first_pending and any(self._current(k) and not k.rung
                                       for k in self._tasks.values()):
            # one first frame at a time: it may be compiling, and a second process would only
            # wait on the same kernels (the ladder's rung can use it instead)
            return False
        if self._last_submit is not None and t <= self._last_submit:
            return False
        quality = self._quality()
        cfg = self._tiers[quality]
        before, after = cfg.window
        a = max(rec.first_step, t - before)
        b = min(rec.next_step, t + after + 1)
        need = (b - a) * rec.layout.frame_bytes
        resize = need > self.pool.region_bytes or (
            self.pool.region_bytes > self.pool.base_bytes >= need  # a large window reverted
        )
        if resize:
            if self.pool.pending:  # the regions change size once the pool is idle
                return False
            if need > self.pool.region_bytes:
                self.pool.grow(need)
            else:
                self.pool.shrink()
            self._warm.clear()  # new processes: their first frames load the kernels again
        self._tag += 1
        tag = self._tag
        arrival = self._arrival_of(t + rec.after)
        delay = 0.0
        if self._first_pending:
            if self._first_since is None:
                self._first_since = now
                self.put("first_frame_since", now)
            delay = self.slow_first  # test hook: every process waits, as on a compile
        k = self.pool.submit(tag, cfg, rec.layout, rec.packed(a, b), a, [(a, b, t)],
                             delay=delay)
        cold = (k, cfg.method) not in self._warm
        self._tasks[tag] = _Task(
            t, arrival, quality, self.config.version, now, k, cfg.method, cold, self._clock
        )
        self._last_submit = t
        self._next_out = max(now + 1.0 / self.config.max_fps, time.monotonic())
        return True

    def _submit_rung(self, t: int, now: float) -> bool:
        """While the config's first frame compiles, an idle process computes the method's
        rung of the ladder (CSR for CFSR: its kernels compile in seconds) at the newest step,
        one at a time, so the picture climbs from TFP to CSR before CFSR arrives."""
        rung = LADDER.get(self.config.method.method)
        rec = self.rec
        if rung is None or rec is None or any(k.rung for k in self._tasks.values()):
            return False
        if self._last_shown is not None and t <= self._last_shown:
            return False
        cfg = _rung_config(rung)
        before, after = cfg.window
        if t + after >= rec.next_step:
            t = rec.next_step - after - 1
        a, b = max(rec.first_step, t - before), min(rec.next_step, t + after + 1)
        if t < a or (b - a) * rec.layout.frame_bytes > self.pool.region_bytes:
            return False
        self._tag += 1
        k = self.pool.submit(self._tag, cfg, rec.layout, rec.packed(a, b), a, [(a, b, t)])
        self._tasks[self._tag] = _Task(
            t, self._arrival_of(t + after), "full", self.config.version, now, k, rung,
            (k, rung) not in self._warm, self._clock, rung=True,
        )
        self._next_out = max(now + 1.0 / min(self.config.max_fps, STAND_IN_FPS),
                             time.monotonic())
        return True

    def _collect(self) -> bool:
        """Publish the results that are in, in step order; True when one was shown.

        A result whose older sibling (same config, earlier step) is still computing waits
        for it in ``_ready`` (frames side by side finish in any order; showing the newer one
        at once would throw the older one away), and goes out right after it.
        """
        from cfsr.pool import TaskError

        while self._tasks:
            try:
                r = self.pool.collect(timeout=0)
            except TaskError as exc:  # this frame failed; the process takes the next one
                self._tasks.pop(exc.tag, None)
                self._flush()
                raise
            if r is None:
                break
            task = self._tasks.pop(r.tag)
            (t, out), ms = r.outputs[0], r.compute_ms[0]
            if task.cold:  # its time holds the kernels' loading or compiling: not a frame's
                self._warm.add((task.process, task.method))
            if task.rung:
                self._show_rung(task, t, out, ms)
                continue
            if not task.cold and ms > 0:
                old = self._ema.get(task.quality)
                self._ema[task.quality] = ms if old is None else 0.8 * old + 0.2 * ms
            if not self._current(task):
                self.bump("dropped_late")  # computed under a config or a clock since replaced
                continue
            self._ready[t] = (task, out, ms)
        shown = self._flush()
        self._check_hangs()
        return shown

    def _show_rung(self, task: _Task, t: int, out: Any, ms: float) -> None:
        """Show a rung's frame while the config's first frame still waits (and it is newer
        than what is shown); the ladder only climbs, so TFP stops once CSR is shown."""
        if not (self._first_pending and self._current(task)):
            return
        if self._last_shown is not None and t <= self._last_shown:
            return
        self._rung = max(self._rung, RUNG_CODES[task.method])
        self.put("fallback", float(self._rung))
        self._publish(t, out, task.method, task.arrival, ms, timed=False)
        self.bump("fallback_frames")

    def _flush(self) -> bool:
        """Show the waiting results that no older task of their config precedes."""
        shown = False
        while self._ready:
            t = min(self._ready)
            if any(self._current(k) and not k.rung and k.step < t
                   for k in self._tasks.values()):
                break
            task, out, ms = self._ready.pop(t)
            first, self._first_pending = self._first_pending, False
            if first:  # shown however long it took: nothing newer of this config exists
                self.slow_first = 0.0
                self.put("first_frame_since", 0.0)
                self.put("fallback", 0.0)
            # the step order holds within one config: a new config's first frame is shown
            # even at an earlier or equal step (a method that looks further ahead, or any
            # change on a paused replay, whose data end has not moved)
            if not first and self._last_shown is not None and t <= self._last_shown:
                self.bump("dropped_order")
                continue
            # late only when something newer of this config is on its way to replace it: the
            # newest frame there is is shown however old (dropping it leaves an older one up)
            if (
                not first
                and time.monotonic() - task.arrival > LATE_S
                and any(self._current(k) and not k.rung and k.step > t
                        for k in self._tasks.values())
            ):
                self.bump("dropped_late")
                continue
            self._publish(t, out, self._tiers[task.quality].method, task.arrival, ms,
                          timed=not task.cold)
            self.bump("q_" + task.quality)
            shown = True
        return shown

    def _check_hangs(self) -> None:
        """A task pending past :data:`TASK_HANG_S` while its process neither compiles nor
        waits for a compile is a hung process: PoolError, so the worker exits and the
        supervisor restarts it with a fresh pool. Time spent compiling is not counted (the
        process's compile heartbeat, :meth:`FramePool.compiling`): a compile of minutes on a
        busy machine is never killed, and a frame stuck anywhere else still is."""
        from cfsr.pool import PoolError

        now = time.monotonic()
        for task in self._tasks.values():
            if self.pool.compiling(task.process) is not None:
                continue
            since = max(task.submitted, self.pool.compile_ended(task.process))
            if now - since > TASK_HANG_S:
                raise PoolError(
                    f"pool process {task.process} has computed step {task.step} for "
                    f"{now - task.submitted:.0f} s ({now - since:.0f} s since it last "
                    "compiled): taken for a hang"
                )

    def _fallback(self) -> bool:
        """While the first frame under the config waits on numba's compiler (its process's
        compile heartbeat says so), show TFP frames, computed here, so the image does not
        freeze: the ladder's first rung, until a higher one (CSR) is shown. A first frame
        that is merely slow (no compile) keeps the last frame of the chosen method."""
        rec = self.rec
        if (
            rec is None
            or not self._first_pending
            or self._first_since is None
            or self.config.method.method == "tfp"
            or self._rung > RUNG_CODES["tfp"]
            or self._compiling_first() is None
        ):
            return False
        now = time.monotonic()
        if now - self._first_since < FALLBACK_AFTER_S or now < self._fallback_next:
            return False
        t = rec.latest_step()
        if t is None or (self._last_shown is not None and t <= self._last_shown):
            return False
        from cfsr.methods.registry import get_method

        tfp = get_method("tfp")
        fb = _rung_config("tfp")
        before, after = fb.window
        t0 = time.perf_counter()
        out = tfp.run_window(
            rec, max(rec.first_step, t - before), min(rec.next_step, t + after + 1), t,
            fb.params,
        )
        ms = (time.perf_counter() - t0) * 1e3
        self._rung = max(self._rung, RUNG_CODES["tfp"])
        self.put("fallback", float(self._rung))
        self._publish(t, out, "tfp", self._arrival_of(t), ms, timed=False)
        self.bump("fallback_frames")
        self._fallback_next = now + 1.0 / min(self.config.max_fps, STAND_IN_FPS)
        return True

    def _publish(
        self, t: int, out: Any, method: str, arrival: float, compute_ms: float,
        *, timed: bool = True,
    ) -> None:
        """Show frame ``t``; ``timed``: its compute and latency join the status's averages
        (not a process's first frame of a method, whose time holds the kernels' loading)."""
        from cfsr.display import to_display

        gain = self.config.gain
        g = float(gain) if gain else _auto_gain(out.rate)
        img = to_display(out.rate, g)
        latency_ms = (time.monotonic() - arrival) * 1e3
        self.slot.publish(
            step=t,
            image=img,
            masks=out.masks,
            method=method,
            gain=g,
            t_arrival=arrival,
            compute_ms=compute_ms,
            latency_ms=latency_ms,
        )
        self._last_shown = t
        self.bump("frames_out")
        if not timed:
            return
        a = 0.2
        for name, v in (("compute_ms", compute_ms), ("latency_ms", latency_ms)):
            old = self.st[name]
            self.st[name] = v if old == 0 else (1 - a) * old + a * v

    def _report_compile(self) -> None:
        """Tell the supervisor what the config's first frame waits on (each change of
        kernel, count or whole CPU second, and once when no compile holds it any more)."""
        from cfsr.warmup import measured_compile

        got = self._compiling_first()
        key = None if got is None else (got[1].kernel, got[1].kernels, int(got[1].cpu_s))
        if key == self._compile_key:
            return
        self._compile_key = key
        progress = None
        if got is not None:
            task, beat = got
            table = measured_compile().get("methods", {}).get(task.method, {})
            progress = CompileProgress(
                method=task.method, kernel=beat.kernel, waiting=beat.waiting,
                kernels=beat.kernels, total=len(table.get("kernels", [])) or None,
                cpu_s=beat.cpu_s, estimate_s=table.get("cpu_s"),
            )
        self.evt_q.put(Compiling(progress))

    def maybe_output(self) -> bool:
        """One round of output: collect and publish, submit the next step, or show a
        fallback frame while the first one waits; True when something happened."""
        shown = self._collect()
        submitted = self._submit()
        fell_back = self._fallback()
        self._report_compile()
        return shown or submitted or fell_back


def pick_tier(
    full_ms: float | None, fast_ms: float | None, budget_ms: float, credit: float
) -> tuple[str, float]:
    """CFSR's auto tier for the next frame, and the credit carried to the one after.

    ``full_ms``/``fast_ms``: measured cost of a frame of each tier (None: not measured yet,
    so that tier is tried); ``budget_ms``: what one frame may cost for the pool to keep the
    frame rate (processes / max_fps). Full when full frames fit the budget; otherwise the
    share of full frames that keeps the mean cost within it, ``(budget - fast) / (full -
    fast)``, spread evenly by the credit (none when even fast frames exceed it).
    """
    if full_ms is None:
        return "full", credit
    if full_ms <= budget_ms:
        return "full", 0.0
    if fast_ms is None:
        return "fast", credit
    share = 0.0 if full_ms <= fast_ms else (budget_ms - fast_ms) / (full_ms - fast_ms)
    credit += min(1.0, max(0.0, share))
    if credit >= 1.0:
        return "full", credit - 1.0
    return "fast", credit


def _tiers(cfg: WorkerConfig) -> dict[str, Any]:
    """The method configs a worker config runs, by tier: the config as given under its own
    ``quality`` (``full`` for a method without one), or for a method with a ``quality``
    parameter (CFSR) under ``quality = auto``, its ``full`` and ``fast`` tiers."""
    m = cfg.method
    if "quality" not in m.params:
        return {"full": m}
    if cfg.quality != "auto":
        return {str(m.params["quality"]): m}
    return {
        "full": m.replace(params={"quality": "full"}),
        "fast": m.replace(params={"quality": "fast"}),
    }


@functools.cache
def _rung_config(method: str) -> Any:
    """A rung of the ladder at its default parameters (TFP, the first: cheap, and the
    first a warm-up compiles; CSR for CFSR)."""
    from cfsr.config import MethodConfig

    return MethodConfig(method)


def _auto_gain(rate) -> float:
    from cfsr.display import auto_gain

    return auto_gain(rate)


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
    from cfsr._heap import keep_freed_memory
    from cfsr.procs import ignore_stop_signals

    # Ctrl+C, a closed terminal, Ctrl+\ and a kill of the process group reach us too: the
    # supervisor stops us (and our pool, releasing its semaphores and regions), not the
    # signal; it kills us (SIGKILL) when a stop does not end us.
    ignore_stop_signals()
    keep_freed_memory()  # frames reuse the last frame's large arrays (no page faults)
    from cfsr.pool import PoolError, TaskError
    from cfsr.procs import start_compile_beat

    # We are a daemon of the web process (ended with it), and multiprocessing forbids a
    # daemon children of its own; our pool's processes are daemons of ours and also leave by
    # themselves within a second of our end (cfsr.pool checks its parent), so nothing lingers.
    mp.current_process()._config["daemon"] = False  # type: ignore[attr-defined]

    # at exit, do not wait to hand over events nobody may read any more (a supervisor that
    # died leaves the queue's pipe full, and the exit would block on it for ever)
    evt_q.cancel_join_thread()
    w: _Worker | None = None
    try:
        w = _Worker(slot_path, config, evt_q, workers, threads)
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


# ----------------------------------------------------------------------------------------------
# supervisor (web process)
# ----------------------------------------------------------------------------------------------
class WorkerSupervisor:
    """Run :func:`worker_main` in a child process; restart it when it dies.

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

    # -- lifecycle --------------------------------------------------------------------------------
    def start(self, ring_path: str, layout: Layout) -> None:
        """Spawn the worker on the ring at ``ring_path`` and watch it."""
        self._ring_path, self._layout = ring_path, layout
        self._spawn()
        self._thread = threading.Thread(target=self._monitor, name="cfsr-supervisor", daemon=True)
        self._thread.start()

    def _spawn(self) -> None:
        from cfsr.procs import release_queue

        with self._lock:
            self.ready.clear()
            for q in (self._cmd_q, self._evt_q):  # a restart: the dead worker's queues
                if q is not None:
                    release_queue(q)
            self._cmd_q = self._ctx.Queue()
            self._evt_q = self._ctx.Queue()
            self._proc = self._ctx.Process(
                target=worker_main,
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
            from cfsr.procs import stop_signals_blocked

            with stop_signals_blocked():  # until the worker ignores them (worker_main)
                self._proc.start()
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
        from cfsr.procs import release_queue

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
            self._send(Attach(ring_path, layout))

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

    def _monitor(self) -> None:
        backoff = 0.5
        while not self._stop.wait(0.1):
            self._drain()
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
                  "ring_overruns", "ring_torn", "gaps", "errors", "q_full", "q_fast",
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
                quality=QualityShare(
                    mode=self.config.quality if "quality" in self.config.method.params
                    else None,
                    full=st.q_full,
                    fast=st.q_fast,
                ),
                fallback_method=_RUNG_NAMES.get(int(st.fallback)) if first else None,
                compiling=self.compiling if first else None,
            ),
            latency_ms=st.latency_ms,
            compute_ms=st.compute_ms,
            ring_lost_frames=st.ring_lost_frames,
            skipped_frames=st.worker_skip_frames,
        )
