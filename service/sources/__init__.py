"""The source registry: every kind of spike source the service and ``cfsr record`` can open.

A *kind* (the USB camera, a replayed recording, the demo, the simulator, a third party's
camera) is one :class:`SourceKind` object that owns everything about it outside the driver:

* its command-line flags (:meth:`SourceKind.add_arguments`, :meth:`SourceKind.spec_from_args`),
  for ``cfsr serve`` and ``cfsr record``;
* its entries in the viewer's source menu, ``GET /api/sources``
  (:meth:`SourceKind.entries`, :meth:`SourceKind.entry`, :meth:`SourceKind.spec_for`);
* opening it (:meth:`SourceKind.open`), which returns a
  :class:`cfsr_live.driver.source.Source` whose ``info.kind`` is the kind's name (the one
  name of a kind: the status and a recording's sidecar show it).

What a source lost is in its own typed counters
(:class:`cfsr_live.driver.source.SourceCounters`), not in the kind: the status page's
``drops`` read them whatever the kind.

Kinds are found through the entry-point group :data:`ENTRY_POINT_GROUP` (``cfsr.sources``),
the way commands join the CLI through ``cfsr.commands``: the built-in kinds are declared in
this distribution's ``pyproject.toml``, and a camera package declares its own in its
``pyproject.toml``; nothing else in the service names a kind. The model is OpenEB's device
discovery: list what can be opened, then open one by its id.

:func:`register` adds a kind at run time (tests, embedding applications); a name registered
twice is an error, as for methods.
"""

from __future__ import annotations

import argparse
import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cfsr_live.service.settings import SourceSpec, cache_dir

if TYPE_CHECKING:
    from cfsr_live.driver.source import Source
    from cfsr_live.service.catalog import CatalogEntry, SourceCatalog
    from cfsr_live.service.settings import Settings

__all__ = [
    "ENTRY_POINT_GROUP",
    "OpenOptions",
    "SourceKind",
    "get",
    "kinds",
    "register",
    "unregister",
]

log = logging.getLogger("cfsr.sources")

#: entry-point group through which kinds of source are found (name = the kind's name, value =
#: a :class:`SourceKind` subclass or instance)
ENTRY_POINT_GROUP = "cfsr.sources"


@dataclass(frozen=True)
class OpenOptions:
    """How the opening command wants a source delivered. ``None`` leaves the device's own
    default (``cfsr record`` sets only what it needs; ``cfsr serve`` sets everything from its
    :class:`~cfsr_live.service.settings.Settings`)."""

    #: replay speed, x real time (1 = the sensor's 40,000 steps/s)
    speed: float | None = None
    #: start again at the end of a recording
    loop: bool | None = None
    #: a recording's replay pacing (:class:`~cfsr_live.driver.source.ReplayMode`): ``paced``
    #: (real-time schedule, late frames skipped) or ``unpaced`` (as fast as the consumer
    #: reads, nothing skipped); ``cfsr serve --replay-mode``
    mode: str | None = None
    #: the consumer is a writer (``cfsr record``): every kind delivers as fast as it is read
    #: and skips nothing, the simulator too (which ``mode`` leaves paced: it stands for a
    #: live camera in the viewer)
    unpaced: bool = False
    #: frames per block a replay delivers
    block_frames: int | None = None
    #: folder for generated data (the simulator's scenes); None: generate each time
    cache_dir: Path | None = None
    #: steps of the built-in demo recording (1 step = 25 us)
    demo_steps: int | None = None
    #: where a kind reports slow preparations (the demo's first simulation)
    say: Callable[[str], None] | None = None

    @classmethod
    def from_settings(cls, settings: Settings, say: Callable[[str], None] | None = None
                      ) -> OpenOptions:
        return cls(speed=settings.speed, loop=settings.loop, mode=settings.replay_mode,
                   block_frames=settings.block_frames, cache_dir=cache_dir(),
                   demo_steps=settings.demo_steps, say=say)

    def given(self, *names: str) -> dict[str, Any]:
        """The fields ``names`` that are set, as keyword arguments for a device."""
        return {n: getattr(self, n) for n in names if getattr(self, n) is not None}


