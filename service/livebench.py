"""Live frame rate for ``cfsr bench --throughput``: the service's own pipeline on the demo.

The runtime of ``cfsr serve`` (replay of the built-in demo, paced at real time -> ring ->
worker pool -> frame slot) runs without its web server, for each configuration asked for:
a method, CFSR's live tier (auto, full, fast) and the pool's processes x threads. Each run
counts the frames the worker published over ``seconds`` after a settling period (the first
frames of a configuration load kernels), so the figure is what a viewer receives at most (the
WebSocket sends every frame the slot gets to a client that keeps up). Registered in the
``cfsr.benchmarks`` entry-point group as ``live``; ``python -m cfsr_live.service.livebench`` runs it
alone.

Each configuration runs idle and, with ``busy``, again beside that many CPU-bound processes
(a machine doing other work). Besides the rate, a run reports what a user on such a machine
sees: the drops by stage (``drops``: spike data lost on the link or by the recorder, a paced
replay's skips when acquisition lost to other work, and the display's skips: the worker's
ring reader overrun, or older steps it did not need), the share of computed frames shown,
and the output rate the service reports
(the hub's figure, sampled once a second) against the rate a client polling the frame slot
received.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

from cfsr_live.service.config import ConfigChange
from cfsr_live.service.hub import FrameHub
from cfsr_live.service.runtime import Runtime
from cfsr_live.service.settings import Settings

__all__ = ["BUSY_CONFIGS", "LIVE_CONFIGS", "cpu_hogs", "live_throughput"]

#: (method, CFSR tier, processes, threads each): the live figures the benchmark reports
LIVE_CONFIGS: tuple[tuple[str, str, int, int], ...] = (
    ("cfsr", "auto", 2, 1),
    ("cfsr", "full", 2, 1),
    ("cfsr", "full", 1, 2),
    ("cfsr", "fast", 2, 1),
    ("csr", "full", 2, 1),
    ("tfp", "full", 1, 1),
)
#: the configurations also run on a busy machine (the live default)
BUSY_CONFIGS: tuple[tuple[str, str, int, int], ...] = (("cfsr", "auto", 2, 1),)
#: CPU-bound processes beside the service in a busy run (on 2 cores: the machine is full)
BUSY_HOGS = 2


@contextlib.contextmanager
def cpu_hogs(n: int) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``n`` CPU-bound processes (a busy loop each, default priority) while the block runs."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                              stdin=subprocess.DEVNULL) for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


class _Client:
    """A viewer that keeps up: the service's hub polling the frame slot (as the server's fan-out
    does), sampling the output rate the hub reports once a second."""

    def __init__(self, slot: Any) -> None:
        self.hub = FrameHub(slot)
        self.reported: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-client", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_sample = time.monotonic() + 1.0
        while not self._stop.wait(self.hub.poll_s):
            self.hub.poll_once()
            if time.monotonic() >= next_sample:
                next_sample += 1.0
                self.reported.append(self.hub.fps())

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2)


#: the stages of ``GET /api/status`` ``drops`` a run reports (frames)
DROP_STAGES = ("usb", "replay", "recorder", "ring", "worker")


def _drops(rt: Any) -> dict[str, int]:
    """The service's drops by stage: ``usb`` and ``recorder`` lose spike data, ``replay`` is a
    paced replay that fell behind its clock (acquisition losing to other work), ``ring`` and
    ``worker`` are frames the display skipped."""
    d = rt.status().drops
    return {k: int(getattr(d, k)) for k in DROP_STAGES}


def _run_one(method: str, quality: str, workers: int, threads: int, seconds: float,
             settle: float, max_fps: float) -> dict[str, Any]:
    rt = Runtime(Settings(method="tfp", max_fps=max_fps, workers=workers, threads=threads,
                          warmup=False))
    rt.start()
    try:
        tier = quality if method == "cfsr" else None
        rt.set_config(ConfigChange(method=method, quality=tier))
        assert rt.worker is not None
        end = time.monotonic() + settle + 120.0
        while time.monotonic() < end:  # the first frame of the method (kernels loaded)
            st = rt.worker.status(40_000.0).status
            if st.first_frame_s is None and st.frames_out > 0 and st.applied_version >= 1:
                break
            time.sleep(0.1)
        time.sleep(settle)
        client = _Client(rt.slot)
        s0, c0, drops0 = rt.worker.status(40_000.0), rt.worker.stats(), _drops(rt)
        t0 = time.monotonic()
        time.sleep(seconds)
        client.stop()
        s1, c1, drops1 = rt.worker.status(40_000.0), rt.worker.stats(), _drops(rt)
        dt = time.monotonic() - t0
    finally:
        rt.stop()
    a, b = s0.status, s1.status
    shown = b.frames_out - a.frames_out
    dropped = (b.dropped_late - a.dropped_late) + (b.dropped_order - a.dropped_order)
    reported = client.reported[1:]  # the first second's window holds the settling frames
    return {
        "method": method,
        "quality": quality if method == "cfsr" else None,
        "workers": workers,
        "threads": threads,
        "max_fps": max_fps,
        "fps": (b.frames_out - a.frames_out) / dt,
        "full_frames": c1.shown_full - c0.shown_full,
        "fast_frames": c1.shown_fast - c0.shown_fast,
        "dropped_late": b.dropped_late - a.dropped_late,
        "dropped_order": b.dropped_order - a.dropped_order,
        "compute_ms": s1.compute_ms,
        "latency_ms": s1.latency_ms,
        "real_time_factor": b.real_time_factor,
        "reconstruction_nice": b.reconstruction_nice,
        "drops": {k: drops1[k] - drops0[k] for k in DROP_STAGES},
        "shown_share": shown / (shown + dropped) if shown + dropped else None,
        "received_fps": client.hub.frames_seen / dt,
        "reported_fps": sum(reported) / len(reported) if reported else None,
        "seconds": dt,
    }


def live_throughput(
    seconds: float = 20.0,
    *,
    configs: Sequence[tuple[str, str, int, int]] = LIVE_CONFIGS,
    settle: float = 3.0,
    max_fps: float = 30.0,
    busy: int = BUSY_HOGS,
    progress: Any = None,
) -> dict[str, Any]:
    """Frames per second the live service publishes on the demo, per configuration.

    Returns ``{"runs": [...], "seconds": ..., "max_fps": ..., "busy": ...}``; each run:
    ``fps``, frames at each CFSR tier, frames dropped late or out of order, compute and
    latency (EMA, ms), the input's real-time factor, the drops by stage,
    the share of computed frames shown, the received and reported output rates, and
    ``busy``: the CPU-bound processes beside it (each configuration runs idle; those of
    :data:`BUSY_CONFIGS` run again beside ``busy`` of them when ``busy`` > 0).
    ``progress(label)`` is called before each run.
    """
    runs = []
    for method, quality, workers, threads in configs:
        cfg = (method, quality, workers, threads)
        for hogs in (0, busy) if busy and cfg in BUSY_CONFIGS else (0,):
            if progress is not None:
                progress(f"live {method} {quality} {workers}x{threads} busy {hogs}")
            try:
                with cpu_hogs(hogs):
                    run = _run_one(method, quality, workers, threads, seconds, settle, max_fps)
            except Exception as exc:  # noqa: BLE001 - reported in the result, the rest run
                run = {"method": method, "quality": quality, "workers": workers,
                       "threads": threads, "error": f"{type(exc).__name__}: {exc}"}
            runs.append({**run, "busy": hogs})
    return {"runs": runs, "seconds": seconds, "max_fps": max_fps, "busy": busy}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="measured seconds per run")
    ap.add_argument("--max-fps", type=float, default=30.0)
    ap.add_argument("--busy", type=int, default=BUSY_HOGS,
                    help="run the live default again beside this many CPU-bound processes")
    ap.add_argument(
        "--config",
        action="append",
        metavar="METHOD:TIER:WORKERSxTHREADS",
        help="e.g. cfsr:auto:2x1 (repeatable; default: the benchmark's set)",
    )
    a = ap.parse_args(argv)
    configs = LIVE_CONFIGS
    if a.config:
        configs = []
        for c in a.config:
            m, q, wt = c.split(":")
            w, t = wt.lower().split("x")
            configs.append((m, q, int(w), int(t)))
    result = live_throughput(a.seconds, configs=configs, max_fps=a.max_fps, busy=a.busy,
                             progress=lambda s: print(s, flush=True))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
