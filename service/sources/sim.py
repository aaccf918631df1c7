"""The live simulator: a synthetic scene fired through the spike camera model at the sensor's
rate (``cfsr_live.replay.simulator``), listed as ``sim:<scene>``."""

from __future__ import annotations

import argparse

from cfsr_live.driver.source import ReplayMode, Source
from cfsr_live.replay.simulator import SimulatorSource
from cfsr_live.service.catalog import CatalogEntry, SourceCatalog
from cfsr_live.service.settings import SourceSpec
from cfsr_live.service.sources import OpenOptions, SourceKind

__all__ = ["SimKind", "SIM_SCENES"]

#: the synthetic scene that needs no simulator; cfsr.simulate's scenes are added when present
SIM_SCENES = ("pattern",)

_HELP = {
    "serve": "live simulator source (pattern, disk, ...)",
    "record": "record the live simulator (pattern, disk..)",
}


def _scenes() -> list[str]:
    try:
        # deferred: the simulator loads when its scenes are listed (pattern needs none)
        from cfsr.simulate import SCENES
    except ImportError:
        return [*SIM_SCENES]
    return [*SIM_SCENES, *SCENES]


class SimKind(SourceKind):
    name = "sim"
    summary = "the live simulator (a synthetic scene at the sensor's rate)"
    order = 30

    def add_select_argument(self, select, command: str) -> None:
        select.add_argument("--sim", metavar="SCENE", help=_HELP[command])

    def spec_from_args(self, args: argparse.Namespace) -> SourceSpec | None:
        scene = getattr(args, "sim", None)
        return SourceSpec(kind=self.name, options={"scene": scene}) if scene else None

    def entries(self, catalog: SourceCatalog) -> list[CatalogEntry]:
        return [CatalogEntry(id=f"sim:{s}", kind="sim", name=f"live simulator: {s}")
                for s in _scenes()]

    def entry(self, catalog: SourceCatalog, source_id: str) -> CatalogEntry | None:
        # no listing (importing the simulator is enough to know its scenes)
        if not source_id.startswith("sim:") or source_id[4:] not in _scenes():
            return None
        return CatalogEntry(id=source_id, kind="sim", name=source_id[4:])

    def spec_for(self, catalog: SourceCatalog, entry: CatalogEntry) -> SourceSpec:
        return SourceSpec(kind=self.name, options={"scene": entry.id.split(":", 1)[1]})

    def spec_id(self, spec: SourceSpec) -> str:
        return f"sim:{spec.options.get('scene') or 'pattern'}"

    def open(self, spec: SourceSpec, options: OpenOptions) -> Source:
        kw = options.given("speed")
        if options.cache_dir is not None:
            kw["cache_dir"] = options.cache_dir / "sim"
        if options.unpaced:  # a paced simulator stands for a live camera: serve keeps it
            kw["mode"] = ReplayMode.UNPACED
        return SimulatorSource(spec.options.get("scene") or "pattern", **kw)
