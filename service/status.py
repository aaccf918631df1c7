"""The live service's status as typed values: each component reports its own small model and
:meth:`cfsr_live.service.runtime.Runtime.status` composes them into :class:`StatusModel`
(``GET /api/status``, ``/metrics``).

Who reports what:

* the source and its acquisition thread: :class:`SourceReport` (:func:`source_report`; the
  driver's objects know nothing of these models, arrows point down, so the report is read
  here from their public accessors);
* the spike ring: :class:`RingStatus` (:func:`ring_status`, same reason);
* the worker supervisor: :class:`WorkerReport` (:meth:`WorkerSupervisor.status`);
* the frame hub: :class:`HubStatus` (:meth:`FrameHub.status`), with one :class:`ClientDrops`
  per client;
* the recorder: :class:`RecordStatus` (:meth:`Recorder.status`).

Why: a figure is added or renamed in one component's model and its report, and the composed
response cannot drift from its declared shape (each model is validated where it is made,
not once at the end by the HTTP layer).

Only pydantic is imported here, not FastAPI: the hub, the recorder and the supervisor use
these models without the web stack; :mod:`cfsr_live.service.models` re-exports them for the HTTP
API.
"""

from __future__ import annotations

import time
from collections import deque
from typing import TYPE_CHECKING, Any, NamedTuple

from pydantic import BaseModel, Field

from cfsr_live.driver.source import CameraControl, ReplayControl
from cfsr_live.service.kernel_warmup import KernelStatus

if TYPE_CHECKING:
    from cfsr_live.driver.acquisition import Acquisition
    from cfsr_live.driver.source import Source, SourceCounters
    from cfsr_live.shm.ring import SpikeRing

__all__ = [
    "ClientDrops",
    "Drops",
    "HubStatus",
    "RateMeter",
    "RecordStatus",
    "ReplayState",
    "RingStatus",
    "SourceLosses",
    "SourceReport",
    "SourceStatus",
    "StatusModel",
    "WorkerReport",
    "WorkerStatus",
    "real_time_factor",
    "ring_status",
    "source_report",
]


class RateMeter:
    """Rate of a cumulative counter over the last ``window`` seconds, from samples.

    The counters (frames published, steps ingested) live in other threads and processes;
    sampling them on a clock (the runtime's sampler thread) gives a rate that neither
    depends on how often the status is asked for nor costs anything in the hot loops.
    """

    def __init__(self, window: float = 2.0) -> None:
        self.window = window
        self._s: deque[tuple[float, float]] = deque(maxlen=64)

    def add(self, value: float, t: float | None = None) -> None:
        """One sample of the counter (at monotonic time ``t``, default now)."""
        self._s.append((time.monotonic() if t is None else t, value))

    def rate(self) -> float:
        """Counter units per second over the window (0 with fewer than two samples)."""
        if len(self._s) < 2:
            return 0.0
        t1, v1 = self._s[-1]
        t0, v0 = self._s[0]
        for t, v in self._s:
            if t1 - t <= self.window:
                t0, v0 = t, v
                break
        return (v1 - v0) / (t1 - t0) if t1 > t0 else 0.0


def real_time_factor(steps_per_s: float, rate_hz: float) -> float:
    """Steps taken in per second over the sensor's steps per second (1: keeping up with the
    camera); 0 while the sensor rate is unknown (0)."""
    return steps_per_s / rate_hz if rate_hz else 0.0


# -- the source ---------------------------------------------------------------------------------
class ReplayState(BaseModel):
    playing: bool
    speed: float
    loop: bool
    position: int = Field(description="file frame of the next block")
    start: int
    end: int
    n_frames: int
    mode: str
    loops: int
    ended: bool
    rate_hz: float


class SourceStatus(BaseModel):
    id: str | None
    kind: str | None
    name: str | None
    state: str | None
    capabilities: list[str] = []
    width: int | None = None
    height: int | None = None
    rate_hz: float | None = None
    counters: dict[str, Any] = {}
    replay: ReplayState | None = None
    last_error: str | None = None


class SourceReport(BaseModel):
    """The source's report: its ``status`` section and the frames it lost (for ``drops``)."""

    status: SourceStatus
    link_lost_frames: int = Field(
        0, description="frames lost on the source's link to the host, a USB camera's or any "
        "other kind's (its counters' lost_frames)")
    replay_behind_frames: int = Field(0, description="frames a paced replay skipped")


class SourceLosses(NamedTuple):
    """Frames a source lost: on its link to the host (the status's ``drops.usb``) and skipped
    by a paced replay (``drops.replay``)."""

    link: int = 0
    paced: int = 0

    @classmethod
    def of(cls, counters: SourceCounters) -> SourceLosses:
        """The losses in a source's ``counters`` (a field the source lacks counts 0)."""
        return cls(counters.lost_frames or 0, counters.replay_behind_frames or 0)

    def plus(self, other: SourceLosses) -> SourceLosses:
        return SourceLosses(self.link + other.link, self.paced + other.paced)


