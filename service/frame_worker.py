"""The worker process's state: the ring reader, the streaming buffer, the pool that
reconstructs, and the latest-frame slot it publishes to (:class:`FrameWorker`).

The worker maps the spike ring and the latest-frame slot, feeds ring blocks into the single
:class:`cfsr.StreamingReconstructor`, and publishes the newest reconstruction (8-bit image,
coarse and fine masks, timings) at most ``max_fps`` times a second. It never waits for anyone:
when it falls behind it skips the backlog it does not need (counted as ``worker_skip``), and if
the ring overran it, the ring reader counts those frames (``ring_lost``). Its loop and commands
are in :mod:`cfsr_live.service.worker_loop`.
"""

from __future__ import annotations

import os
import time
from collections import deque
from typing import Any

from cfsr.defects import DefectCorrector, DefectMap
from cfsr.display import auto_gain, to_display
from cfsr.layout import Layout
from cfsr.methods.registry import get_method
from cfsr.pool import FramePool, PoolError, TaskError
from cfsr.streaming import StreamingReconstructor
from cfsr_live.driver.source import BlockFlags
from cfsr_live.service.config import WorkerConfig
from cfsr_live.service.frameslot import FrameSlot
from cfsr_live.service.kernel_warmup import RECONSTRUCTION_NICE
from cfsr_live.service.ladder import LadderSteps
from cfsr_live.service.pacing import FrameTask, late_after_s, pick_tier, tiers_of
from cfsr_live.service.priority import FramePriority
from cfsr_live.service.schema import DEFECT_STATES, DEFECTS_MASK, quality_code
from cfsr_live.service.worker_messages import ConfigAnswer, DefectMapFound
from cfsr_live.shm.ring import SpikeRing

__all__ = ["TASK_HANG_S", "UNWATCHED_FPS", "FrameWorker"]




#: frames a second with no client watching: enough for ``/readyz`` and ``/metrics`` to see the
#: worker publish, without spending the machine on frames nobody sees
UNWATCHED_FPS = 1.0
#: a pool task pending longer than this, not counting the time its process spent compiling
#: kernels (or waiting for another process's compile of them), is taken for a hang
TASK_HANG_S = 120.0


