"""Live frame rate for ``cfsr bench --throughput``: the service's own pipeline on the demo.

The runtime of ``cfsr serve`` (replay of the built-in demo, paced at real time -> ring ->
worker pool -> frame slot) runs without its web server, for each configuration asked for:
a method, CFSR's live tier (auto, full, fast) and the pool's processes x threads. Each run
counts the frames the worker published over ``seconds`` after a settling period (the first
frames of a configuration load kernels), so the figure is what a viewer receives at most (the
WebSocket sends every frame the slot gets to a client that keeps up). Registered in the
``cfsr.benchmarks`` entry-point group as ``live``; ``python -m cfsr_live.service.livebench`` runs it
alone.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from typing import Any

__all__ = ["LIVE_CONFIGS", "live_throughput"]

#: (method, CFSR tier, processes, threads each): the live figures the benchmark reports
LIVE_CONFIGS: tuple[tuple[str, str, int, int], ...] = (
    ("cfsr", "auto", 2, 1),
    ("cfsr", "full", 2, 1),
    ("cfsr", "full", 1, 2),
    ("cfsr", "fast", 2, 1),
    ("csr", "full", 2, 1),
    ("tfp", "full", 1, 1),
)


def _run_one(method: str, quality: str, workers: int, threads: int, seconds: float,
             settle: float, max_fps: float) -> dict[str, Any]:
    from cfsr_live.service.config import ConfigChange
    from cfsr_live.service.runtime import Runtime
    from cfsr_live.service.settings import Settings

    rt = Runtime(Settings(method="tfp", max_fps=max_fps, workers=workers, threads=threads,
                          warmup=False))
    rt.start()
    try:
        params = {"quality": quality} if method == "cfsr" else None
        rt.set_config(ConfigChange(method=method, params=params))
        assert rt.worker is not None
        end = time.monotonic() + settle + 120.0
        while time.monotonic() < end:  # the first frame of the method (kernels loaded)
            st = rt.worker.status(40_000.0).status
            if st.first_frame_s is None and st.frames_out > 0 and st.applied_version >= 1:
                break
            time.sleep(0.1)
        time.sleep(settle)
        s0 = rt.worker.status(40_000.0)
        t0 = time.monotonic()
        time.sleep(seconds)
        s1 = rt.worker.status(40_000.0)
        dt = time.monotonic() - t0
    finally:
        rt.stop()
    a, b = s0.status, s1.status
    return {
        "method": method,
        "quality": quality if method == "cfsr" else None,
        "workers": workers,
        "threads": threads,
        "max_fps": max_fps,
        "fps": (b.frames_out - a.frames_out) / dt,
        "full_frames": b.quality.full - a.quality.full,
        "fast_frames": b.quality.fast - a.quality.fast,
        "dropped_late": b.dropped_late - a.dropped_late,
        "dropped_order": b.dropped_order - a.dropped_order,
        "compute_ms": s1.compute_ms,
        "latency_ms": s1.latency_ms,
        "real_time_factor": b.real_time_factor,
        "seconds": dt,
    }


def live_throughput(
    seconds: float = 20.0,
    *,
    configs: Sequence[tuple[str, str, int, int]] = LIVE_CONFIGS,
    settle: float = 3.0,
    max_fps: float = 30.0,
    progress: Any = None,
) -> dict[str, Any]:
    """Frames per second the live service publishes on the demo, per configuration.

    Returns ``{"runs": [...], "seconds": ..., "max_fps": ...}``; each run: ``fps``, frames
    at each CFSR tier, frames dropped late or out of order, compute and latency (EMA, ms), the
    input's real-time factor. ``progress(label)`` is called before each run.
    """
    runs = []
    for method, quality, workers, threads in configs:
        if progress is not None:
            progress(f"live {method} {quality} {workers}x{threads}")
        try:
            runs.append(_run_one(method, quality, workers, threads, seconds, settle, max_fps))
        except Exception as exc:  # noqa: BLE001 - reported in the result, the rest still run
            runs.append({"method": method, "quality": quality, "workers": workers,
                         "threads": threads, "error": f"{type(exc).__name__}: {exc}"})
    return {"runs": runs, "seconds": seconds, "max_fps": max_fps}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="measured seconds per run")
    ap.add_argument("--max-fps", type=float, default=30.0)
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
    print(json.dumps(live_throughput(a.seconds, configs=configs, max_fps=a.max_fps,
                                     progress=lambda s: print(s, flush=True)), indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
