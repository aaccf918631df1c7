"""Which sources the service can open, and opening them.

Recordings come only from the configured data folder: the listing is made by scanning that
folder (symlinks that leave it are ignored), and a client selects an entry by its *id* from the
listing. No path sent by a client is ever opened.

A scan never fails because of one bad file: a recording whose sidecar or size is bad, or a
FIFO/socket/device named like a recording, is listed with a ``note`` saying what is wrong (and
logged once), cannot be selected, and is never opened for reading (only ``stat``; sidecars are
opened without blocking and read only when they are regular files).
"""

from __future__ import annotations

import logging
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from driver.source import Source
from service.settings import Settings, SourceSpec

__all__ = ["SourceCatalog", "CatalogEntry", "SIM_SCENES"]

log = logging.getLogger("cfsr.catalog")

SUFFIXES = (".dat", ".npz")
MAX_DEPTH = 4
MAX_ENTRIES = 500
#: the synthetic scene that needs no simulator; cfsr.simulate's scenes are added when present
SIM_SCENES = ("pattern",)


@dataclass
class CatalogEntry:
    id: str
    kind: str  # demo | file | replay | usb | sim
    name: str
    path: Path | None = None
    frames: int | None = None
    bytes: int | None = None
    width: int | None = None
    height: int | None = None
    rate_hz: float | None = None
    note: str | None = None
    #: False when the entry cannot be opened (bad sidecar, bad size, not a regular file);
    #: ``note`` says why.
    usable: bool = True

    def public(self) -> dict[str, Any]:
        d = {
            "id": self.id,
            "kind": self.kind,
            "name": self.name,
            "frames": self.frames,
            "bytes": self.bytes,
            "width": self.width,
            "height": self.height,
            "duration_s": (self.frames / self.rate_hz) if self.frames and self.rate_hz else None,
            "note": self.note,
        }
        return d


def _simulator_scenes() -> list[str]:
    try:
        from cfsr.simulate import SCENES
    except ImportError:
        return []
    return list(SCENES)


