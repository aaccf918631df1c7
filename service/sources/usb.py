"""The USB spike camera (``cfsr_live.driver.usb``; needs pyusb, in the ``live`` extra)."""

from __future__ import annotations

import argparse

from cfsr.cli._extras import require_extra
from cfsr_live.driver.source import Source
from cfsr_live.service.catalog import CatalogEntry, SourceCatalog
from cfsr_live.service.settings import SourceSpec
from cfsr_live.service.sources import OpenOptions, SourceKind

__all__ = ["UsbKind"]

_HELP = {"serve": "use the USB spike camera", "record": "record from the USB spike camera"}
_VID_HELP = {
    "serve": "USB vendor id (with --usb), e.g. 0x1d6b",
    "record": "USB vendor id (with --usb)",
}


def _int_auto(text: str) -> int:
    return int(text, 0)


class UsbKind(SourceKind):
    name = "usb"
    summary = "the USB spike camera"
    order = 20

    def add_select_argument(self, select, command: str) -> None:
        select.add_argument("--usb", action="store_true", help=_HELP[command])

    def add_arguments(self, parser, command: str) -> None:
        parser.add_argument("--vid", type=_int_auto, help=_VID_HELP[command])
        parser.add_argument("--pid", type=_int_auto, help="USB product id (with --usb)")

    def spec_from_args(self, args: argparse.Namespace) -> SourceSpec | None:
        ids = {k: v for k in ("vid", "pid") if (v := getattr(args, k, None)) is not None}
        if not getattr(args, "usb", False):
            if ids:
                raise ValueError("--vid/--pid only apply with --usb")
            return None
        return SourceSpec(kind=self.name, options=ids)

    def entries(self, catalog: SourceCatalog) -> list[CatalogEntry]:
        import importlib.util

        cam = CatalogEntry(id="usb", kind="usb", name="USB spike camera")
        if importlib.util.find_spec("usb") is None:
            cam.note = "pyusb is not installed"
        return [cam]

    def spec_for(self, catalog: SourceCatalog, entry: CatalogEntry) -> SourceSpec:
        # the ids given on the command line when it opened a camera
        cur = catalog.settings.source
        ids = dict(cur.options) if cur.kind == self.name else {}
        return SourceSpec(kind=self.name, options=ids)

    def check_installed(self) -> None:
        require_extra("live", ["usb"])

    def open(self, spec: SourceSpec, options: OpenOptions) -> Source:
        # deferred: the driver needs the live extra (isal, pyusb); a base install lists it
        from cfsr_live.driver.usb import UsbCameraSource

        kw = {k: spec.options[k] for k in ("vid", "pid") if spec.options.get(k) is not None}
        return UsbCameraSource(**kw)
