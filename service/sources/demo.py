"""The built-in demo: a simulated recording of a moving disk, made on first use and cached,
replayed like a recording. ``cfsr serve`` opens it when no source is named."""

from __future__ import annotations

import logging

from cfsr_live.driver.source import ReplayMode, Source
from cfsr_live.replay.device import ReplayDevice
from cfsr_live.service import demo as demo_file  # read at call time (tests stand one in)
from cfsr_live.service.catalog import CatalogEntry, SourceCatalog
from cfsr_live.service.settings import Settings, SourceSpec
from cfsr_live.service.sources import OpenOptions, SourceKind

__all__ = ["DemoKind"]

log = logging.getLogger("cfsr.sources")

NAME = "built-in demo (simulated disk)"


def _steps(options: OpenOptions) -> int:
    """Steps of the demo recording (1 step = 25 us): the options', else the settings' default
    (``$CFSR_DEMO_STEPS``)."""
    return options.demo_steps if options.demo_steps is not None else Settings.demo_steps


class DemoKind(SourceKind):
    name = "demo"
    summary = "the built-in demo recording (simulated on first use, then cached)"
    order = 0

    def entries(self, catalog: SourceCatalog) -> list[CatalogEntry]:
        dp = demo_file.demo_path(catalog.settings.demo_steps)
        demo = CatalogEntry(id="demo", kind="demo", name=NAME)
        if dp.exists():
            demo = catalog.describe_file(dp, "demo", "demo") or demo
            demo.name = NAME
        else:
            demo.note = "simulated on first use"
        return [demo]

    def prepare(self, spec: SourceSpec, options: OpenOptions) -> None:
        demo_file.ensure_demo(_steps(options), say=options.say or (lambda m: None))

    def open(self, spec: SourceSpec, options: OpenOptions) -> Source:
        path = demo_file.ensure_demo(_steps(options),
                                     say=options.say or (lambda m: log.warning("%s", m)))
        kw = options.given("speed", "loop", "mode", "block_frames")
        if options.unpaced:
            kw["mode"] = ReplayMode.UNPACED
        return ReplayDevice(path, kind=self.name, name="demo", **kw)