def source_report(
    source_id: str | None, src: Source | None, acq: Acquisition | None, rate_hz: float
) -> SourceReport:
    """What the current source ``src`` and its acquisition thread ``acq`` report.

    ``counters`` are the source's own counters with the acquisition thread's on top (the
    shape ``GET /api/status`` always had); a camera adds its device status, or the error
    that reading it raised (the camera may be gone right now).
    """
    if src is None:
        status = SourceStatus(id=source_id, kind=None, name=None, state=None, rate_hz=rate_hz,
                              counters=acq.stats() if acq else {},
                              last_error=acq.last_error if acq else None)
        return SourceReport(status=status)
    own = src.counters()
    counters: dict[str, Any] = {**own.as_dict(), **(acq.stats() if acq else {})}
    cam = src.get_facility(CameraControl)
    if cam is not None:
        try:
            counters["device"] = cam.device_status()
        except Exception as exc:  # noqa: BLE001 - the camera may be gone right now
            counters["device"] = {"error": str(exc)}
    ctl = src.get_facility(ReplayControl)
    status = SourceStatus(
        id=source_id,
        kind=src.info.kind,
        name=src.info.name,
        state=src.state.value,
        capabilities=src.capabilities(),
        width=src.info.layout.width,
        height=src.info.layout.height,
        rate_hz=rate_hz,
        counters=counters,
        replay=None if ctl is None else ReplayState.model_validate(ctl.state()),
        last_error=src.last_error or (acq.last_error if acq else None),
    )
    link, paced = SourceLosses.of(own)
    return SourceReport(status=status, link_lost_frames=link, replay_behind_frames=paced)


# -- the ring -----------------------------------------------------------------------------------
class RingStatus(BaseModel):
    path: str | None = Field(description="the shared-memory file of the spike ring")
    slots: int = Field(description="blocks the ring holds")
    slot_frames: int = Field(description="frames per block")
    capacity_s: float = Field(description="seconds of sensor data the ring holds")
    frames_published: int = Field(description="frames written into this and earlier rings")
    blocking: bool = Field(description="the producer waits for the worker (replay mode "
                           "unpaced)")


def ring_status(ring: SpikeRing | None, frames_before: int, rate_hz: float) -> RingStatus:
    """The spike ring's report; ``frames_before`` counts frames published into earlier rings
    (a source of another geometry gets a new ring)."""
    if ring is None:
        return RingStatus(path=None, slots=0, slot_frames=0, capacity_s=0.0,
                          frames_published=0, blocking=False)
    return RingStatus(
        path=str(ring.path),
        slots=ring.n_slots,
        slot_frames=ring.slot_frames,
        capacity_s=ring.capacity_frames / rate_hz,
        frames_published=frames_before + ring.frames_published,
        blocking=bool(ring.blocking),
    )


# -- the worker ---------------------------------------------------------------------------------
class QualityShare(BaseModel):
    """CFSR's quality tiers in the live service: the mode and the frames shown at each."""

    mode: str | None = Field(
        None,
        description="auto (full when the frame rate allows it, fast frames between), full or "
        "fast; None for a method without tiers",
    )
    shown: str | None = Field(
        None, description="the tier that made the frame shown last (full or fast; None before "
        "one of the current method, or for a method without tiers)")
    full: int = Field(0, description="frames shown at full quality in the last 10 s under the "
                      "current config (every frame of a method without tiers)")
    fast: int = Field(0, description="frames shown at the fast tier in the last 10 s under the "
                      "current config")


class CompileProgress(BaseModel):
    """The compile the chosen method's first frame waits on, as its pool process reports
    it each second (its compile heartbeat)."""

    method: str = Field(description="the method whose kernels compile")
    kernel: str | None = Field(
        None, description="the kernel compiling now (module.function), or waited for while "
        "another process compiles it"
    )
    waiting: bool = Field(False, description="waiting for another process's compile of it")
    kernels: int = Field(0, description="kernels compiled or loaded so far")
    total: int | None = Field(
        None, description="kernels the method compiles on an empty cache (measured table)"
    )
    cpu_s: float = Field(0.0, description="CPU seconds the process spent on it so far")
    estimate_s: float | None = Field(
        None, description="CPU seconds the whole method took to compile when measured"
    )


class DefectMapStatus(BaseModel):
    """The hot/dead pixel map the worker corrects every method's spikes with (cfsr.defects)."""

    state: str = Field("off", description="off (no correction), learning (from the stream, "
                       "before its warm-up of 2,000 steps), ready, or given (from outside)")
    hot: int = Field(0, description="pixels called hot: each takes a neighbour's spikes")
    dead: int = Field(0, description="pixels called dead: each takes a neighbour's spikes")
    confidence: float = Field(0.0, description="steps counted over the warm-up (0..1)")
    gain: bool = Field(False, description="a flat-field calibration's per-pixel gain "
                       "(threshold spread) is divided out of every method's output")


