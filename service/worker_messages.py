"""The messages between the web process's :class:`~cfsr_live.service.supervisor.WorkerSupervisor`
and the worker process (:mod:`cfsr_live.service.worker_loop`).

Everything that crosses the process boundary is a small frozen dataclass (pickled by the
queues): commands :class:`Configure`, :class:`Attach`, :class:`Inject`, :class:`Stop` to the
worker; events :class:`Ready`, :class:`ConfigAnswer`, :class:`WorkerError` (a failed frame,
or a fatal error), :class:`Compiling` and :class:`DefectMapFound` back. A
:class:`~cfsr_live.service.config.WorkerConfig` was validated where it was made (in the web
process) and is applied as is. This module imports nothing of the reconstruction, so the web
process can use it without the worker's imports.
"""

from __future__ import annotations

import traceback
from dataclasses import dataclass
from typing import Literal, NamedTuple

from cfsr.layout import Layout
from cfsr_live.service.config import WorkerConfig
from cfsr_live.service.status import CompileProgress

__all__ = [
    "RUNG_CODES",
    "RUNG_NAMES",
    "Attach",
    "Compiling",
    "ConfigAck",
    "ConfigAnswer",
    "Configure",
    "DefectMapFound",
    "Inject",
    "Ready",
    "HoldStep",
    "Stop",
    "Viewers",
    "WorkerError",
]

#: the ``fallback`` counter's values (in the shared counters): which rung of the ladder stands
#: in while a first frame compiles
RUNG_CODES = {"tfp": 1, "csr": 2}
RUNG_NAMES = {v: k for k, v in RUNG_CODES.items()}


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
class Viewers:
    """How many clients watch the frames (WebSocket, MJPEG): with none the worker computes
    :data:`~cfsr_live.service.frame_worker.UNWATCHED_FPS` frames a second (enough for
    ``/readyz`` and ``/metrics``) instead of ``max_fps``."""

    count: int


@dataclass(frozen=True)
class HoldStep:
    """Compute frames at ``step`` instead of the newest one while the buffer still holds its
    window (a paused replay's compare: the chosen method on the pinned step, whichever method
    looks further ahead); None: the newest again."""

    step: int | None


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


@dataclass(frozen=True)
class DefectMapFound:
    """The hot/dead pixel map the worker corrects with changed: ``map`` in its JSON form
    (:meth:`cfsr.defects.DefectMap.to_dict`), which a recording keeps in its sidecar."""

    map: dict


class ConfigAck(NamedTuple):
    """:meth:`WorkerSupervisor.wait_config`'s answer (a tuple: ``state, reason = ...``)."""

    state: Literal["applied", "rejected", "pending"]
    reason: str | None = None
