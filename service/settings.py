"""Settings of the live service (one object, built by ``cfsr serve`` or by tests)."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cfsr.datfile import MIN_GAIN
from cfsr_live.driver.source import ReplayMode
from cfsr_live.service.body import BODY_TIMEOUT_S

if TYPE_CHECKING:
    from cfsr_live.service.config import Quality

#: open connections (HTTP and WebSocket) at most, by default (service/httpproto.py lowers it
#: under the open-file limit); here so that the parser of `cfsr serve` needs no uvicorn
DEFAULT_MAX_CONNECTIONS = 1000

#: frames per second the worker (or one client) may ask for: below 0.1 a viewer would wait
#: minutes for a frame
MAX_FPS_RANGE = (0.1, 240.0)
#: seconds of sensor data the shared ring may hold (1 s of a 400 x 250 camera is 500 MB)
RING_SECONDS_RANGE = (0.01, 10.0)
#: the shared ring's size cap in MiB (``cfsr serve --ring-max-mb``): the ring holds
#: ``ring_seconds`` of the source or what fits under the cap, whichever is less. The smallest
#: cap still holds 8 blocks of the largest displayable frame (8 x 256 x 128 KiB)
RING_MAX_MB_RANGE = (256, 65536)
#: a recording's file name (without folder; ``.dat`` is added): a letter or digit first, then
#: letters, digits, ``.``, ``_``, ``-``; at most 64 characters, so never a path or a hidden file
RECORDING_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
RECORDING_NAME_RE = re.compile(RECORDING_NAME_PATTERN)
#: most pixels (width x height) of a source: what the display's frame slot holds. The one
#: geometry limit of the live service: the slot is made this size, the listing notes a
#: recording over it, and a switch to one is refused (422) naming both numbers
MAX_DISPLAY_PIXELS = 1 << 20
#: smallest display gain (spikes/step shown as white): one spike per million steps (25 s);
#: below, 1/gain overflows the frame header's float32. The same bound as a sidecar's gain
#: (one owner: :data:`cfsr.datfile.MIN_GAIN`)
MIN_DISPLAY_GAIN = MIN_GAIN

__all__ = [
    "MAX_DISPLAY_PIXELS",
    "MAX_FPS_RANGE",
    "MIN_DISPLAY_GAIN",
    "RECORDING_NAME_PATTERN",
    "RECORDING_NAME_RE",
    "RING_MAX_MB_RANGE",
    "RING_SECONDS_RANGE",
    "Settings",
    "SourceSpec",
    "cache_dir",
    "default_data_dir",
    "is_loopback",
]


def _httpproto() -> Any:
    # deferred: the parser of `cfsr serve` needs no uvicorn
    from cfsr_live.service import httpproto

    return httpproto


def _default_workers() -> int:
    """One single-threaded reconstruction process per usable core (measured: on 2 cores two
    processes of one thread give 2-3x the frames of one process of two threads)."""
    # deferred: cfsr.pool (multiprocessing) loads only when the workers are not given
    from cfsr.pool import default_workers

    return default_workers(1)


def _timeout_s(var: str, default: float) -> float:
    """Seconds from environment variable ``var`` (tests that wait a timeout out lower it),
    else ``default``; a value that is not a number of seconds in (0, 3600] is refused."""
    text = os.environ.get(var)
    if text is None:
        return default
    value = float(text)
    if not 0 < value <= 3600:  # NaN fails too
        raise ValueError(f"{var}={text!r}: seconds in (0, 3600] expected")
    return value


def cache_dir() -> Path:
    """``$CFSR_CACHE_DIR``, else ``$XDG_CACHE_HOME/cfsr``, else ``~/.cache/cfsr``."""
    env = os.environ.get("CFSR_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "cfsr"


def default_data_dir() -> Path:
    """``$CFSR_DATA_DIR``, else ``$XDG_DATA_HOME/cfsr``, else ``~/.local/share/cfsr``."""
    env = os.environ.get("CFSR_DATA_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_DATA_HOME")
    return (Path(xdg) if xdg else Path.home() / ".local" / "share") / "cfsr"


def is_loopback(host: str) -> bool:
    import ipaddress

    if host in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass
class SourceSpec:
    """What to open: a source kind's name (``demo``, ``replay``, ``usb``, ``sim``, or one a
    package registers: :mod:`cfsr_live.service.sources`), the file it reads (``path``, for
    kinds that read one) and the kind's own ``options`` (the USB camera's ``vid``/``pid``, the
    simulator's ``scene``). Only the kind reads ``options``."""

    kind: str = "demo"
    path: Path | None = None
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def id(self) -> str:
        """The listing id of this source (``GET /api/sources``), as its kind names it."""
        # deferred: a cycle (cfsr_live.service.sources imports SourceSpec from here)
        from cfsr_live.service.sources import get

        return get(self.kind).spec_id(self)


