"""The service's moving parts, owned by the FastAPI lifespan: source, acquisition thread,
ring, worker supervisor, frame hub and recorder.

Data flow: ``Source.read_block`` -> :class:`~cfsr_live.driver.acquisition.Acquisition` ->
:class:`~cfsr_live.shm.ring.SpikeRing` (shared memory) -> worker process -> latest-frame slot ->
:class:`~cfsr_live.service.hub.FrameHub` -> per-client latest-only queues.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from datetime import datetime
from typing import TYPE_CHECKING, Any

from cfsr.layout import STEP_RATE_HZ, Layout
from cfsr_live.driver.acquisition import Acquisition
from cfsr_live.driver.source import ReplayControl, ReplayMode, Source
from cfsr_live.service.catalog import SourceCatalog
from cfsr_live.service.config import ConfigChange, DisplayScale, LiveConfig, WorkerConfig
from cfsr_live.service.frameslot import FrameSlot
from cfsr_live.service.kernel_warmup import KernelWarmup
from cfsr_live.service.recorder import Recorder
from cfsr_live.service.safefs import UnsafePathError, open_subfolder
from cfsr_live.service.settings import MAX_DISPLAY_PIXELS, RECORDING_NAME_RE, Settings, SourceSpec
from cfsr_live.service.status import (
    Drops,
    HubStatus,
    RateMeter,
    RecordStatus,
    SourceLosses,
    SourceReport,
    StatusModel,
    WorkerReport,
    real_time_factor,
    ring_status,
    source_report,
)
from cfsr_live.service.supervisor import WorkerSupervisor
from cfsr_live.shm.ring import SpikeRing

if TYPE_CHECKING:
    from cfsr_live.service.hub import FrameHub

__all__ = ["Runtime", "ConflictError"]

log = logging.getLogger("cfsr.runtime")


class ConflictError(RuntimeError):
    """The request cannot be served in the current state (HTTP 409)."""


class Runtime:
    """Owns the live components and their order of start and stop; answers the routers.

    It keeps no figures of its own beyond what spans components (frames and losses of
    sources and rings used before the current ones): each component reports its own status
    and :meth:`status` composes them.
    """

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.catalog = SourceCatalog(settings)
        self.catalog.add_cli_source(settings.source)
        self.slot: FrameSlot | None = None
        self.ring: SpikeRing | None = None
        self.source: Source | None = None
        self.source_id: str | None = None
        self.acq: Acquisition | None = None
        self.worker: WorkerSupervisor | None = None
        self.recorder: Recorder | None = None
        self.last_recording: RecordStatus | None = None
        #: the configuration in force (set by :meth:`start`, changed by :meth:`set_config`)
        self.config: LiveConfig
        self._lock = threading.RLock()
        self.started = time.monotonic()
        self._in_rate = RateMeter()  # frames entering the ring (this and earlier rings)
        self._frames_base = 0  # frames published into earlier rings
        self._lost_base = SourceLosses()  # what sources switched away from lost
        self._sampler_stop = threading.Event()
        self._sampler: threading.Thread | None = None
        self._viewers: int | None = None  # clients watching (None: no hub told us)
        self._stopped = False
        self.kernels = KernelWarmup()

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        """Validate the configuration of the settings, open the source, make the ring and
        the frame slot, start acquisition and the worker (all or nothing)."""
        st = self.settings
        self.config = LiveConfig.make(st.method, st.params, DisplayScale(), st.max_fps,
                                      st.quality)
        try:
            self.slot = FrameSlot.create(MAX_DISPLAY_PIXELS)
            spec = self.settings.source
            src = self.catalog.open(spec)
            self._install(src, spec.id)
            self.worker = WorkerSupervisor(
                self.slot,
                self._worker_config(),
                hang_timeout=self.settings.worker_hang_timeout,
                workers=self.settings.workers,
                threads=self.settings.threads,
            )
            assert self.ring is not None
            if self._viewers is not None:
                self.worker.set_viewers(self._viewers)
            self.worker.start(str(self.ring.path), self.source.info.layout)
            if self.settings.warmup:  # a first start compiles every method in the background
                self.kernels.start(first=self.config.method.method)
        except BaseException:
            # a start that fails half-way leaves no segment, thread or worker behind
            self.stop()
            raise
        self._sampler = threading.Thread(target=self._sample, name="cfsr-rates", daemon=True)
        self._sampler.start()

    def stop(self) -> None:
        """Stop everything started so far; safe to call twice and after a failed start."""
        self._sampler_stop.set()
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
            self.kernels.stop()
            if self.recorder is not None:
                self.last_recording = self.recorder.stop()
                self.recorder = None
            if self.acq is not None:
                self.acq.stop()
            if self.source is not None:
                self.source.close()
            if self.worker is not None:
                self.worker.stop()
            if self.ring is not None:
                self.ring.close()
            if self.slot is not None:
                self.slot.close()

    def _sample(self) -> None:
        while not self._sampler_stop.wait(0.25):
            ring, w = self.ring, self.worker
            if ring is not None:
                try:
                    self._in_rate.add(self._frames_base + ring.frames_published)
                except (TypeError, AttributeError):
                    pass
            if w is not None:
                w.sample()

    # -- sources ----------------------------------------------------------------------------------
    def _ring_for(self, src: Source) -> SpikeRing:
        lay = src.info.layout
        slot_frames = max(1, src.info.max_block_frames)
        # ring_seconds of the source, or less where that is over the byte cap: the rate and
        # geometry may come from any file in the data folder (ValueError -> 422 naming both)
        cap = self.settings.ring_max_bytes
        try:
            n_slots = SpikeRing.slots_for(self.settings.ring_seconds * src.info.rate_hz,
                                          slot_frames, lay.frame_bytes, max_bytes=cap)
        except ValueError as exc:
            raise ValueError(f"{src.info.name}: {exc} (cfsr serve --ring-max-mb)") from None
        blocking = self.settings.replay_mode == ReplayMode.UNPACED
        return SpikeRing.create(n_slots, slot_frames, lay.frame_bytes, blocking=blocking,
                                max_bytes=cap)

    def _check_geometry(self, src: Source) -> None:
        """ValueError (HTTP 422) when ``src``'s frames are larger than the display's frame
        slot holds (:data:`~cfsr_live.service.settings.MAX_DISPLAY_PIXELS`): such a source would be
        accepted and never shown (and its ring sized for frames nobody can display)."""
        lay = src.info.layout
        limit = self.slot.max_pixels if self.slot is not None else MAX_DISPLAY_PIXELS
        if lay.width * lay.height > limit:
            raise ValueError(
                f"{src.info.name}: {lay.width} x {lay.height} = {lay.width * lay.height} "
                f"pixels is more than the {limit} pixels the display holds"
            )

    def _install(self, src: Source, source_id: str) -> bool:
        """Make ``src`` the current source; returns True if a new ring was created."""
        src.open()
        try:
            self._check_geometry(src)  # a camera knows its geometry once open
        except ValueError:
            src.close()
            raise
        ring = self.ring
        new_ring = (
            ring is None
            or ring.frame_bytes != src.info.layout.frame_bytes
            or ring.slot_frames != max(1, src.info.max_block_frames)
        )
        if new_ring:
            if ring is not None:
                self._frames_base += ring.frames_published
            ring = self._ring_for(src)
        self.ring = ring
        self.source = src
        self.source_id = source_id
        self.acq = Acquisition(src, ring)
        self.acq.start()
        return new_ring

    def list_sources(self) -> list[dict[str, Any]]:
        out = []
        for e in self.catalog.scan().values():
            d = e.public()
            d["current"] = e.id == self.source_id
            out.append(d)
        return out

    def switch_source(self, source_id: str) -> dict[str, Any]:
        """Open listed source ``source_id`` and make it current (KeyError if not listed)."""
        spec: SourceSpec = self.catalog.spec_for(source_id)
        new = self.catalog.open(spec)  # may raise: the old source keeps running
        try:
            self._check_geometry(new)
        except ValueError:
            new.close()
            raise
        with self._lock:
            if self.recorder is not None:
                self.last_recording = self.recorder.stop()
                self.recorder = None
            old_acq, old_src, old_ring = self.acq, self.source, self.ring
            if old_acq is not None:
                old_acq.stop()
            if old_src is not None:
                self._keep_source_counters(old_src)
                old_src.close()
            try:
                new_ring = self._install(new, source_id)
            except Exception:
                # could not start the new one: go back to the old source
                if old_src is not None:
                    self._install(old_src, self.source_id or "previous")
                raise
            if new_ring and self.worker is not None:
                self.worker.attach(str(self.ring.path), new.info.layout)
                if old_ring is not None:
                    # the worker re-maps the new ring; the old file can go (mappings persist)
                    old_ring.close()
            self.worker.configure(self._worker_config())
        return self.source.describe()

    def _keep_source_counters(self, src: Source) -> None:
        """Keep what a source lost when it is switched away from (its counters' loss
        fields, whatever its kind)."""
        self._lost_base = self._lost_base.plus(SourceLosses.of(src.counters()))

    def facility(self, kind):
        src = self.source
        return None if src is None else src.get_facility(kind)

    def replay(self) -> ReplayControl:
        ctl = self.facility(ReplayControl)
        if ctl is None:
            kind = self.source.info.kind if self.source else "none"
            raise ConflictError(f"the current source ({kind}) has no replay controls")
        return ctl

    # -- configuration ----------------------------------------------------------------------------
    def _effective_gain(self, config: LiveConfig | None = None) -> float | None:
        """Display gain the worker uses (spikes/step shown as white; None: auto per frame)
        under ``config`` (default: the stored one), with the current source's own gain."""
        c = self.config if config is None else config
        src_gain = self.source.info.meta.get("gain") if self.source is not None else None
        return c.display.effective_gain(src_gain)

    def _worker_config(self, config: LiveConfig | None = None) -> WorkerConfig:
        """What the worker needs of ``config`` (default: the stored one)."""
        c = self.config if config is None else config
        return WorkerConfig(
            method=c.method,
            gain=self._effective_gain(c),
            max_fps=c.max_fps,
            deterministic=self.settings.replay_mode == ReplayMode.UNPACED,
            quality=c.quality,
            defects=c.defects,
            # the replayed recording's map (its sidecar): a replay starts corrected
            defect_map=self.source.info.meta.get("defects") if self.source else None,
        )

    def get_config(self) -> dict[str, Any]:
        """The stored configuration with the gain in effect (``GET /api/config``)."""
        self._settle_pending_config()
        return {**self.config.public(), "effective_gain": self._effective_gain()}

    #: Seconds :meth:`set_config` waits for the worker to apply a configuration before it
    #: answers "pending" (the worker reads commands between frames; a first frame of a
    #: method may first compile its kernels, which takes longer).
    config_ack_timeout_s: float = 5.0
    #: A configuration stored before the worker answered: (version, it, the one it replaced).
    _pending_config: tuple[int, LiveConfig, LiveConfig] | None = None

    def set_config(self, change: ConfigChange) -> dict[str, Any]:
        """Validate ``change``, hand the result to the worker, and store it once the worker
        applied it.

        All or nothing: a value out of range raises ValueError here (the new
        :class:`~cfsr_live.service.config.LiveConfig` cannot be made); a configuration the worker
        cannot apply (it keeps running the old one) raises ValueError with the worker's
        reason, and the stored configuration is not changed. When the worker has not
        answered within :attr:`config_ack_timeout_s`, the configuration is stored (the
        worker applies commands in order) and the result says ``state: "pending"``; should
        the worker reject it later, the next :meth:`get_config`/:meth:`set_config` restores
        the one it replaced. Returns the configuration with ``state`` (``applied`` or
        ``pending``) and the worker's config ``version``.
        """
        with self._lock:
            self._settle_pending_config()
            new = self.config.changed(change)
            if self.worker is None:
                self.config = new
                return {**self.get_config(), "state": "applied", "version": None}
            version = self.worker.configure(self._worker_config(new))
            ack = self.worker.wait_config(version, self.config_ack_timeout_s)
            if ack.state == "rejected":
                raise ValueError(f"configuration not applied, {ack.reason}")
            if ack.state == "pending":
                self._pending_config = (version, new, self.config)
            self.config = new
            return {**self.get_config(), "state": ack.state, "version": version}

    def _settle_pending_config(self) -> None:
        """Take the worker's late answer to a configuration stored while "pending"."""
        pend, w = self._pending_config, self.worker
        if pend is None or w is None:
            return
        version, stored, replaced = pend
        state = w.wait_config(version, 0.0).state
        if state == "pending":
            return
        with self._lock:
            self._pending_config = None
            if state == "rejected" and self.config is stored:
                self.config = replaced

    # -- recording --------------------------------------------------------------------------------
    def start_recording(
        self, name: str | None, max_frames: int | None = None, max_bytes: int | None = None
    ) -> RecordStatus:
        """Record the live stream to ``DATA_DIR/recordings/NAME.dat`` (+ sidecar), capped at
        ``max_bytes`` (default: the free space less the recorder's reserve); OSError when not
        even one block fits."""
        with self._lock:
            if self.recorder is not None and self.recorder.running:
                raise ConflictError(f"already recording to {self.recorder.path.name}")
            given = name
            name = name or datetime.now().strftime("rec-%Y%m%d-%H%M%S")
            if not RECORDING_NAME_RE.match(name):
                raise ValueError(f"recording name {name[:80]!r}: use letters, digits, . _ - "
                                 "only")
            if not name.endswith(".dat"):
                name += ".dat"
            folder = self.settings.data_dir / "recordings"
            try:
                # never through a link, never outside the data folder (cfsr_live.service.safefs)
                dir_fd = open_subfolder(self.settings.data_dir, "recordings")
            except UnsafePathError as exc:
                raise ConflictError(str(exc)) from None
            src = self.source
            assert src is not None and self.ring is not None
            meta = {
                "source": src.describe(),
                "gain": src.info.meta.get("gain"),
                "method_at_start": self.config.method.method,
            }
            meta = {k: v for k, v in meta.items() if v is not None}
            try:
                # a name is claimed by creating it exclusively: another server recording into
                # this folder, or a link planted there, makes it taken (an unnamed recording
                # takes the next free suffix)
                for k in range(1 if given else 100):
                    stem = name[:-4] if k == 0 else f"{name[:-4]}-{k + 1}"
                    try:
                        self.recorder = Recorder(
                            self.ring,
                            folder / f"{stem}.dat",
                            src.info.layout,
                            rate_hz=src.info.rate_hz,
                            meta=meta,
                            max_frames=max_frames,
                            max_bytes=max_bytes,
                            dir_fd=dir_fd,
                            defects=lambda: self.worker.defect_map if self.worker else None,
                        )
                        break
                    except FileExistsError:
                        if given or k == 99:
                            raise ConflictError(
                                f"recording {stem}.dat (or its sidecar) already exists in the "
                                "data folder (another server recording there, or a link)"
                            ) from None
            finally:
                os.close(dir_fd)
            return self.recorder.status()

    def stop_recording(self) -> RecordStatus:
        with self._lock:
            if self.recorder is None:
                raise ConflictError("not recording")
            self.last_recording = self.recorder.stop()
            self.recorder = None
            return self.last_recording

    def record_status(self) -> RecordStatus:
        """The recorder's report; once a recording has stopped by itself (cap, max_frames,
        error) it becomes the last recording, shown until the next one starts."""
        r = self.recorder
        if r is not None:
            st = r.status()
            if not st.recording:
                self.last_recording = st
                self.recorder = None
            return st
        if self.last_recording is not None:
            return self.last_recording.model_copy(update={"recording": False})
        return RecordStatus(recording=False)

    def set_viewers(self, count: int) -> None:
        """``count`` clients watch the frames (the hub says so as they come and go): with none,
        the worker computes one frame a second."""
        self._viewers = count
        if self.worker is not None:
            self.worker.set_viewers(count)

    def hold_step(self, step: int | None) -> None:
        """Frames at ``step`` instead of the newest while the worker's buffer holds it (a
        paused replay's compare; None: the newest again)."""
        if self.worker is not None:
            self.worker.hold_step(step)

    # -- status -----------------------------------------------------------------------------------
    def _rate_hz(self) -> float:
        """The current source's sensor rate, steps/s (the nominal one with no source)."""
        return self.source.info.rate_hz if self.source else float(STEP_RATE_HZ)

    def source_report(self) -> SourceReport:
        """The current source's and its acquisition thread's report."""
        return source_report(self.source_id, self.source, self.acq, self._rate_hz())

    def status(self, hub: FrameHub | None = None) -> StatusModel:
        """``GET /api/status``: every component's own report, composed; the drops of sources
        used before the current one are kept (:meth:`_keep_source_counters`)."""
        rate_hz = self._rate_hz()
        source = self.source_report()
        worker = self.worker.status(rate_hz) if self.worker else WorkerReport.absent()
        frames = hub.status() if hub else HubStatus()
        recording = self.record_status()
        in_rate = self._in_rate.rate()
        lost_before = self._lost_base
        return StatusModel(
            uptime_s=time.monotonic() - self.started,
            source=source.status,
            method=self.config.method.method,
            params=dict(self.config.method.params),
            input_steps_per_s=in_rate,
            real_time_factor=real_time_factor(in_rate, rate_hz),
            output_fps=frames.output_fps,
            latency_ms=worker.latency_ms,
            compute_ms=worker.compute_ms,
            frame_step=frames.frame_step,
            drops=Drops(
                usb=source.link_lost_frames + lost_before.link,
                replay=source.replay_behind_frames + lost_before.paced,
                ring=worker.ring_lost_frames,
                worker=worker.skipped_frames,
                clients=frames.client_drops,
                recorder=recording.lost_frames,
                per_client=frames.clients,
            ),
            worker=worker.status,
            ring=ring_status(self.ring, self._frames_base, rate_hz),
            clients=len(frames.clients),
            recording=recording,
            kernels=self.kernels.status(),
        )

    @property
    def layout(self) -> Layout | None:
        return self.source.info.layout if self.source else None
