"""One interface for every spike source: the USB camera, the replay device and the simulator.

A :class:`Source` delivers *blocks* of packed frames (the ``.dat`` byte layout, see
:class:`cfsr.layout.Layout`) with the 64-bit index of the first frame. The index is the
source's step clock (1 step = 25 us at 40 kHz): consecutive blocks are contiguous unless frames
were lost (then the index jumps and the gap is the loss) or the content jumped on purpose
(a replay seek; flagged :attr:`BlockFlags.DISCONTINUITY`).

Optional features are *facilities* (OpenEB style): ``source.get_facility(ReplayControl)``
returns the facility or ``None`` when the source lacks it, so callers must check::

    ctl = source.get_facility(ReplayControl)
    if ctl is None:
        ...  # a live camera cannot seek
    else:
        ctl.seek(1000)
"""

from __future__ import annotations

import abc
import enum
import time
import warnings
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar

import numpy as np

from cfsr.layout import STEP_RATE_HZ, Layout

__all__ = [
    "Block",
    "BlockFlags",
    "CameraControl",
    "Facility",
    "ReplayControl",
    "ReplayMode",
    "Source",
    "SourceDisconnected",
    "SourceEnded",
    "SourceError",
    "SourceInfo",
    "SourceCounters",
    "SourceState",
]


class SourceError(RuntimeError):
    """A source cannot deliver data as asked (bad configuration, device refused, ...)."""


class SourceDisconnected(SourceError):
    """The device went away (USB errno 19 / 5). Sources that reconnect handle this inside."""


class SourceEnded(SourceError):
    """A finite source (non-looping replay) has delivered its last frame."""


class BlockFlags(enum.IntFlag):
    NONE = 0
    #: The content does not continue the previous block (seek, new session, reconnect).
    DISCONTINUITY = 1
    #: Frames were lost just before this block (index gap); ``Block.lost_before`` says how many.
    LOSS = 2
    #: Last block of a finite stream.
    END = 4


class SourceState(enum.StrEnum):
    CLOSED = "closed"
    OPENING = "opening"
    STREAMING = "streaming"
    PAUSED = "paused"
    DISCONNECTED = "disconnected"
    BACKOFF = "backoff"
    ENDED = "ended"
    ERROR = "error"


@dataclass(frozen=True)
class SourceInfo:
    """What a source is: its kind, geometry and rate.

    ``kind`` is the name the source registry (``cfsr_live.service.sources``, entry-point group
    ``cfsr.sources``) knows the kind by: ``usb``, ``replay``, ``demo``, ``sim``, or a camera
    package's own. The status and a recording's sidecar show this name, so it is the one
    vocabulary of kinds.
    """

    kind: str
    name: str
    layout: Layout
    rate_hz: float = float(STEP_RATE_HZ)
    max_block_frames: int = 256
    serial: str | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "name": self.name,
            "width": self.layout.width,
            "height": self.layout.height,
            "frame_bytes": self.layout.frame_bytes,
            "rate_hz": self.rate_hz,
            "max_block_frames": self.max_block_frames,
            "serial": self.serial,
        }


@dataclass(frozen=True)
class SourceCounters:
    """What a source counted since it was made, in frames (a snapshot: :meth:`Source.counters`
    makes a new one each call, so a reader in another thread sees figures of one moment).

    A field is ``None`` where the source lacks what it counts: a file has no link to lose
    frames on, a camera is never paced by the host. The status's ``drops`` read the two
    loss fields, whatever the kind. A source with more to count subclasses this record (a
    frozen dataclass with fields of its own, all with defaults): the USB camera's
    :class:`cfsr_live.driver.usb.UsbCounters` adds its link's events.
    """

    #: frames handed to the reader
    frames_delivered: int = 0
    #: frames lost on the link before they reached the host (index gaps in the headers): the
    #: status's ``drops.usb``
    lost_frames: int | None = None
    #: frames a paced replay skipped to stay on schedule: the status's ``drops.replay``
    replay_behind_frames: int | None = None
    #: times a looping replay started again
    loops: int | None = None

    def as_dict(self) -> dict[str, int]:
        """The fields the source has (not ``None``), by name: the status's
        ``source.counters``."""
        return {f.name: v for f in fields(self) if (v := getattr(self, f.name)) is not None}


