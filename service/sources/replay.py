"""Recorded ``.dat`` files replayed through the source interface: the data folder's recordings
(listed as ``file:<path in the folder>``) and the one named by ``--replay FILE`` (listed as
``replay:<name>``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cfsr_live.driver.source import ReplayMode, Source
from cfsr_live.replay.device import ReplayDevice
from cfsr_live.service.catalog import CatalogEntry, SourceCatalog
from cfsr_live.service.settings import SourceSpec
from cfsr_live.service.sources import OpenOptions, SourceKind

__all__ = ["ReplayKind"]

_HELP = {
    "serve": "replay a .dat recording",
    "record": "re-record (a range of) a .dat, as fast as it can be written",
}


class ReplayKind(SourceKind):
    name = "replay"
    summary = "a .dat recording replayed at the sensor's rate (or faster)"
    order = 10

    def add_select_argument(self, select, command: str) -> None:
        select.add_argument("--replay", metavar="FILE", type=Path, help=_HELP[command])

    def spec_from_args(self, args: argparse.Namespace) -> SourceSpec | None:
        if getattr(args, "replay", None) is None:
            return None
        if not args.replay.is_file():
            raise ValueError(f"{args.replay}: no such recording")
        return SourceSpec(kind=self.name, path=args.replay.resolve())

    def entries(self, catalog: SourceCatalog) -> list[CatalogEntry]:
        return catalog.scan_folder()

    def entry(self, catalog: SourceCatalog, source_id: str) -> CatalogEntry | None:
        if not source_id.startswith("file:"):
            return None
        return catalog.file_entry(source_id[5:])

    def spec_for(self, catalog: SourceCatalog, entry: CatalogEntry) -> SourceSpec:
        return SourceSpec(kind=self.name, path=entry.path)

    def cli_entry(self, catalog: SourceCatalog, spec: SourceSpec) -> CatalogEntry | None:
        if spec.path is None:
            return None
        return catalog.describe_file(spec.path, self.spec_id(spec), "replay")

    def spec_id(self, spec: SourceSpec) -> str:
        return f"replay:{spec.path.name}" if spec.path is not None else self.name

    def open(self, spec: SourceSpec, options: OpenOptions) -> Source:
        if spec.path is None:
            raise ValueError("replay source needs a file")
        kw = options.given("speed", "loop", "mode", "block_frames")
        if options.unpaced:
            kw["mode"] = ReplayMode.UNPACED
        return ReplayDevice(spec.path, **kw)
