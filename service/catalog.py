"""Which sources the service can open, and opening them.

The listing is made by the registered source kinds (:mod:`cfsr_live.service.sources`): each
kind lists its own entries, resolves its own ids and opens its own sources; this module holds
what they share (the entry type, the data folder's safe scan) and asks every kind in turn.

Recordings come only from the configured data folder: the listing is made by scanning that
folder (symlinks that leave it are ignored), and a client selects an entry by its *id* from the
listing. No path sent by a client is ever opened.

A scan never fails because of one bad file: a recording whose sidecar or size is bad, whose
frames are larger than the display holds, a FIFO/socket/device named like a recording, a
symbolic link that loops, dangles or leads out of the folder, a folder that cannot be read (any
``OSError``: permissions, loops, a file removed while the scan runs) is listed with a ``note``
saying what is wrong (and logged once), cannot be selected, and is never opened for reading
(only ``stat``; sidecars are opened without blocking and read only when they are regular
files). The listing holds at most :data:`MAX_ENTRIES` entries from the folder, whatever their
depth; when it stops there, its last entry says so.
"""

from __future__ import annotations

import errno
import logging
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cfsr.datfile import SpikeFileError, file_kind, read_sidecar
from cfsr.layout import STEP_RATE_HZ, Layout
from cfsr_live.driver.source import Source
from cfsr_live.service import sources
from cfsr_live.service.settings import MAX_DISPLAY_PIXELS, Settings, SourceSpec

__all__ = ["SourceCatalog", "CatalogEntry"]

log = logging.getLogger("cfsr.catalog")

SUFFIXES = (".dat", ".npz")
MAX_DEPTH = 4
MAX_ENTRIES = 500


@dataclass
class CatalogEntry:
    id: str
    #: what the viewer's menu shows it as (a source kind's name, or ``file`` for a recording
    #: of the data folder)
    kind: str
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


def _os_problem(exc: OSError) -> str:
    """An OSError in words, without the path (the entry names the file)."""
    if exc.errno == errno.ELOOP:
        return "a symbolic link that loops"
    if exc.errno == errno.ENOENT:
        return "a symbolic link to nothing (dangling)"
    return f"cannot be read ({exc.strerror or exc})"


