"""Recording to ``.dat`` + sidecar from the ring (a ring consumer like the worker).

The recorder reads every block it can; frames it could not get (the ring overran it, or the
source reported loss) go into the sidecar's ``drop_map`` as ``[first_step, frames, kind]``
and ``clean_capture`` is true only when nothing was lost.
"""

from __future__ import annotations

import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cfsr.datfile import DatWriter
from cfsr.layout import Layout
from driver.ring import SpikeRing
from driver.source import BlockFlags

__all__ = ["Recorder"]


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
    ) -> None:
        self.ring = ring
        self.path = Path(path)
        self.layout = layout
        self.max_frames = max_frames
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
        try:
            while not self._stop.is_set():
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
                if self.max_frames is not None:
                    data = data[: self.max_frames - self.frames]
                self._writer.write_packed(data)
                self.frames += data.shape[0]
                if self.max_frames is not None and self.frames >= self.max_frames:
                    break
        except Exception as exc:  # noqa: BLE001 - reported in status and the sidecar
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
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
            }
        )
        self._writer.close()
        self._reader.close()

    def stop(self, timeout: float = 10.0) -> dict[str, Any]:
        self._stop.set()
        self._thread.join(timeout)
        return self.describe()

    def wait(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def describe(self) -> dict[str, Any]:
        return {
            "recording": self.running,
            "path": str(self.path),
            "name": self.path.name,
            "frames": self.frames,
            "bytes": self.frames * self.layout.frame_bytes,
            "elapsed_s": round(time.monotonic() - self.started, 3),
            "lost_frames": sum(d[1] for d in self.drop_map),
            "error": self.error,
        }