class FrameWorker(LadderSteps):
    """The worker process's state: the ring reader, the streaming buffer, and the pool of
    processes that reconstruct (:class:`cfsr.pool.FramePool`).

    The loop ingests ring blocks into the buffer, hands the newest computable step to an idle
    pool process whenever ``max_fps`` allows, and publishes finished frames in step order:
    a result older than one already shown is dropped (``dropped_order``), one whose spikes
    arrived longer ago than the pipeline takes at the rate it holds
    (:func:`~cfsr_live.service.pacing.late_after_s`) while a newer frame of its config computes, or
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
        self.slot = FrameSlot.attach(slot_path)
        self.evt_q = evt_q
        self.config = config
        self.ring = None
        self.reader = None
        self.rec = None
        self.layout = None
        #: the source's given defect map (WorkerConfig.defect_map) the corrector started from,
        #: and the corrector version last sent to the supervisor (for recordings)
        self._defects_given: Any = ()
        self._defects_sent = -1
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
        #: clients watching the frames (None: not told, as a worker run without the web
        #: process's hub: compute at max_fps)
        self.viewers: int | None = None
        #: the step to compute instead of the newest (a paused replay's compare), or None
        self.hold: int | None = None
        # not waiting for the processes to start: the heartbeat and the first frames of the
        # loop do not wait on their imports
        self.pool = FramePool(workers, threads, wait=False, nice=RECONSTRUCTION_NICE)
        self.put("workers", self.pool.workers)
        self.put("threads", self.pool.threads)
        self._tasks: dict[int, FrameTask] = {}
        self._compile_key: tuple[Any, ...] | None = None  # the compile last reported
        #: (process, method) pairs that returned a frame: their kernels are loaded
        self._warm: set[tuple[int, str]] = set()
        self._tag = 0
        self._tiers: dict[str, Any] = {}
        #: frames below acquisition: pool processes lowered once their kernels are loaded
        self._priority = FramePriority()
        self._reset_output()

    def _reset_output(self) -> None:
        """Forget what was submitted and shown under the previous config."""
        self._last_submit: int | None = None
        self._last_shown: int | None = None
        self._first_since: float | None = None  # first task under this config submitted at
        self._first_pending = True
        self._ready: dict[int, tuple[FrameTask, Any, float]] = {}  # results waiting for older ones
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
        self.hold = None  # a step of the old clock
        self._arrival.clear()
        self._last_submit = self._last_shown = None
        if self._ready:
            self.bump("dropped_late", len(self._ready))
            self._ready.clear()

    def _current(self, task: FrameTask) -> bool:
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
        # from the oldest block held, not the head: a paused replay (paused before our first
        # frame, or sought and stepped before we started) writes nothing more, and its blocks
        # already in the ring are what there is to show; older ones than a frame needs are
        # skipped at the first ingest (worker_skip)
        self.reader = self.ring.reader(start="oldest", register=self.config.deterministic, keep=1)
        self._defects_given = ()  # a new source: its sensor's map is learnt afresh
        self._build()

    def _build(self, cfg: WorkerConfig | None = None) -> None:
        """Make the reconstructor run ``cfg`` (default: the current config), all or nothing.

        The new state is built completely before it replaces the running one
        (:meth:`StreamingReconstructor.set_method` is itself atomic; the buffer holds the
        longest window of the config's tiers); on any failure this raises with the old
        configuration and reconstructor untouched. On success the config becomes current and
        its version is acknowledged to the supervisor.
        """
        cfg = self.config if cfg is None else cfg
        tiers = tiers_of(cfg)
        widest = max(tiers.values(), key=lambda m: sum(m.window))
        if self.rec is None or self.rec.layout != self.layout:
            # hot and dead pixels corrected before every method (its corrector: _set_defects)
            rec = StreamingReconstructor(widest, self.layout, slack=1024)
            if self.rec is not None:
                self._gaps_base += self.rec.gaps
            self.rec = rec
        else:
            self.rec.set_method(widest)
        self._set_defects(cfg)
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
            if reader.backlog > need_blocks + 1 or (reader.backlog and not self._start_due()):
                # counted in reader.skipped_frames; until a frame can start, the newest blocks
                # stay in the ring uncopied (the CPU goes to acquisition and to the pool)
                reader.skip_to_latest(need_blocks)
                if not self._start_due():
                    return 0
        budget = time.monotonic() + 0.05
        while True:
            blk = reader.poll()
            if blk is None:
                break
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
        self._put_defects()
        return pushed

    def _set_defects(self, cfg: WorkerConfig) -> None:
        """The corrector of ``cfg``: the source's given map (its sidecar's: a calibration, or
        a map learnt before) kept as is, else one learnt from the stream; a new given map or a
        new source starts a new one. Switched on or off by ``cfg.defects``."""
        if self.rec.defects is None or cfg.defect_map != self._defects_given:
            given = (DefectMap.from_dict(cfg.defect_map, self.layout.shape)
                     if cfg.defect_map else None)
            self.rec.defects = DefectCorrector(self.layout, given)  # given: kept as is
            self._defects_given = cfg.defect_map
            self._defects_sent = -1
        self.rec.defects.enabled = cfg.defects

    def _put_defects(self) -> None:
        """The defect map's state in the counters (the status's ``defects``); a changed map
        to the supervisor, which a recording keeps in its sidecar."""
        d = self.rec.defects if self.rec is not None else None
        if d is None:
            return
        if d.version != self._defects_sent and (d.map.n_hot or d.map.n_dead or d.inv_gain
                                                is not None):
            self._defects_sent = d.version
            self.evt_q.put(DefectMapFound(d.current().to_dict()))
        st = d.state()
        self.put("defects_state", DEFECT_STATES.index(st["state"]))
        self.put("defects_hot", st["hot"])
        self.put("defects_dead", st["dead"])
        self.put("defects_confidence", st["confidence"])
        self.put("defects_gain", int(st["gain"] and d.enabled))

    def _start_due(self) -> bool:
        """Whether a frame (or a stand-in) may start now: the pace allows it and a pool
        process is idle. Only then are ring blocks copied in (the window's, a few ms): the
        blocks that arrived while every process was busy are never copied. Copying from 50 ms
        before a process's measured finish, and all along while it ran past it or computed a
        first frame (kernels loading, seconds), cost the worker 312 ms of CPU a frame at load
        9 (52 ms copying only with a process idle), taken from the pool and acquisition."""
        now = time.monotonic()
        if self._first_pending and self._first_since is not None and now >= self._fallback_next:
            return True  # a stand-in, computed here
        return now >= self._next_out and bool(self.pool.idle)

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
        t = self._held(t)
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
        self._tasks[tag] = FrameTask(
            t, arrival, quality, self.config.version, now, k, cfg.method, cold, self._clock
        )
        self._last_submit = t
        self._next_out = max(now + 1.0 / self._pace_fps(), time.monotonic())
        return True


    def _collect(self) -> bool:
        """Publish the results that are in, in step order; True when one was shown.

        A result whose older sibling (same config, earlier step) is still computing waits
        for it in ``_ready`` (frames side by side finish in any order; showing the newer one
        at once would throw the older one away), and goes out right after it.
        """
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
                and time.monotonic() - task.arrival > self._late_after(task.quality)
                and any(self._current(k) and not k.rung and k.step > t
                        for k in self._tasks.values())
            ):
                self.bump("dropped_late")
                continue
            tier = task.quality if "quality" in self.config.method.params else ""
            self._publish(t, out, self._tiers[task.quality].method, task.arrival, ms,
                          timed=not task.cold, quality=tier)
            self.bump("shown_" + task.quality)
            shown = True
        return shown

    def _check_hangs(self) -> None:
        """A task pending past :data:`TASK_HANG_S` while its process neither compiles nor
        waits for a compile is a hung process: PoolError, so the worker exits and the
        supervisor restarts it with a fresh pool. Time spent compiling is not counted (the
        process's compile heartbeat, :meth:`FramePool.compiling`): a compile of minutes on a
        busy machine is never killed, and a frame stuck anywhere else still is."""
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


    def _publish(
        self, t: int, out: Any, method: str, arrival: float, compute_ms: float,
        *, timed: bool = True, quality: str = "",
    ) -> None:
        """Show frame ``t``; ``timed``: its compute and latency join the status's averages
        (not a process's first frame of a method, whose time holds the kernels' loading);
        ``quality``: the tier that made it ("" for a method without tiers, or a stand-in)."""
        d = self.rec.defects if self.rec is not None else None
        if d is not None:  # a flat-field calibration's gain divided out (every method)
            out = d.flatten(out, get_method(method))
        gain = self.config.gain
        g = float(gain) if gain else auto_gain(out.rate)
        img = to_display(out.rate, g)
        latency_ms = (time.monotonic() - arrival) * 1e3
        masks = out.masks
        if d is not None and d.enabled and (d.map.n_hot or d.map.n_dead):
            masks = {**masks, DEFECTS_MASK: d.map.mask}
        self.slot.publish(
            step=t,
            image=img,
            masks=masks,
            method=method,
            gain=g,
            t_arrival=arrival,
            compute_ms=compute_ms,
            latency_ms=latency_ms,
            quality=quality,
        )
        self.put("shown_tier", quality_code(quality))
        self._last_shown = t
        self.bump("frames_out")
        if not timed:
            return
        a = 0.2
        for name, v in (("compute_ms", compute_ms), ("latency_ms", latency_ms)):
            old = self.st[name]
            self.st[name] = v if old == 0 else (1 - a) * old + a * v


    def hold_at(self, step: int | None) -> None:
        """Compute at ``step`` from now on (None: the newest step), once per config; a step
        back on purpose, so its frame is shown though a later one was."""
        self.hold = step
        self._last_submit = self._last_shown = None
        self._next_out = 0.0

    def _held(self, newest: int) -> int:
        """The step to compute: the held one while the buffer holds its window (the widest
        tier's, up to ``newest``), else ``newest``."""
        h, rec = self.hold, self.rec
        if h is None or rec is None or not rec.first_step + rec.before <= h <= newest:
            return newest
        return h

    def watch(self, viewers: int) -> None:
        """``viewers`` clients watch from now on: with none, compute :data:`UNWATCHED_FPS`
        frames a second; the first to connect gets a frame at once."""
        if viewers and not self.viewers:
            self._next_out = 0.0
        self.viewers = viewers
        self.put("viewers", viewers)

    def _pace_fps(self) -> float:
        """Frames a second to start: ``max_fps``, or :data:`UNWATCHED_FPS` with no viewer."""
        fps = self.config.max_fps
        return min(fps, UNWATCHED_FPS) if self.viewers == 0 else fps

    def _late_after(self, quality: str) -> float:
        """Seconds after its newest spike arrived that a frame of tier ``quality`` is late."""
        return late_after_s(self._ema.get(quality), self.pool.workers, self.config.max_fps)

    def _lower_priority(self) -> None:
        """Pool processes that returned a frame compute the next ones below acquisition
        (:class:`~cfsr_live.service.priority.FramePriority`); the status shows their nice."""
        pids = self.pool.pids
        if self._priority.lower(pids[k] for k, _ in self._warm if k < len(pids)):
            self.put("pool_nice", self._priority.lowest(p for p in pids if p > 0))

    def maybe_output(self) -> bool:
        """One round of output: collect and publish, submit the next step, or show a
        fallback frame while the first one waits; True when something happened."""
        self._lower_priority()
        shown = self._collect()
        submitted = self._submit()
        fell_back = self._fallback()
        self._report_compile()
        return shown or submitted or fell_back