@dataclass
class Block:
    """A block of packed frames.

    Attributes
    ----------
    index : int
        Step index of ``data[0]`` (64-bit, the source's clock).
    data : ndarray, shape (n, frame_bytes), uint8
        Packed frames; a view valid until the next ``read_block`` call.
    flags : BlockFlags
    lost_before : int
        Frames the source knows were lost between the previous block and this one.
    t_host : float
        ``time.monotonic()`` when the block was received.
    """

    index: int
    data: np.ndarray
    flags: BlockFlags = BlockFlags.NONE
    lost_before: int = 0
    t_host: float = field(default_factory=time.monotonic)

    @property
    def n_frames(self) -> int:
        return int(self.data.shape[0])


class Facility(abc.ABC):
    """Base class of optional source features (see :meth:`Source.get_facility`).

    An abstract base class, so that a facility missing one of its interface's methods fails
    when it is made (TypeError), not when a caller first needs that method. Each interface
    names itself (a class attribute ``name``, the word :meth:`Source.capabilities` lists).
    """

    @property
    @abc.abstractmethod
    def name(self) -> str:
        """The capability's name, e.g. ``"replay"``."""


class ReplayControl(Facility):
    """Transport controls of a recorded or synthetic source (not available on a camera)."""

    name = "replay"

    @abc.abstractmethod
    def play(self) -> None: ...

    @abc.abstractmethod
    def pause(self) -> None: ...

    @abc.abstractmethod
    def step(self, n: int = 1) -> None:
        """While paused, deliver the next ``n`` frames."""

    @abc.abstractmethod
    def seek(self, frame: int) -> None:
        """Jump to file frame ``frame`` (O(1))."""

    @abc.abstractmethod
    def state(self) -> dict[str, Any]:
        """``playing, speed, loop, position, n_frames, mode``."""

    @abc.abstractmethod
    def set_speed(self, speed: float) -> None: ...

    @abc.abstractmethod
    def set_loop(self, loop: bool) -> None: ...


class ReplayMode(enum.StrEnum):
    """How a replayed or generated source delivers its frames (``ReplayControl.state()``'s
    ``mode``, ``cfsr serve --replay-mode``)."""

    #: on the sensor's schedule (25 us a step over the speed); a reader that falls behind
    #: loses frames, counted as ``replay_behind_frames``, as a camera's overflowing FIFO would
    PACED = "paced"
    #: as fast as the reader reads, nothing skipped (tests, re-recording): deterministic
    UNPACED = "unpaced"

    @classmethod
    def of(cls, value: str) -> ReplayMode:
        """The mode named ``value``; ``fast``, its former name, still works with a
        DeprecationWarning (it read like CFSR's fast tier). ValueError naming the modes."""
        if value == "fast":
            warnings.warn("replay mode 'fast' is now named 'unpaced'", DeprecationWarning,
                          stacklevel=3)
            return cls.UNPACED
        try:
            return cls(value)
        except ValueError:
            raise ValueError(f"replay mode must be 'paced' or 'unpaced', got {value!r}") from None


class CameraControl(Facility):
    """Controls only a live camera has (device info, stream start/stop, device counters)."""

    name = "camera"

    @abc.abstractmethod
    def device_info(self) -> dict[str, Any]: ...

    @abc.abstractmethod
    def device_status(self) -> dict[str, Any]: ...


F = TypeVar("F", bound=Facility)


class Source(abc.ABC):
    """A stream of packed spike frames.

    Subclasses implement :meth:`open`, :meth:`close`, :meth:`read_block` and declare their
    facilities in ``self._facilities``.
    """

    info: SourceInfo

    def __init__(self) -> None:
        self._facilities: dict[type[Facility], Facility] = {}
        self.state = SourceState.CLOSED
        self.last_error: str | None = None

    # -- lifecycle ----------------------------------------------------------------------
    @abc.abstractmethod
    def open(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def read_block(self, timeout: float = 0.5) -> Block | None:
        """The next block, or ``None`` if none arrived within ``timeout`` seconds.

        Raises :class:`SourceEnded` after the last block of a finite source.
        """

    # -- capability discovery -------------------------------------------------------------
    def get_facility(self, kind: type[F]) -> F | None:
        """The facility of type ``kind`` or ``None`` when this source has none."""
        for cls, fac in self._facilities.items():
            if issubclass(cls, kind):
                return fac  # type: ignore[return-value]
        return None

    def capabilities(self) -> list[str]:
        return sorted(f.name for f in self._facilities.values())

    def counters(self) -> SourceCounters:
        """What the source counted so far (frames delivered, lost, skipped; a subclass of
        :class:`SourceCounters` adds its own events)."""
        return SourceCounters()

    def describe(self) -> dict[str, Any]:
        d = self.info.to_dict()
        d["state"] = self.state.value
        d["capabilities"] = self.capabilities()
        d["counters"] = self.counters().as_dict()
        d["last_error"] = self.last_error
        return d

    def __enter__(self) -> Source:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