@dataclass
class Settings:
    host: str = "127.0.0.1"
    port: int = 8000
    token: str | None = None
    data_dir: Path = field(default_factory=default_data_dir)
    source: SourceSpec = field(default_factory=SourceSpec)
    speed: float = 1.0
    loop: bool = True
    #: a recording's pacing: ``paced``, or ``unpaced``: deterministic, as fast as the worker
    #: consumes (a name is made a :class:`~cfsr_live.driver.source.ReplayMode` at once)
    replay_mode: ReplayMode = ReplayMode.PACED
    block_frames: int = 256
    ring_seconds: float = 0.25
    #: the ring's size cap, bytes (default :data:`cfsr_live.shm.ring.DEFAULT_MAX_BYTES`, 1 GiB)
    ring_max_bytes: int = 1 << 30
    method: str = "tfp"
    #: the method's parameters (CFSR's tier is not one of them: ``quality`` below)
    params: dict = field(default_factory=dict)
    max_fps: float = 30.0
    #: CFSR's live tier (``cfsr serve --quality``): auto, full or fast
    quality: Quality = "auto"
    #: reconstruction processes and numba/OpenCV threads in each (``cfsr serve --workers``,
    #: ``--threads``): frames computed at once; default: one single-threaded process per core
    workers: int = field(default_factory=lambda: _default_workers())
    threads: int = 1
    worker_hang_timeout: float = 120.0
    viewer_dir: Path | None = None
    test_hooks: bool = False  # expose POST /api/debug/* (tests only)
    #: extra Host names (besides loopback and the bound address) the service answers to
    allowed_hosts: list[str] = field(default_factory=list)
    #: extra browser origins (besides the service's own) allowed to open /ws or change state
    allowed_origins: list[str] = field(default_factory=list)
    #: addresses of reverse proxies whose X-Forwarded-For / X-Forwarded-Proto are believed
    #: (``cfsr serve --trusted-proxy``); none by default: the peer address is the client, so a
    #: header cannot pick its throttle slot or the address shown in the status
    trusted_proxies: list[str] = field(default_factory=list)
    #: open connections at most (``cfsr serve --max-connections``), lowered below the open-file
    #: limit at start (:func:`cfsr_live.service.httpproto.connection_cap`)
    max_connections: int = 1000
    demo_steps: int = int(os.environ.get("CFSR_DEMO_STEPS", "6000"))
    #: seconds a client has to complete a request head (service/httpproto.py), then its body
    #: (service/body.py, 408 after); ``CFSR_HEADER_TIMEOUT_S`` / ``CFSR_BODY_TIMEOUT_S``
    header_timeout_s: float = field(default_factory=lambda: _timeout_s(
        "CFSR_HEADER_TIMEOUT_S", _httpproto().HEADER_TIMEOUT_S))
    body_timeout_s: float = field(default_factory=lambda: _timeout_s(
        "CFSR_BODY_TIMEOUT_S", BODY_TIMEOUT_S))
    #: compile every method's kernels in a background process when they are not cached yet
    #: (``cfsr serve`` turns it on unless ``--no-warmup``; service.kernel_warmup)
    warmup: bool = False

    def __post_init__(self) -> None:
        self.data_dir = Path(self.data_dir).expanduser()
        self.replay_mode = ReplayMode.of(self.replay_mode)
        if self.token is not None and not self.token.strip():
            # a token of blanks is one an attacker guesses first (and "--token ' '" is a
            # slip, not a choice): refused on every bind, not only where one is required
            raise ValueError("the access token is blank (--token or CFSR_TOKEN): give a real "
                             "one, or none on a loopback address")
        if not is_loopback(self.host) and not self.token:
            raise ValueError(
                f"binding to {self.host} (not loopback) requires an access token "
                "(--token or CFSR_TOKEN)"
            )
