"""Recording to ``.dat`` + sidecar from the ring (a ring consumer like the worker).

The recorder reads every block it can; frames it could not get (the ring overran it, or the
source reported loss) go into the sidecar's ``drop_map`` as ``[first_step, frames, kind]``
and ``clean_capture`` is true only when nothing was lost.

A recording never fills the disk: it is capped at ``max_bytes`` (default: the free space less
:data:`RESERVE_BYTES`), refused before it starts when not even one block fits, and stopped
cleanly when the free space falls under the reserve while it runs (other writers share the
disk). Whatever stops it (``stop_reason``), the ``.dat`` holds whole frames only and its sidecar
is written atomically (see :class:`cfsr.datfile.DatWriter`), so the recording opens.
"""

from __future__ import annotations

import shutil
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cfsr.datfile import DatWriter
from cfsr.layout import Layout
from driver.source import BlockFlags
from shm.ring import SpikeRing

if TYPE_CHECKING:
    # not at run time: ``cfsr record`` imports this module (:func:`size_cap`) in the base
    # install, which has no pydantic; only the live service asks a recorder for its status
    from service.status import RecordStatus

__all__ = ["Recorder", "RESERVE_BYTES", "free_bytes", "size_cap"]

#: free space a recording always leaves on its disk (for the sidecar, logs, the system)
RESERVE_BYTES = 64 * 1024 * 1024
#: how often the free space is looked at while recording, s
_SPACE_CHECK_S = 0.5


def free_bytes(folder: Path) -> int:
    return int(shutil.disk_usage(folder).free)


def size_cap(folder: Path, max_bytes: int | None, least: int, least_what: str) -> int:
    """Bytes a recording in ``folder`` may write: ``max_bytes`` (if given) within the free
    space less :data:`RESERVE_BYTES`.

    ValueError when ``max_bytes`` is under ``least`` bytes (the request is wrong); OSError when
    the disk has not ``least`` bytes to spare (the disk is full).
    """
    if max_bytes is not None and max_bytes < least:
        raise ValueError(f"max_bytes {max_bytes} is less than {least_what}")
    room = free_bytes(folder) - RESERVE_BYTES
    cap = room if max_bytes is None else min(room, max_bytes)
    if cap < least:
        raise OSError(
            f"not enough free space to record in {folder}: {max(0, room + RESERVE_BYTES) / 1e6:.0f}"
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
    ) -> None:
        self.ring = ring
        self.path = Path(path)
        self.layout = layout
        fb = layout.frame_bytes
        block = ring.slot_frames * fb
        self.max_bytes = size_cap(
            self.path.parent, max_bytes, block,
            f"one block of the stream ({ring.slot_frames} frames = {block} bytes)",
        )
        cap = self.max_bytes // fb
        self._asked_frames = max_frames
        self.max_frames = cap if max_frames is None else min(max_frames, cap)
        self.stop_reason: str | None = None
        self._reader = ring.reader(start="latest", keep=max(1, ring.n_slots // 2))
        self._writer = DatWriter(path, layout, rate_hz=rate_hz, meta=meta or {})
        self._stop = threading.Event()
        self.drop_map: list[list[Any]] = []
        self.frames = 0
        self.started = time.monotonic()
        self.started_at = datetime.now(UTC).isoformat(timespec="seconds")
        self.first_step: int | None = None
        self.error: str | None = None
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
                    free = free_bytes(self.path.parent)
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
        try:
            self._writer.close()
        except OSError as exc:  # e.g. no room left even for the sidecar: the .dat still opens
            self.error = (self.error + "; " if self.error else "") + f"sidecar not written: {exc}"
        self._reader.close()

    def stop(self, timeout: float = 10.0) -> RecordStatus:
        """Stop recording (the file is closed and its sidecar written) and report."""
        self._stop.set()
        self._thread.join(timeout)
        return self.status()

    def wait(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def status(self) -> RecordStatus:
        """The recorder's report (``recording`` in ``GET /api/status``, ``GET /api/record``)."""
        from service.status import RecordStatus

        running = self.running  # read once: a stop reason shows only once it has stopped
        return RecordStatus(
            recording=running,
            path=str(self.path),
            name=self.path.name,
            frames=self.frames,
            bytes=self.frames * self.layout.frame_bytes,
            elapsed_s=round(time.monotonic() - self.started, 3),
            lost_frames=sum(d[1] for d in self.drop_map),
            error=self.error,
            max_bytes=self.max_bytes,
            stop_reason=None if running else self.stop_reason,
        )
