"""The acquisition thread: ``Source.read_block()`` -> ``SpikeRing.write()``, forever.

It never waits for a consumer (the ring overwrites the oldest data); in the ring's
``blocking`` test mode it waits for registered consumers instead. A source error does not end
the thread: it is recorded and retried with backoff, so the service stays up while a camera
is gone (USB sources reconnect by themselves inside ``read_block``).
"""

from __future__ import annotations

import logging
import threading

from cfsr_live.driver.source import BlockFlags, Source, SourceEnded, SourceError, SourceState
from cfsr_live.shm.ring import SpikeRing

__all__ = ["Acquisition"]

log = logging.getLogger("cfsr.acquisition")


class Acquisition:
    """Pump blocks from ``source`` into ``ring`` on a daemon thread.

    Attributes
    ----------
    blocks, frames : int
        Published so far.
    lost_frames : int
        Frames the source reported lost before blocks (USB index gaps, replay behind schedule).
    discontinuities : int
        Blocks flagged DISCONTINUITY (seek, reconnect).
    errors : int
        Source errors survived.
    """

    def __init__(self, source: Source, ring: SpikeRing, *, read_timeout: float = 0.2) -> None:
        if source.info.layout.frame_bytes != ring.frame_bytes:
            raise ValueError(
                f"source frames are {source.info.layout.frame_bytes} bytes but the ring holds "
                f"{ring.frame_bytes}-byte frames"
            )
        self.source = source
        self.ring = ring
        self.read_timeout = read_timeout
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.blocks = 0
        self.frames = 0
        self.lost_frames = 0
        self.discontinuities = 0
        self.errors = 0
        self.ended = False
        self.last_error: str | None = None
        self._next_index: int | None = None
        self._pending_discontinuity = True  # the first block after (re)start

    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("acquisition already started")
        self._thread = threading.Thread(target=self._run, name="cfsr-acquisition", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def thread_ident(self) -> int | None:
        """``threading`` ident of the acquisition thread once started (for per-thread CPU
        time: ``time.pthread_getcpuclockid``)."""
        return None if self._thread is None else self._thread.ident

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        backoff = 0.05
        src = self.source
        while not self._stop.is_set():
            try:
                blk = src.read_block(self.read_timeout)
            except SourceEnded:
                self.ended = True
                self._stop.wait(0.05)
                continue
            except SourceError as exc:
                self.errors += 1
                self.last_error = str(exc)
                log.warning("source error: %s (retry in %.2f s)", exc, backoff)
                self._stop.wait(backoff)
                backoff = min(2.0, backoff * 2)
                continue
            except Exception as exc:  # noqa: BLE001 - keep the service up, report it
                self.errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
                src.state = SourceState.ERROR
                log.exception("unexpected source failure")
                self._stop.wait(backoff)
                backoff = min(2.0, backoff * 2)
                continue
            if blk is None:
                continue
            self.ended = False
            backoff = 0.05
            flags = int(blk.flags)
            if self._pending_discontinuity:
                flags |= BlockFlags.DISCONTINUITY
                self._pending_discontinuity = False
            if flags & BlockFlags.DISCONTINUITY:
                self.discontinuities += 1
            self.lost_frames += blk.lost_before
            self.ring.write(
                blk.index,
                blk.data,
                flags=flags,
                lost_before=blk.lost_before,
                t_host=blk.t_host,
                stop_waiting=self._stop.is_set,
            )
            self.blocks += 1
            self.frames += blk.n_frames
            self._next_index = blk.index + blk.n_frames

    def stats(self) -> dict[str, object]:
        return {
            "running": self.running,
            "blocks": self.blocks,
            "frames": self.frames,
            "lost_frames": self.lost_frames,
            "discontinuities": self.discontinuities,
            "errors": self.errors,
            "ended": self.ended,
            "last_error": self.last_error,
        }