class WorkerStatus(BaseModel):
    alive: bool
    ready: bool
    pid: int | None
    restarts: int
    crashes: list[dict[str, Any]]
    last_errors: list[dict[str, Any]]
    config_version: int
    applied_version: int
    heartbeat_age_s: float | None
    first_frame_s: float | None = Field(
        None,
        description="seconds the first frame under the current config has been computing "
        "(None: none pending); on a machine's first use it waits on numba's compiler",
    )
    steps_per_s: float
    real_time_factor: float
    frames_out: int
    gaps: int
    workers: int = Field(1, description="reconstruction processes: frames computed at once")
    threads_per_worker: int = Field(1, description="numba/OpenCV threads in each process")
    quality: QualityShare = Field(default_factory=QualityShare)
    dropped_late: int = Field(
        0,
        description="frames computed but not shown: a newer frame was computing and their "
        "spikes arrived longer ago than twice what a frame takes at the rate the machine holds "
        "(at least a second), or their config was replaced (no spike data lost)",
    )
    dropped_order: int = Field(
        0,
        description="frames computed but not shown: a newer step was shown first (no spike "
        "data lost)",
    )
    fallback_method: str | None = Field(
        None,
        description="while the first frame under the config waits on the compiler, the "
        "method whose frames are shown instead: TFP at once, then CSR (for CFSR) as soon as "
        "its kernels are ready",
    )
    compiling: CompileProgress | None = Field(
        None, description="the compile the first frame under the config waits on, if any"
    )
    fallback_frames: int = Field(0, description="frames of the fallback method shown so far")
    reconstruction_nice: int = Field(
        0,
        description="nice value the reconstruction pool computes frames at: above the "
        "acquisition's (0) once every kernel is cached and loaded, so a busy machine takes CPU "
        "from frames, not from spike data (compiles run at 0: they are what a user waits for)",
    )
    defects: DefectMapStatus = Field(default_factory=DefectMapStatus,
                                     description="the hot/dead pixel map and its state")


class WorkerReport(BaseModel):
    """The supervisor's report: the ``worker`` section and the pipeline figures the worker
    measures, shown at the top level (latency, compute time) and in ``drops``."""

    status: WorkerStatus
    latency_ms: float = Field(0.0, description="newest spike used -> frame published (EMA)")
    compute_ms: float = Field(0.0, description="reconstruction time per frame (EMA)")
    ring_lost_frames: int = Field(
        0, description="frames the ring overwrote before the worker read them: skipped by the "
        "display, not lost (the recorder reads the ring on its own)")
    skipped_frames: int = Field(0, description="frames the worker skipped to show the newest")

    @classmethod
    def absent(cls) -> WorkerReport:
        """The report while no worker exists (before start, after a failed start)."""
        return cls(status=WorkerStatus(
            alive=False, ready=False, pid=None, restarts=0, crashes=[], last_errors=[],
            config_version=0, applied_version=-1, heartbeat_age_s=None, steps_per_s=0.0,
            real_time_factor=0.0, frames_out=0, gaps=0,
        ))


# -- the hub and its clients --------------------------------------------------------------------
class ClientDrops(BaseModel):
    id: int
    kind: str
    peer: str
    sent: int
    dropped: int
    pending: int
    max_fps: float | None
    connected_s: float


class HubStatus(BaseModel):
    """The frame hub's report: the rate and newest frame it fans out, and its clients."""

    output_fps: float = 0.0
    frame_step: int | None = None
    clients: list[ClientDrops] = []
    client_drops: int = Field(0, description="frames replaced unsent, gone clients included")


# -- the recorder -------------------------------------------------------------------------------
class RecordStatus(BaseModel):
    recording: bool
    path: str | None = None
    name: str | None = None
    frames: int = 0
    bytes: int = 0
    elapsed_s: float = 0.0
    lost_frames: int = 0
    error: str | None = None
    max_bytes: int | None = None
    stop_reason: str | None = Field(
        None, description="why it stopped: stopped, max_frames reached, size cap reached, "
        "disk nearly full, error"
    )


# -- the whole ----------------------------------------------------------------------------------
class Drops(BaseModel):
    usb: int = Field(0, description="frames lost on the USB link (index gaps, bad blocks)")
    replay: int = Field(0, description="frames a paced replay skipped to stay on schedule")
    ring: int = Field(0, description="frames the display skipped because the ring overran the "
                      "worker (spike data is not lost: the recorder reads the ring on its own)")
    worker: int = Field(0, description="frames the worker skipped to show the newest data")
    clients: int = Field(0, description="frames replaced before a client could receive them")
    recorder: int = Field(0, description="frames the current/last recording lost")
    per_client: list[ClientDrops] = []


class StatusModel(BaseModel):
    uptime_s: float
    source: SourceStatus
    method: str
    params: dict[str, Any]
    input_steps_per_s: float = Field(description="steps/s entering the ring from the source")
    real_time_factor: float = Field(description="input steps/s divided by the sensor rate")
    output_fps: float = Field(description="reconstructed frames/s published by the worker")
    latency_ms: float = Field(description="newest spike used -> frame published (EMA)")
    compute_ms: float = Field(description="reconstruction time per frame (EMA)")
    frame_step: int | None = Field(None, description="step index of the newest frame")
    drops: Drops
    worker: WorkerStatus
    ring: RingStatus
    clients: int
    recording: RecordStatus
    kernels: KernelStatus = Field(
        default_factory=KernelStatus,
        description="the background compilation of the reconstruction kernels on a first start",
    )
