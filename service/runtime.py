"""The service's moving parts, owned by the FastAPI lifespan: source, acquisition thread,
ring, worker supervisor, frame hub and recorder.

Data flow: ``Source.read_block`` -> :class:`~driver.acquisition.Acquisition` ->
:class:`~shm.ring.SpikeRing` (shared memory) -> worker process -> latest-frame slot ->
:class:`~service.hub.FrameHub` -> per-client latest-only queues.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from datetime import datetime
from typing import Any

from cfsr.layout import Layout
from driver.acquisition import Acquisition
from driver.source import CameraControl, ReplayControl, Source
from service.catalog import SourceCatalog
from service.config import DisplayScale, LiveConfig, WorkerConfig
from service.settings import RECORDING_NAME_RE, Settings, SourceSpec
from service.worker import WorkerSupervisor
from shm.frameslot import FrameSlot
from shm.ring import SpikeRing

__all__ = ["Runtime", "ConflictError"]

log = logging.getLogger("cfsr.runtime")


class ConflictError(RuntimeError):
    """The request cannot be served in the current state (HTTP 409)."""


class _RateMeter:
    def __init__(self, window: float = 2.0) -> None:
        self.window = window
        self._s: deque[tuple[float, float]] = deque(maxlen=64)

    def add(self, value: float, t: float | None = None) -> None:
        self._s.append((time.monotonic() if t is None else t, value))

    def rate(self) -> float:
        if len(self._s) < 2:
            return 0.0
        t1, v1 = self._s[-1]
        t0, v0 = self._s[0]
        for t, v in self._s:
            if t1 - t <= self.window:
                t0, v0 = t, v
                break
        return (v1 - v0) / (t1 - t0) if t1 > t0 else 0.0


class Runtime:
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
        self.recorder = None
        self.last_recording: dict[str, Any] | None = None
        #: the configuration in force (set by :meth:`start`, changed by :meth:`set_config`)
        self.config: LiveConfig
        self._lock = threading.RLock()
        self.started = time.monotonic()
        self._in_rate = _RateMeter()
        self._work_rate = _RateMeter()
        self._frames_base = 0  # frames published into earlier rings
        self._lost_base: dict[str, float] = {}
        self._sampler_stop = threading.Event()
        self._sampler: threading.Thread | None = None
        self._stopped = False

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        """Validate the configuration of the settings, open the source, make the ring and
        the frame slot, start acquisition and the worker (all or nothing)."""
        from cfsr.config import MethodConfig

        st = self.settings
        self.config = LiveConfig(MethodConfig(st.method, st.params), DisplayScale(), st.max_fps)
        try:
            self.slot = FrameSlot.create()
            spec = self.settings.source
            src = self.catalog.open(spec)
            self._install(src, spec.id)
            self.worker = WorkerSupervisor(
                self.slot, self._worker_config(), hang_timeout=self.settings.worker_hang_timeout
            )
            assert self.ring is not None
            self.worker.start(str(self.ring.path), self.source.info.layout)
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
                self._work_rate.add(w.stats().get("steps_ingested", 0.0))

    # -- sources ----------------------------------------------------------------------------------
    def _ring_for(self, src: Source) -> SpikeRing:
        lay = src.info.layout
        slot_frames = max(1, src.info.max_block_frames)
        want = self.settings.ring_seconds * src.info.rate_hz
        n_slots = max(8, math.ceil(want / slot_frames))
        blocking = self.settings.replay_mode == "fast"
        return SpikeRing.create(n_slots, slot_frames, lay.frame_bytes, blocking=blocking)

    def _install(self, src: Source, source_id: str) -> bool:
        """Make ``src`` the current source; returns True if a new ring was created."""
        src.open()
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
        c = src.counters()
        for k in ("lost_frames", "replay_behind_frames"):
            self._lost_base[k] = self._lost_base.get(k, 0) + c.get(k, 0)

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
            deterministic=self.settings.replay_mode == "fast",
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

    def set_config(
        self,
        *,
        method: str | None = None,
        params: dict[str, Any] | None = None,
        display: dict[str, Any] | None = None,
        max_fps: float | None = None,
    ) -> dict[str, Any]:
        """Validate, hand to the worker, and store once the worker applied it.

        All or nothing: a value out of range raises ValueError here (the new
        :class:`~service.config.LiveConfig` cannot be made); a configuration the worker
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
            new = self.config.changed(
                method=method, params=params, display=display, max_fps=max_fps
            )
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
    ) -> dict[str, Any]:
        """Record the live stream to ``DATA_DIR/recordings/NAME.dat`` (+ sidecar), capped at
        ``max_bytes`` (default: the free space less the recorder's reserve); OSError when not
        even one block fits."""
        from service.recorder import Recorder

        with self._lock:
            if self.recorder is not None and self.recorder.running:
                raise ConflictError(f"already recording to {self.recorder.path.name}")
            name = name or datetime.now().strftime("rec-%Y%m%d-%H%M%S")
            if not RECORDING_NAME_RE.match(name):
                raise ValueError(f"recording name {name!r}: use letters, digits, . _ - only")
            if not name.endswith(".dat"):
                name += ".dat"
            folder = self.settings.data_dir / "recordings"
            folder.mkdir(parents=True, exist_ok=True)
            path = folder / name
            if path.exists():
                raise ConflictError(f"recording {name} already exists")
            src = self.source
            assert src is not None and self.ring is not None
            meta = {
                "source": src.describe(),
                "gain": src.info.meta.get("gain"),
                "method_at_start": self.config.method.method,
            }
            meta = {k: v for k, v in meta.items() if v is not None}
            self.recorder = Recorder(
                self.ring,
                path,
                src.info.layout,
                rate_hz=src.info.rate_hz,
                meta=meta,
                max_frames=max_frames,
                max_bytes=max_bytes,
            )
            return self.recorder.describe()

    def stop_recording(self) -> dict[str, Any]:
        with self._lock:
            if self.recorder is None:
                raise ConflictError("not recording")
            self.last_recording = self.recorder.stop()
            self.recorder = None
            return self.last_recording

    def record_status(self) -> dict[str, Any]:
        r = self.recorder
        if r is not None:
            d = r.describe()
            if not d["recording"]:
                self.last_recording = d
                self.recorder = None
            return d
        if self.last_recording is not None:
            return {**self.last_recording, "recording": False}
        return {"recording": False}

    # -- status -----------------------------------------------------------------------------------
    def status(self, hub=None) -> dict[str, Any]:
        src, w, ring = self.source, self.worker, self.ring
        rate_hz = src.info.rate_hz if src else 40000.0
        wst = w.stats() if w else {}
        in_rate = self._in_rate.rate()
        w_rate = self._work_rate.rate()
        counters = src.counters() if src else {}
        source = {
            "id": self.source_id,
            "kind": src.info.kind if src else None,
            "name": src.info.name if src else None,
            "state": src.state.value if src else None,
            "capabilities": src.capabilities() if src else [],
            "width": src.info.layout.width if src else None,
            "height": src.info.layout.height if src else None,
            "rate_hz": rate_hz,
            "counters": {**counters, **(self.acq.stats() if self.acq else {})},
            "replay": None,
            "last_error": (src.last_error if src else None)
            or (self.acq.last_error if self.acq else None),
        }
        ctl = src.get_facility(ReplayControl) if src else None
        if ctl is not None:
            source["replay"] = ctl.state()
        cam = src.get_facility(CameraControl) if src else None
        if cam is not None:
            try:
                source["counters"]["device"] = cam.device_status()
            except Exception as exc:  # noqa: BLE001 - the camera may be gone right now
                source["counters"]["device"] = {"error": str(exc)}
        rec = self.record_status()
        usb_lost = counters.get("lost_frames", 0) if src and src.info.kind == "usb" else 0
        per_client = hub.client_stats() if hub else []
        drops = {
            "usb": int(usb_lost + self._lost_base.get("lost_frames", 0)),
            "replay": int(
                counters.get("replay_behind_frames", 0)
                + self._lost_base.get("replay_behind_frames", 0)
            ),
            "ring": int(wst.get("ring_lost_frames", 0)),
            "worker": int(wst.get("worker_skip_frames", 0)),
            "clients": int(hub.total_client_drops()) if hub else 0,
            "recorder": int(rec.get("lost_frames", 0) or 0),
            "per_client": per_client,
        }
        wd = w.describe() if w else {
            "alive": False, "ready": False, "pid": None, "restarts": 0, "crashes": [],
            "last_errors": [], "config_version": 0, "applied_version": -1,
            "heartbeat_age_s": None,
        }
        wd.update(
            {
                "steps_per_s": w_rate,
                "real_time_factor": w_rate / rate_hz if rate_hz else 0.0,
                "frames_out": int(wst.get("frames_out", 0)),
                "gaps": int(wst.get("gaps", 0)),
            }
        )
        latest = hub.latest if hub else None
        return {
            "uptime_s": time.monotonic() - self.started,
            "source": source,
            "method": self.config.method.method,
            "params": dict(self.config.method.params),
            "input_steps_per_s": in_rate,
            "real_time_factor": in_rate / rate_hz if rate_hz else 0.0,
            "output_fps": hub.fps() if hub else 0.0,
            "latency_ms": float(wst.get("latency_ms", 0.0)),
            "compute_ms": float(wst.get("compute_ms", 0.0)),
            "frame_step": latest.step if latest is not None else None,
            "drops": drops,
            "worker": wd,
            "ring": {
                "path": str(ring.path) if ring else None,
                "slots": ring.n_slots if ring else 0,
                "slot_frames": ring.slot_frames if ring else 0,
                "capacity_s": (ring.capacity_frames / rate_hz) if ring else 0.0,
                "frames_published": (self._frames_base + ring.frames_published) if ring else 0,
                "blocking": bool(ring.blocking) if ring else False,
            },
            "clients": len(per_client),
            "recording": rec,
        }

    @property
    def layout(self) -> Layout | None:
        return self.source.info.layout if self.source else None
