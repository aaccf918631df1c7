"""Recording to ``.dat`` + sidecar from the ring (a ring consumer like the worker).

The recorder reads every block it can; frames it could not get (the ring overran it, or the
source reported loss) go into the sidecar's ``drop_map`` as ``[first_step, frames, kind]``
and ``clean_capture`` is true only when nothing was lost.

A recording never fills the disk: it is capped at ``max_bytes`` (default: the free space less
:data:`RESERVE_BYTES`), refused before it starts when not even one block fits, and stopped
cleanly when the free space falls under the reserve while it runs (other writers share the
disk). Whatever stops it (``stop_reason``), the ``.dat`` holds whole frames only and its sidecar
exists from before the first frame is on disk (:class:`~cfsr.datfile.DatWriter` reserves its
space at the start), so the recording opens with its own geometry even when another writer
fills the disk. A recording that got no frame leaves no file, however it ends: the files get
their names only with the first frames (:class:`FolderDatWriter`).

The ``.dat`` and its sidecar are created through :mod:`cfsr_live.service.safefs`
(:class:`FolderDatWriter`):
exclusively, never through a symbolic link, in a folder opened inside the data folder; a name
that exists in any form (another server's recording, a dangling link) is refused before a byte
is written.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cfsr.datfile import (
    DatWriter,
    _overwrite,
    _sidecar_dict,
    sidecar_path,
    validate_sidecar,
)
from cfsr.defects import DefectMap
from cfsr.layout import Layout
from cfsr_live.driver.source import BlockFlags
from cfsr_live.service.safefs import create_exclusive, name_taken, write_bytes_at
from cfsr_live.shm.ring import SpikeRing

if TYPE_CHECKING:
    # not at run time: ``cfsr record`` imports this module (:func:`size_cap`) in the base
    # install, which has no pydantic; only the live service asks a recorder for its status
    from cfsr_live.service.status import RecordStatus

__all__ = ["FolderDatWriter", "Recorder", "RESERVE_BYTES", "free_bytes", "size_cap"]

#: free space a recording always leaves on its disk (for the sidecar, logs, the system)
RESERVE_BYTES = 64 * 1024 * 1024
#: how often the free space is looked at while recording, s
_SPACE_CHECK_S = 0.5


def free_bytes(folder: Path | int) -> int:
    """Free bytes (for this user) on the disk of ``folder``, a path or an open folder's
    descriptor (which a link swapped in meanwhile cannot redirect)."""
    if isinstance(folder, int):
        st = os.fstatvfs(folder)
        return int(st.f_bavail * st.f_frsize)
    return int(shutil.disk_usage(folder).free)


class _NameHold:
    """Holds a recording's name in a folder from the recording's start until its files exist,
    without a file: an abstract Unix socket named after the folder and the name, which the
    kernel frees when the process ends in any way (SIGKILL included). Another recorder that
    wants the same name, in this process or another, is refused (FileExistsError)."""

    def __init__(self, dir_fd: int, name: str) -> None:
        import hashlib
        import socket

        st = os.fstat(dir_fd)
        key = hashlib.sha256(f"{st.st_dev}:{st.st_ino}:{name}".encode()).hexdigest()[:40]
        self._sock: Any = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._sock.bind(f"\0cfsr-recording-{key}")
        except OSError as exc:
            self._sock.close()
            if exc.errno != errno.EADDRINUSE:
                raise
            raise FileExistsError(errno.EEXIST, f"{name} is being recorded", name) from None

    def release(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _unnamed_file(dir_fd: int, flags: int) -> int | None:
    """A new file in the folder with no name yet (``O_TMPFILE``: it vanishes with the process
    unless linked), or None where the file system or the system has no such files."""
    if not hasattr(os, "O_TMPFILE"):
        return None
    try:
        return os.open(".", flags | os.O_TMPFILE | os.O_CLOEXEC, 0o644, dir_fd=dir_fd)
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL):
            return None
        raise


class FolderDatWriter(DatWriter):
    """A :class:`~cfsr.datfile.DatWriter` whose ``.dat`` and sidecar are created in an open
    folder (``dir_fd``) with :mod:`cfsr_live.service.safefs`: never through a link
    (FileExistsError when ``NAME.dat`` or ``NAME.dat.json`` exists in any form), the sidecar
    by an atomic rename. Same checks, whole-frame trimming and sidecar as the base class,
    which opens its file by path (following links, truncating what is there).

    The files get their names only with the first frames: until then the ``.dat`` and the
    reserved sidecar are unnamed files in the folder (``O_TMPFILE``), and the name is held by
    :class:`_NameHold`. So a recording that got no frame leaves no file however it ends (a
    SIGKILL before the first block left an empty ``.dat`` that nothing opens), and the
    ``.dat`` appears with its first frames and its sidecar beside it. Where unnamed files are
    not available the files are created at once, as before."""

    def __init__(
        self,
        dir_fd: int,
        name: str,
        layout: Layout,
        *,
        rate_hz: float,
        meta: dict[str, Any] | None = None,
        display_path: Path | None = None,
    ) -> None:
        self.path = display_path or Path(name)
        self.layout = layout
        self.rate_hz = float(rate_hz)
        self.meta = dict(meta or {})
        self.n_frames = 0
        side = sidecar_path(name).name
        validate_sidecar(_sidecar_dict(layout, 0, self.rate_hz, self.meta), side)
        for n in (name, side):
            if name_taken(dir_fd, n):
                raise FileExistsError(errno.EEXIST, f"{n} already exists", n)
        self._side, self._name = side, name
        self._hold: _NameHold | None = _NameHold(dir_fd, name)
        self._named = False
        self._dir_fd = os.dup(dir_fd)
        self._side_fd = -1
        try:
            fd = _unnamed_file(self._dir_fd, os.O_WRONLY)
            if fd is None:  # no unnamed files here: the name is taken now
                fd = create_exclusive(self._dir_fd, name)
                self._named = True
            self._fh = os.fdopen(fd, "wb", buffering=0)
        except BaseException:
            self._release_folder()
            raise
        try:
            self._reserve_sidecar()  # before the first byte of spikes (removes the .dat if not)
        except BaseException:
            self._release_folder()
            raise

    def _put_sidecar(self, data: bytes) -> None:
        if self._named:
            write_bytes_at(self._dir_fd, self._side, data)
            return
        # the reserve goes into an unnamed file of its own, linked beside the first frames
        self._side_fd = _unnamed_file(self._dir_fd, os.O_WRONLY)
        if self._side_fd is None:
            raise OSError(errno.EOPNOTSUPP, "no unnamed sidecar file", self._side)
        _overwrite(self._side_fd, data)

    def _put_sidecar_in_place(self, data: bytes) -> None:
        fd = os.open(self._side, os.O_WRONLY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=self._dir_fd)
        try:
            _overwrite(fd, data)
        finally:
            os.close(fd)

    def write_packed(self, packed) -> None:
        try:
            super().write_packed(packed)
        finally:
            if not self._named and self.n_frames:
                self._name_files()

    def _name_files(self) -> None:
        """Give the files their names (sidecar first: a reader never meets a ``.dat`` without
        it); neither replaces anything that took a name meanwhile."""
        for fd, name in ((self._side_fd, self._side), (self._fh.fileno(), self._name)):
            try:
                os.link(f"/proc/self/fd/{fd}", name, dst_dir_fd=self._dir_fd,
                        follow_symlinks=True)
            except BaseException:
                if name == self._name:
                    with contextlib.suppress(OSError):
                        os.unlink(self._side, dir_fd=self._dir_fd)
                raise
        self._named = True
        os.close(self._side_fd)
        self._side_fd = -1

    def _remove_files(self) -> None:
        if not self._named:
            return  # never named: closing them is their end
        for name in (self._name, self._side):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(name, dir_fd=self._dir_fd)

    def close(self) -> None:
        if not self.n_frames:  # no frame came: nothing to keep (nothing opens an empty .dat)
            self.discard()
            return
        try:
            super().close()
        finally:
            self._release_folder()

    def discard(self) -> None:
        try:
            super().discard()
        finally:
            self._release_folder()

    def _release_folder(self) -> None:
        if self._side_fd >= 0:
            os.close(self._side_fd)
            self._side_fd = -1
        if self._hold is not None:
            self._hold.release()
            self._hold = None
        if self._dir_fd >= 0:
            os.close(self._dir_fd)
            self._dir_fd = -1


def size_cap(
    folder: Path | int, max_bytes: int | None, least: int, least_what: str,
    *, where: str | None = None,
) -> int:
    """Bytes a recording in ``folder`` (a path or an open folder's descriptor, then named
    ``where`` in messages) may write: ``max_bytes`` (if given) within the free space less
    :data:`RESERVE_BYTES`.

    ValueError when ``max_bytes`` is under ``least`` bytes (the request is wrong); OSError when
    the disk has not ``least`` bytes to spare (the disk is full).
    """
    if max_bytes is not None and max_bytes < least:
        raise ValueError(f"max_bytes {max_bytes} is less than {least_what}")
    room = free_bytes(folder) - RESERVE_BYTES
    cap = room if max_bytes is None else min(room, max_bytes)
    if cap < least:
        free_mb = max(0, room + RESERVE_BYTES) / 1e6
        raise OSError(
            f"not enough free space to record in {where or folder}: {free_mb:.0f}"
            f" MB free, a recording keeps {RESERVE_BYTES / 1e6:.0f} MB free and needs at least "
            f"{least_what}"
        )
    return cap


class Recorder:
    def __init__(
        self,
        ring: SpikeRing,
        path: Path,
        layout: Layout,
        *,
        rate_hz: float,
        meta: dict[str, Any] | None = None,
        max_frames: int | None = None,
        max_bytes: int | None = None,
        dir_fd: int | None = None,
        defects: Callable[[], dict[str, Any] | None] | None = None,
    ) -> None:
        """Record into ``path`` (created in the open folder ``dir_fd``, else in its parent
        folder); FileExistsError when the name or its sidecar's exists in any form.
        ``defects``: the defect map the live worker corrects with, now (JSON form of
        :class:`cfsr.defects.DefectMap`, or None); asked when the recording ends and kept
        in its sidecar, so a replay of it starts corrected."""
        self.ring = ring
        self._defects = defects
        self.path = Path(path)
        self.layout = layout
        fb = layout.frame_bytes
        block = ring.slot_frames * fb
        own_fd = dir_fd is None
        if own_fd:
            dir_fd = os.open(self.path.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            self.max_bytes = size_cap(
                dir_fd, max_bytes, block,
                f"one block of the stream ({ring.slot_frames} frames = {block} bytes)",
                where=str(self.path.parent),
            )
            self._writer = FolderDatWriter(dir_fd, self.path.name, layout, rate_hz=rate_hz,
                                           meta=meta or {}, display_path=self.path)
        finally:
            if own_fd:
                os.close(dir_fd)
        # the free space is watched on the folder the file is in, whatever its path becomes
        self._space_fd = os.dup(self._writer._dir_fd)
        cap = self.max_bytes // fb
        self._asked_frames = max_frames
        self.max_frames = cap if max_frames is None else min(max_frames, cap)
        self.stop_reason: str | None = None
        self._reader = ring.reader(start="latest", keep=max(1, ring.n_slots // 2))
        self._stop = threading.Event()
        self.drop_map: list[list[Any]] = []
        self.frames = 0
        self.started = time.monotonic()
        self.started_at = datetime.now(UTC).isoformat(timespec="seconds")
        self.first_step: int | None = None
        self.error: str | None = None
        #: True once a recording that got no frame has been removed (nothing to keep)
        self.removed = False
        self._thread = threading.Thread(target=self._run, name="cfsr-recorder", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        r = self._reader
        next_check = time.monotonic() + _SPACE_CHECK_S
        try:
            while not self._stop.is_set():
                if time.monotonic() >= next_check:
                    next_check = time.monotonic() + _SPACE_CHECK_S
                    free = free_bytes(self._space_fd)
                    if free < RESERVE_BYTES:
                        self.stop_reason = f"disk nearly full ({free / 1e6:.0f} MB free)"
                        break
                blk = r.poll()
                if blk is None:
                    self._stop.wait(0.002)
                    continue
                lost = r.lost_frames
                data = blk.data.copy()
                ok = r.release(blk)
                if r.lost_frames > lost:
                    gap = r.lost_frames - lost - (0 if ok else blk.n_frames)
                    if gap > 0:
                        self.drop_map.append([blk.index - gap, gap, "ring_overrun"])
                if not ok:
                    self.drop_map.append([blk.index, blk.n_frames, "ring_overrun"])
                    continue
                if blk.lost_before:
                    self.drop_map.append([blk.index - blk.lost_before, blk.lost_before, "source"])
                if blk.flags & BlockFlags.DISCONTINUITY and self.frames:
                    self.drop_map.append([blk.index, 0, "discontinuity"])
                if self.first_step is None:
                    self.first_step = blk.index
                data = data[: self.max_frames - self.frames]
                try:
                    self._writer.write_packed(data)
                finally:
                    self.frames = self._writer.n_frames  # whole frames on disk, even on error
                if self.frames >= self.max_frames:
                    self.stop_reason = (
                        "max_frames reached" if self.frames == self._asked_frames
                        else f"size cap reached ({self.frames * self.layout.frame_bytes} bytes)"
                    )
                    break
        except Exception as exc:  # noqa: BLE001 - reported in status and the sidecar
            self.error = f"{type(exc).__name__}: {exc}"
            self.stop_reason = "error"
        finally:
            if self.stop_reason is None:
                self.stop_reason = "stopped"
            self._finish()

    def _finish(self) -> None:
        lost = sum(d[1] for d in self.drop_map)
        self._writer.meta.update(
            {
                "recorded_at": self.started_at,
                "first_step": self.first_step,
                "drop_map": self.drop_map,
                "lost_frames": lost,
                "clean_capture": lost == 0 and self.error is None,
                "record_error": self.error,
                "stop_reason": self.stop_reason,
            }
        )
        self._keep_defects()
        try:
            if self.frames:
                self._writer.close()
            else:  # nothing came: no empty .dat (which nothing opens) is left behind
                self._writer.discard()
                self.removed = True
        except OSError as exc:  # the sidecar's reserved space could not be written either
            self.error = (self.error + "; " if self.error else "") + f"sidecar not final: {exc}"
        self._reader.close()
        os.close(self._space_fd)

    def _keep_defects(self) -> None:
        """The worker's defect map at the end, in the sidecar (checked: one that does not
        fit this recording, or a broken one, is left out and said in ``record_error``)."""
        try:
            dmap = self._defects() if self._defects is not None else None
            if dmap is not None:
                DefectMap.from_dict(dmap, self.layout.shape, where="the worker's defect map")
                self._writer.meta["defects"] = dmap
        except Exception as exc:  # noqa: BLE001 - the recording itself is fine
            note = f"defect map not kept: {exc}"
            self._writer.meta["record_error"] = "; ".join(
                e for e in (self._writer.meta.get("record_error"), note) if e)

    def stop(self, timeout: float = 10.0) -> RecordStatus:
        """Stop recording (the file is closed and its sidecar written) and report."""
        self._stop.set()
        self._thread.join(timeout)
        return self.status()

    def wait(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def status(self) -> RecordStatus:
        """The recorder's report (``recording`` in ``GET /api/status``, ``GET /api/record``)."""
        # deferred: the status models need pydantic, which the base install's `cfsr record` lacks
        from cfsr_live.service.status import RecordStatus

        running = self.running  # read once: a stop reason shows only once it has stopped
        return RecordStatus(
            recording=running,
            # the folder of the recording and its name, never the server's absolute path
            # (which the listing does not show either): "recordings/NAME.dat"
            path=None if self.removed else f"{self.path.parent.name}/{self.path.name}",
            name=self.path.name,
            frames=self.frames,
            bytes=self.frames * self.layout.frame_bytes,
            elapsed_s=round(time.monotonic() - self.started, 3),
            lost_frames=sum(d[1] for d in self.drop_map),
            error=self.error,
            max_bytes=self.max_bytes,
            stop_reason=None if running else self.stop_reason,
        )