class SourceCatalog:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.data_dir = settings.data_dir.resolve()
        self.extra: dict[str, CatalogEntry] = {}  # sources named on the command line
        self._reported: set[tuple[str, str]] = set()  # (path, problem) already logged

    def add_cli_source(self, spec: SourceSpec) -> None:
        if spec.kind == "replay" and spec.path is not None:
            e = self._describe_file(spec.path, f"replay:{spec.path.name}", "replay")
            if e is not None:
                self.extra[e.id] = e

    # -- listing ----------------------------------------------------------------------------
    def _unusable(self, e: CatalogEntry, problem: str) -> CatalogEntry:
        """Mark ``e`` as not openable because of ``problem``; log each problem once.

        The log line keeps full paths; the note, which clients see, names files relative to
        the recording's folder (the server's directory layout is not theirs to read).
        """
        e.usable = False
        folder = f"{e.path.parent}{os.sep}" if e.path is not None else None
        e.note = "cannot be opened: " + (problem.replace(folder, "") if folder else problem)
        key = (str(e.path), problem)
        if key not in self._reported:
            self._reported.add(key)
            # info, not warning: the listing's note is where users see it, and a start-up that
            # fails on this very file must stay one line
            log.info("data folder: skipping %s: %s", e.path, problem)
        return e

    def _describe_file(self, path: Path, id_: str, kind: str) -> CatalogEntry | None:
        """Describe ``path`` from ``stat`` and its sidecar; None if it vanished meanwhile."""
        from cfsr.datfile import SpikeFileError, file_kind, read_sidecar
        from cfsr.layout import STEP_RATE_HZ, Layout

        try:
            st = path.stat()
        except OSError:
            return None
        e = CatalogEntry(id=id_, kind=kind, name=path.name, path=path)
        if not stat.S_ISREG(st.st_mode):
            # a FIFO would block whoever opened it; say what it is instead of "empty file"
            return self._unusable(e, f"a {file_kind(st.st_mode)}, not a regular file")
        size = e.bytes = st.st_size
        try:
            meta = read_sidecar(path) or {}
            lay = Layout(**{k: meta[k] for k in ("width", "height", "head_cols") if k in meta})
        except (SpikeFileError, TypeError, ValueError) as exc:
            # the sidecar's own message names it, the key, the value and the allowed range
            return self._unusable(e, str(exc))
        e.width, e.height = lay.width, lay.height
        e.rate_hz = float(meta.get("rate_hz", STEP_RATE_HZ))
        if path.suffix.lower() == ".dat":
            fb = lay.frame_bytes
            e.frames, tail = divmod(size, fb)
            if size == 0:
                return self._unusable(e, "empty file (0 bytes)")
            if tail:
                return self._unusable(
                    e, f"size {size} bytes is not a multiple of the {fb}-byte frame"
                )
        return e

    def scan(self) -> dict[str, CatalogEntry]:
        out: dict[str, CatalogEntry] = {}
        from service.demo import demo_path

        dp = demo_path(self.settings.demo_steps)
        demo = CatalogEntry(id="demo", kind="demo", name="built-in demo (simulated disk)")
        if dp.exists():
            demo = self._describe_file(dp, "demo", "demo") or demo
            demo.name = "built-in demo (simulated disk)"
        else:
            demo.note = "simulated on first use"
        out["demo"] = demo
        out.update(self.extra)
        root = self.data_dir
        if root.is_dir():
            for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
                d = Path(dirpath)
                depth = len(d.relative_to(root).parts)
                if depth >= MAX_DEPTH:
                    dirnames[:] = []
                dirnames[:] = sorted(n for n in dirnames if not n.startswith("."))
                for fn in sorted(filenames):
                    if not fn.lower().endswith(SUFFIXES) or fn.startswith("."):
                        continue
                    p = d / fn
                    try:
                        real = p.resolve(strict=True)
                        real.relative_to(root)  # a symlink leading out of the folder: skip
                    except (OSError, ValueError):
                        continue
                    rel = p.relative_to(root).as_posix()
                    e = self._describe_file(real, f"file:{rel}", "file")
                    if e is not None:
                        e.name = rel
                        out[e.id] = e
                    if len(out) > MAX_ENTRIES:
                        break
        cam = CatalogEntry(id="usb", kind="usb", name="USB spike camera")
        import importlib.util

        if importlib.util.find_spec("usb") is None:
            cam.note = "pyusb is not installed"
        out["usb"] = cam
        for scene in [*SIM_SCENES, *_simulator_scenes()]:
            out[f"sim:{scene}"] = CatalogEntry(
                id=f"sim:{scene}", kind="sim", name=f"live simulator: {scene}"
            )
        return out

    # -- opening ----------------------------------------------------------------------------
    def spec_for(self, source_id: str) -> SourceSpec:
        """Resolve a listing id to what to open; KeyError if the id is not listed."""
        entries = self.scan()
        if source_id not in entries:
            raise KeyError(source_id)
        e = entries[source_id]
        if not e.usable:
            raise ValueError(f"{e.name}: {e.note}")
        if e.kind == "demo":
            return SourceSpec(kind="demo")
        if e.kind in ("file", "replay"):
            return SourceSpec(kind="replay", path=e.path)
        if e.kind == "usb":
            cur = self.settings.source
            return SourceSpec(kind="usb", vid=cur.vid, pid=cur.pid)
        if e.kind == "sim":
            return SourceSpec(kind="sim", scene=source_id.split(":", 1)[1])
        raise KeyError(source_id)

    def open(self, spec: SourceSpec) -> Source:
        s = self.settings
        if spec.kind == "demo":
            from service.demo import ensure_demo

            path = ensure_demo(s.demo_steps, say=lambda m: log.warning("%s", m))
            return self._replay(path, name="demo")
        if spec.kind == "replay":
            if spec.path is None:
                raise ValueError("replay source needs a file")
            return self._replay(spec.path)
        if spec.kind == "usb":
            from driver.usb import UsbCameraSource

            kw = {}
            if spec.vid is not None:
                kw["vid"] = spec.vid
            if spec.pid is not None:
                kw["pid"] = spec.pid
            return UsbCameraSource(**kw)
        if spec.kind == "sim":
            from replay.simulator import SimulatorSource
            from service.settings import cache_dir

            return SimulatorSource(
                spec.scene or "pattern", speed=s.speed, cache_dir=cache_dir() / "sim"
            )
        raise ValueError(f"unknown source kind {spec.kind!r}")

    def _replay(self, path: Path, name: str | None = None) -> Source:
        from replay.device import ReplayDevice

        s = self.settings
        return ReplayDevice(
            path,
            speed=s.speed,
            loop=s.loop,
            mode=s.replay_mode,
            block_frames=s.block_frames,
            name=name,
        )
