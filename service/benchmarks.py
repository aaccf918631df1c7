"""Acquisition throughput for ``cfsr bench --throughput``: camera -> driver -> shared-memory ring.

Two figures, each as x real time (40,000 frames/s of 400 x 250 one-bit frames, 500 MB/s) over
several runs (median, min, max and every run), with zero-loss accounting per run:

* ``driver``: the host side alone, with no emulator in the loop: pyusb,
  :class:`cfsr_live.driver.usb.UsbCameraSource` (header, payload CRC, loss accounting),
  :class:`cfsr_live.driver.acquisition.Acquisition` and the ring, fed by
  :class:`cfsr_live.replay.fake_usb.PreloadedUsbBackend` (blocks built once in memory; one
  ``memmove`` per read stands in for the kernel's copy to user memory and is reported apart, as
  ``transport_copy``).
* ``end_to_end``: the emulated USB camera under umockdev: the real libusb and pyusb against
  :mod:`cfsr_live.replay.umockdev_camera`, streaming unpaced. umockdev calls the emulator on its own
  thread of the measuring process, so each run also reports the CPU milliseconds per block of
  the driver's thread (pyusb, libusb and umockdev's client side, the driver, the ring write),
  the emulator's thread and the ring consumer: the two costs apart.
  umockdev's preload must exist from process start: when this process was not started under
  ``umockdev-wrapper``, this part runs in a child process that is. Without umockdev the replay
  device (memory-mapped ``.dat`` -> ring) stands in, and the result says so.

A run counts frames published into the ring per second of wall time after the first block,
and CPU milliseconds per block per thread; ``cpu_bound_realtime_factor`` is the block's
real-time duration over the driver thread's CPU per block, the figure one core given to the
driver would sustain (steadier than wall time where neighbours share the cores).
Its losses: frames the driver counted lost from the header indices (``driver_index_gaps``),
frames the device dropped (``device_dropped``), frames the ring's consumer lost to overruns
or torn reads (``ring``); ``lost_frames`` is their sum, over every run of both figures at the
top level. The consumer also checks that the indices it read follow on (``consumer.gaps``) and
that it read every frame published (``consumer.unaccounted``). The top-level
``realtime_factor`` and ``frames_per_s`` are the end-to-end median, as before.

Run directly: ``python -m cfsr_live.service.benchmarks --seconds 5 --runs 5`` (``--part driver`` or
``--part end-to-end`` for one figure).
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cfsr.datfile import read_dat, write_dat
from cfsr.layout import STEP_RATE_HZ
from cfsr_live.driver.acquisition import Acquisition
from cfsr_live.replay.device import ReplayDevice
from cfsr_live.replay.pattern import pattern_recording
from cfsr_live.shm.ring import SpikeRing

__all__ = [
    "REAL_TIME",
    "acquisition_throughput",
    "driver_throughput",
    "end_to_end_throughput",
    "summarize_runs",
]

#: what "real time" means here: the sensor's rate and its packed data rate (400 x 250)
REAL_TIME = {
    "frames_per_s": STEP_RATE_HZ,
    "bytes_per_s": STEP_RATE_HZ * 12_500,
    "frame": "400 x 250, one bit per pixel",
}
_RING_SLOTS = 64
_PRELOADED_BLOCKS = 16  # 51 MB of 256-frame blocks: more than the CPU caches hold


def _recording(tmp: Path):
    p = tmp / "bench.dat"
    write_dat(p, pattern_recording(2048))
    return read_dat(p)


def _thread_cpu(ident: int | None) -> float | None:
    """CPU seconds used so far by the thread with this ``threading`` ident (Linux)."""
    if ident is None:
        return None
    try:
        return time.clock_gettime(time.pthread_getcpuclockid(ident))
    except (AttributeError, OSError, OverflowError):
        return None


class _Consumer:
    """Reads the ring in a thread the way the worker does (poll, release), without copying:
    counts frames, torn or overrun blocks and index gaps."""

    def __init__(self, ring) -> None:
        self.reader = ring.reader(start="oldest")
        self.frames = 0
        self.gaps = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-consumer", daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def ident(self) -> int | None:
        return self._thread.ident

    def _run(self) -> None:
        reader, expect = self.reader, None
        while not self._stop.is_set() or reader.backlog:
            blk = reader.poll()
            if blk is None:
                time.sleep(0.0005)
                continue
            if expect is not None and blk.index != expect:
                self.gaps += 1
            expect = blk.index + blk.n_frames
            if reader.release(blk):
                self.frames += blk.n_frames

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)


def _run(
    src,
    seconds: float,
    *,
    emulator_ident: Callable[[], int | None] = lambda: None,
    copy_s: Callable[[], float] | None = None,
    device_dropped: Callable[[], int] = lambda: 0,
) -> dict[str, Any]:
    """One run: acquire from the opened ``src`` into a fresh ring for ``seconds`` of wall time
    after the first block, with a consumer reading the ring; close both."""
    ring = SpikeRing.create(_RING_SLOTS, src.info.max_block_frames, src.info.layout.frame_bytes)
    acq = Acquisition(src, ring)
    cons = _Consumer(ring)
    cons.start()
    acq.start()
    try:
        t0 = time.monotonic()
        while acq.frames == 0 and time.monotonic() - t0 < 10:
            time.sleep(0.002)
        if acq.frames == 0:
            raise RuntimeError(f"no block within 10 s ({src.counters()}, {acq.stats()})")
        idents = {"driver": acq.thread_ident, "emulator": emulator_ident(),
                  "consumer": cons.ident}

        def snap() -> tuple[float, int, int, dict[str, float | None], float, float]:
            cpu = {k: _thread_cpu(v) for k, v in idents.items()}
            return (time.perf_counter(), acq.frames, acq.blocks, cpu, time.process_time(),
                    copy_s() if copy_s else 0.0)

        a = snap()
        time.sleep(seconds)
        b = snap()
    finally:
        acq.stop()
        cons.stop()
        counters = src.counters()
        src.close()
        ring_lost = int(cons.reader.lost_frames)
        ring.close()
    dt, frames, blocks = b[0] - a[0], b[1] - a[1], max(1, b[2] - a[2])
    cpu = {k: (None if a[3][k] is None or b[3][k] is None else (b[3][k] - a[3][k]) / blocks * 1e3)
           for k in idents}
    cpu["process"] = (b[4] - a[4]) / blocks * 1e3
    if copy_s is not None:
        cpu["transport_copy"] = (b[5] - a[5]) / blocks * 1e3
    lost = {
        "driver_index_gaps": int(acq.lost_frames if counters.lost_frames is None
                                 else counters.lost_frames),
        "device_dropped": int(device_dropped()),
        "ring": ring_lost,
    }
    fps = frames / dt
    fpb = int(src.info.max_block_frames)
    drv = cpu.get("driver")
    return {
        "realtime_factor": fps / STEP_RATE_HZ,
        # the block's real-time duration over the driver thread's CPU per block: what one
        # core given to that thread alone would sustain (steadier than wall time on a shared
        # host, where neighbours take the CPU for whole runs)
        "cpu_bound_realtime_factor": None if not drv else fpb / STEP_RATE_HZ * 1e3 / drv,
        "frames_per_s": fps,
        "seconds": dt,
        "frames": frames,
        "blocks": blocks,
        "frames_per_block": fpb,
        "cpu_ms_per_block": cpu,
        "lost": lost,
        "lost_frames": sum(lost.values()),
        "consumer": {
            "frames": cons.frames,
            "gaps": cons.gaps,
            "unaccounted": int(acq.frames) - cons.frames - ring_lost,
        },
    }


def summarize_runs(runs: list[dict[str, Any]], source: str) -> dict[str, Any]:
    """Median, min and max of the runs' real-time factors (and the median CPU per block of
    each thread), every run kept, losses summed over the runs."""
    if not runs:
        raise ValueError("no runs to summarize")
    rtf = [r["realtime_factor"] for r in runs]
    keys = sorted({k for r in runs for k in r.get("cpu_ms_per_block", {})})
    cpu = {}
    for k in keys:
        vals = [r["cpu_ms_per_block"][k] for r in runs
                if r.get("cpu_ms_per_block", {}).get(k) is not None]
        cpu[k] = statistics.median(vals) if vals else None
    med = statistics.median(rtf)
    bound = [r["cpu_bound_realtime_factor"] for r in runs
             if r.get("cpu_bound_realtime_factor") is not None]
    return {
        "source": source,
        "realtime_factor": med,
        "realtime_factor_min": min(rtf),
        "realtime_factor_max": max(rtf),
        "frames_per_s": med * STEP_RATE_HZ,
        "n_runs": len(runs),
        "cpu_ms_per_block": cpu,
        "cpu_bound_realtime_factor": statistics.median(bound) if bound else None,
        "lost_frames": sum(int(r["lost_frames"]) for r in runs),
        "consumer": {
            "frames": sum(r["consumer"]["frames"] for r in runs),
            "gaps": sum(r["consumer"]["gaps"] for r in runs),
            "unaccounted": sum(r["consumer"]["unaccounted"] for r in runs),
        },
        "runs": runs,
    }


def _per_run(seconds: float, runs: int) -> float:
    return max(0.5, seconds / max(1, runs))


def driver_throughput(seconds: float = 5.0, runs: int = 5, *, recording=None) -> dict[str, Any]:
    """The driver alone: preloaded blocks -> pyusb -> UsbCameraSource -> Acquisition -> ring.

    ``seconds`` is shared by the ``runs`` (at least 0.5 s each).
    """
    # deferred: needs the live extra (pyusb, isal); the replay part runs without it
    from cfsr_live.driver.usb import UsbCameraSource
    from cfsr_live.replay.camera_model import CameraModel
    from cfsr_live.replay.fake_usb import PreloadedUsbBackend

    with tempfile.TemporaryDirectory() as d:
        rec = recording if recording is not None else _recording(Path(d))
        out = []
        for _ in range(runs):
            backend = PreloadedUsbBackend(CameraModel(rec), blocks=_PRELOADED_BLOCKS)
            src = UsbCameraSource(backend=backend, read_timeout_ms=500)
            src.open()
            out.append(_run(src, _per_run(seconds, runs), copy_s=lambda b=backend: b.copy_s))
    return summarize_runs(
        out,
        "driver alone: pyusb + UsbCameraSource + Acquisition + ring, fed from "
        f"{_PRELOADED_BLOCKS} preloaded blocks (no emulator)",
    )


def _usb(seconds: float, runs: int) -> dict[str, Any]:
    # deferred: needs the live extra (pyusb, isal); the replay part runs without it
    from cfsr_live.driver.usb import UsbCameraSource
    from cfsr_live.replay import umockdev_camera as U
    from cfsr_live.replay.camera_model import CameraModel

    out = []
    block_bytes = 0
    with tempfile.TemporaryDirectory() as d:
        rec = _recording(Path(d))
        for _ in range(runs):
            model = CameraModel(rec, paced=False, fifo_frames=65536)
            with U.EmulatedCamera(model) as cam:
                src = UsbCameraSource(read_timeout_ms=500)
                src.open()
                block_bytes = int(src.block_bytes)

                def dropped(m=model) -> int:
                    with m.lock:
                        return int(m.dropped_total)

                out.append(_run(src, _per_run(seconds, runs),
                                emulator_ident=lambda c=cam: c.handler.thread_ident,
                                device_dropped=dropped))
    res = summarize_runs(out, "emulated USB camera (umockdev, real libusb + pyusb), unpaced")
    res["block_bytes"] = block_bytes
    return res


def _replay(seconds: float, runs: int) -> dict[str, Any]:
    out = []
    with tempfile.TemporaryDirectory() as d:
        rec = _recording(Path(d))
        for _ in range(runs):
            dev = ReplayDevice(rec, mode="unpaced", loop=True, block_frames=256)
            dev.open()
            out.append(_run(dev, _per_run(seconds, runs)))
    return summarize_runs(
        out, "replay device (memory-mapped .dat), unpaced; umockdev unavailable"
    )


def end_to_end_throughput(seconds: float = 5.0, runs: int = 5) -> dict[str, Any]:
    """The emulated USB camera -> driver -> ring (see the module notes for the fallbacks)."""
    # deferred: needs the live extra (isal); the replay fallback runs without it
    from cfsr_live.replay import umockdev_camera as U

    ok, why = U.available()
    if ok:
        return _usb(seconds, runs)
    wrapper = shutil.which("umockdev-wrapper")
    if wrapper:
        r = subprocess.run(
            [wrapper, sys.executable, "-m", "cfsr_live.service.benchmarks", "--part", "end-to-end",
             "--seconds", str(seconds), "--runs", str(runs)],
            capture_output=True,
            text=True,
            timeout=120 + 3 * seconds + 10 * runs,
        )
        if r.returncode == 0 and r.stdout.strip():
            return json.loads(r.stdout.strip().splitlines()[-1])
        why = f"umockdev child failed ({r.returncode}): {r.stderr.strip()[-300:]}"
    res = _replay(seconds, runs)
    res["note"] = why
    return res


def _fmt(s: dict[str, Any]) -> str:
    return (f"{s['realtime_factor']:.2f}x ({s['realtime_factor_min']:.2f}-"
            f"{s['realtime_factor_max']:.2f} in {s['n_runs']} runs)")


def acquisition_throughput(seconds: float = 5.0, runs: int = 5) -> dict[str, Any]:
    """Both figures (module notes); the top level keeps the end-to-end keys of old."""
    e2e = end_to_end_throughput(seconds, runs)
    try:
        drv = driver_throughput(seconds, runs)
    except Exception as exc:  # noqa: BLE001 - reported beside the end-to-end figure
        drv = {"error": f"{type(exc).__name__}: {exc}", "lost_frames": 0}
    res: dict[str, Any] = {
        "realtime_factor": e2e["realtime_factor"],
        "realtime_factor_min": e2e["realtime_factor_min"],
        "realtime_factor_max": e2e["realtime_factor_max"],
        "frames_per_s": e2e["frames_per_s"],
        "lost_frames": int(e2e["lost_frames"]) + int(drv.get("lost_frames", 0)),
        "consumer": e2e["consumer"],
        "source": f"{e2e['source']}: {_fmt(e2e)}; "
        + (f"driver alone (preloaded blocks, no emulator): {_fmt(drv)}" if "error" not in drv
           else f"driver alone failed: {drv['error']}"),
        "real_time": REAL_TIME,
        "end_to_end": e2e,
        "driver": drv,
    }
    for k in ("block_bytes", "note"):
        if k in e2e:
            res[k] = e2e[k]
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="acquisition throughput into the ring (JSON)")
    p.add_argument("--seconds", type=float, default=5.0, help="per figure, shared by the runs")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--part", choices=("both", "driver", "end-to-end"), default="both")
    a = p.parse_args(argv)
    if a.runs < 1 or not a.seconds > 0:
        p.error("--runs must be >= 1 and --seconds > 0")
    fn = {"both": acquisition_throughput, "driver": driver_throughput,
          "end-to-end": end_to_end_throughput}[a.part]
    print(json.dumps(fn(a.seconds, a.runs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