class SourceCatalog:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.data_dir = settings.data_dir.resolve()
        self.extra: dict[str, CatalogEntry] = {}  # sources named on the command line
        self._extra_kind: dict[str, sources.SourceKind] = {}
        self._reported: set[tuple[str, str]] = set()  # (path, problem) already logged

    def add_cli_source(self, spec: SourceSpec) -> None:
        """List the source the command line opened, when its kind would not list it."""
        kind = sources.get(spec.kind)
        e = kind.cli_entry(self, spec)
        if e is not None:
            self.extra[e.id] = e
            self._extra_kind[e.id] = kind

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

    def describe_file(self, path: Path, id_: str, kind: str) -> CatalogEntry | None:
        """Describe ``path`` from ``stat`` and its sidecar; None if it vanished meanwhile."""
        try:
            st = path.stat()
        except FileNotFoundError:
            return None
        except OSError as exc:  # a link loop, a permission: say so, never fail the scan
            e = CatalogEntry(id=id_, kind=kind, name=path.name, path=path)
            return self._unusable(e, _os_problem(exc))
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
        except OSError as exc:
            return self._unusable(e, "sidecar: " + _os_problem(exc))
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
        px = lay.width * lay.height
        if px > MAX_DISPLAY_PIXELS:
            return self._unusable(
                e, f"{lay.width} x {lay.height} = {px} pixels is more than the "
                f"{MAX_DISPLAY_PIXELS} pixels the display holds"
            )
        return e

    def _folder_entry(self, rel: str, path: Path) -> CatalogEntry | None:
        """An entry for a file of the folder at ``rel`` (relative to the data folder); None
        for a link that leads out of the folder (not listed: the folder is what is shared)."""
        e = CatalogEntry(id=f"file:{rel}", kind="file", name=rel, path=path)
        try:
            real = Path(os.path.realpath(path, strict=True))
        except OSError as exc:  # dangling or looping link
            return self._unusable(e, _os_problem(exc))
        if real != self.data_dir and self.data_dir not in real.parents:
            return None
        d = self.describe_file(real, e.id, "file")
        if d is None:
            return self._unusable(e, "removed while the folder was read")
        d.name = rel
        return d

    def scan_folder(self) -> list[CatalogEntry]:
        """The data folder's recordings, depth first in name order, at most
        :data:`MAX_ENTRIES` (then a last entry saying the listing stops there)."""
        root = self.data_dir
        out: list[CatalogEntry] = []
        stack: list[tuple[Path, int]] = [(root, 0)]
        skipped = 0
        while stack:
            folder, depth = stack.pop()
            rel_dir = folder.relative_to(root).as_posix()
            try:
                with os.scandir(folder) as it:
                    items = sorted(it, key=lambda x: x.name)
            except OSError as exc:
                if folder == root:
                    return out  # no data folder (yet): nothing to list
                if len(out) < MAX_ENTRIES:
                    e = CatalogEntry(id=f"file:{rel_dir}/", kind="file", name=f"{rel_dir}/",
                                     path=folder)
                    out.append(self._unusable(e, "folder " + _os_problem(exc)))
                continue
            subdirs: list[Path] = []
            for it in items:
                name = it.name
                if name.startswith("."):
                    continue
                try:
                    is_dir = it.is_dir(follow_symlinks=False)
                except OSError:
                    is_dir = False
                if is_dir:
                    if depth + 1 < MAX_DEPTH:
                        subdirs.append(Path(it.path))
                    continue
                if not name.lower().endswith(SUFFIXES):
                    continue
                if len(out) >= MAX_ENTRIES:
                    skipped += 1
                    continue
                rel = f"{rel_dir}/{name}" if rel_dir != "." else name
                e = self._folder_entry(rel, Path(it.path))
                if e is not None:
                    out.append(e)
            if len(out) >= MAX_ENTRIES:
                skipped += len(subdirs)  # not entered: counted as folders left out
                continue
            stack.extend((p, depth + 1) for p in reversed(subdirs))
        if skipped:
            out.append(CatalogEntry(
                id="file:(listing cut)", kind="file", name="(more recordings not listed)",
                note=f"the listing stops at {MAX_ENTRIES} recordings; {skipped} more files or "
                "folders of the data folder are not listed (use sub-folders less deep, or "
                "fewer files)", usable=False))
        return out

    def scan(self) -> dict[str, CatalogEntry]:
        """The whole listing, id -> entry: each kind's entries in the kinds' order, the
        sources named on the command line first among their kind's."""
        out: dict[str, CatalogEntry] = {}
        for kind in sources.kinds():
            for id_, e in self.extra.items():
                if self._extra_kind[id_] is kind:
                    out[id_] = e
            for e in kind.entries(self):
                out[e.id] = e
        return out

    # -- opening ----------------------------------------------------------------------------
    def _entry(self, source_id: str) -> tuple[sources.SourceKind, CatalogEntry]:
        """The listing's entry ``source_id`` and its kind, found without listing everything
        (a switch to the simulator never reads the data folder); KeyError if there is none."""
        if source_id in self.extra:
            return self._extra_kind[source_id], self.extra[source_id]
        for kind in sources.kinds():
            e = kind.entry(self, source_id)
            if e is not None:
                return kind, e
        raise KeyError(source_id)

    def file_entry(self, rel: str) -> CatalogEntry | None:
        """The entry of recording ``rel`` (as the listing names it), or None when the listing
        would not hold it: a hidden or non-recording name, too deep, or below a link."""
        parts = rel.split("/")
        if (len(parts) > MAX_DEPTH or not rel.lower().endswith(SUFFIXES)
                or any(p in ("", ".", "..") or p.startswith(".") for p in parts)):
            return None
        folder = self.data_dir
        for p in parts[:-1]:
            folder = folder / p
            if folder.is_symlink() or not folder.is_dir():
                return None  # the scan never enters a linked folder
        path = folder / parts[-1]
        if not os.path.lexists(path):
            return None
        return self._folder_entry(rel, path)

    def spec_for(self, source_id: str) -> SourceSpec:
        """Resolve a listing id to what to open; KeyError if the id is not listed."""
        kind, e = self._entry(source_id)
        if not e.usable:
            raise ValueError(f"{e.name}: {e.note}")
        return kind.spec_for(self, e)

    def open(self, spec: SourceSpec) -> Source:
        """A new (not yet opened) source for ``spec``, made by its kind."""
        kind = sources.get(spec.kind)
        say = lambda m: log.warning("%s", m)  # noqa: E731 - the demo's first simulation
        return kind.open(spec, sources.OpenOptions.from_settings(self.settings, say=say))