class SourceKind:
    """One kind of source. Subclass it, set :attr:`name`, override what the kind has.

    Every method has a default that does nothing (no flags, no entries), so a kind states only
    what it offers; :meth:`open` is the one method every kind must have.
    """

    #: the kind's name: ``SourceSpec.kind`` and the entry point's name
    name: str = ""
    #: one line shown in ``cfsr serve --help`` and the docs
    summary: str = ""
    #: where the kind's entries stand in ``GET /api/sources`` (lower first)
    order: int = 100

    # -- command line ---------------------------------------------------------------------------
    def add_select_argument(self, select: argparse._MutuallyExclusiveGroup,
                            command: str) -> None:
        """Add the flag that picks this kind in ``command`` (``serve`` or ``record``) to
        ``select``, the group that lets one source be named per command line."""

    def add_arguments(self, parser: argparse.ArgumentParser, command: str) -> None:
        """Add the kind's own options (applied with its flag) to ``command``'s parser."""

    def spec_from_args(self, args: argparse.Namespace) -> SourceSpec | None:
        """The spec the command line asks for when it picks this kind, else None. Called for
        every kind: raise ValueError for this kind's options given without its flag."""
        return None

    # -- the listing ----------------------------------------------------------------------------
    def entries(self, catalog: SourceCatalog) -> Iterable[CatalogEntry]:
        """The kind's entries in the listing (``GET /api/sources``), in order."""
        return ()

    def entry(self, catalog: SourceCatalog, source_id: str) -> CatalogEntry | None:
        """The listing's entry ``source_id`` if this kind has it, else None. Override it to
        find one entry without listing them all (a switch must not scan a data folder)."""
        return next((e for e in self.entries(catalog) if e.id == source_id), None)

    def spec_for(self, catalog: SourceCatalog, entry: CatalogEntry) -> SourceSpec:
        """What to open for the (usable) listing entry ``entry``."""
        return SourceSpec(kind=self.name)

    def cli_entry(self, catalog: SourceCatalog, spec: SourceSpec) -> CatalogEntry | None:
        """An entry for the source named on the command line, when the listing would not
        have it otherwise (a recording outside the data folder)."""
        return None

    def spec_id(self, spec: SourceSpec) -> str:
        """The listing id of ``spec`` (the source the command line opened is shown as
        current in the listing when the ids agree)."""
        return self.name

    # -- opening --------------------------------------------------------------------------------
    def check_installed(self) -> None:
        """Raise (``cfsr.cli._extras.MissingExtra``) when an optional dependency the kind
        needs is missing; ``cfsr record`` calls it before opening."""

    def prepare(self, spec: SourceSpec, options: OpenOptions) -> None:
        """Slow work before the first open that the user should hear about (``cfsr serve``
        calls it before the service starts)."""

    def open(self, spec: SourceSpec, options: OpenOptions) -> Source:
        """A new, not yet opened :class:`~cfsr_live.driver.source.Source` for ``spec``; raise
        ValueError, OSError or ``SourceError`` with a clear message when it cannot be made."""
        raise NotImplementedError(f"source kind {self.name!r} cannot open sources")

    def __repr__(self) -> str:
        return f"<source kind {self.name!r}>"


_KINDS: dict[str, SourceKind] = {}
_loaded = False
_LOAD_LOCK = threading.Lock()


def _instance(obj: Any) -> SourceKind:
    kind = obj() if isinstance(obj, type) else obj
    if not isinstance(kind, SourceKind) or not kind.name:
        raise TypeError(f"{obj!r} is not a named SourceKind")
    return kind


def register(kind: SourceKind | type[SourceKind]) -> SourceKind:
    """Add ``kind`` (a :class:`SourceKind` or subclass); ValueError if its name is taken."""
    k = _instance(kind)
    _load()
    if k.name in _KINDS:
        raise ValueError(f"source kind {k.name!r} registered twice")
    _KINDS[k.name] = k
    return k


def unregister(name: str) -> None:
    """Remove kind ``name`` (tests)."""
    _KINDS.pop(name, None)


def _load() -> None:
    """Register the kinds of the entry-point group, once. A plugin that fails to load is
    logged and skipped: a broken camera package must not take the service down."""
    global _loaded
    if _loaded:
        return
    with _LOAD_LOCK:  # the API's worker threads may ask first: none sees a half-filled table
        if not _loaded:
            _load_entry_points()
            _loaded = True


def _load_entry_points() -> None:
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in _KINDS:
            continue  # one distribution seen twice (an editable install beside a wheel)
        try:
            k = _instance(ep.load())
        except Exception as exc:  # noqa: BLE001 - any plugin error: skip that kind, say why
            log.warning("source kind %r (%s) not loaded: %s", ep.name, ep.value, exc)
            continue
        if k.name != ep.name:
            log.warning("source kind %r: entry point %r names it differently; not loaded",
                        k.name, ep.name)
            continue
        _KINDS[k.name] = k


def kinds() -> list[SourceKind]:
    """Every registered kind, in listing order."""
    _load()
    return sorted(_KINDS.values(), key=lambda k: (k.order, k.name))


def get(name: str) -> SourceKind:
    """The kind ``name``; ValueError naming the known ones if there is none."""
    _load()
    try:
        return _KINDS[name]
    except KeyError:
        raise ValueError(
            f"unknown source kind {name!r}; known: {', '.join(sorted(_KINDS)) or 'none'}"
        ) from None
