"""Acquisition throughput for ``cfsr bench --throughput``: source -> driver -> shared-memory ring.

The preferred source is the emulated USB camera, so the figure includes the real pyusb and
libusb paths. umockdev's preload must exist from process start, so when this process was not
started under ``umockdev-wrapper`` the measurement runs in a child process that is. Without
umockdev the replay device (memory-mapped ``.dat`` -> ring) is measured instead, and the result
says so. The camera streams unpaced, as fast as the path allows: the ratio to 40,000 frames/s
is the headroom over real time.

Run directly: ``umockdev-wrapper python -m service.benchmarks --seconds 5``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from cfsr.layout import STEP_RATE_HZ


def _recording(tmp: Path):
    from cfsr.datfile import read_dat, write_dat
    from replay.pattern import pattern_recording

    p = tmp / "bench.dat"
    write_dat(p, pattern_recording(2048))
    return read_dat(p)


def _drain(ring, seconds: float, source_counters) -> dict[str, Any]:
    """Consume the ring in a thread while the acquisition runs; count frames and gaps."""
    reader = ring.reader(start="oldest")
    got = {"frames": 0, "gaps": 0, "ring_lost": 0}
    stop = threading.Event()

    def consume() -> None:
        expect = None
        while not stop.is_set() or reader.backlog:
            blk = reader.poll()
            if blk is None:
                time.sleep(0.0005)
                continue
            if expect is not None and blk.index != expect:
                got["gaps"] += 1
            expect = blk.index + blk.n_frames
            if reader.release(blk):
                got["frames"] += blk.n_frames

    th = threading.Thread(target=consume, daemon=True)
    th.start()
    t0 = time.monotonic()
    while source_counters()["frames_delivered"] == 0 and time.monotonic() - t0 < 10:
        time.sleep(0.005)
    t1 = time.monotonic()
    f1 = source_counters()["frames_delivered"]
    time.sleep(seconds)
    t2 = time.monotonic()
    f2 = source_counters()["frames_delivered"]
    stop.set()
    th.join(10)
    got["ring_lost"] = int(getattr(reader, "lost_frames", 0))
    rate = (f2 - f1) / (t2 - t1)
    return {"frames_per_s": rate, "realtime_factor": rate / STEP_RATE_HZ, "consumer": got}


def _measure(src, frame_bytes: int, fpb: int, seconds: float) -> tuple[dict[str, Any], int]:
    """Acquire from an opened source into a fresh ring for ``seconds``; close both."""
    from driver.acquisition import Acquisition
    from shm.ring import SpikeRing

    ring = SpikeRing.create(64, fpb, frame_bytes)
    acq = Acquisition(src, ring)
    acq.start()
    try:
        res = _drain(ring, seconds, src.counters)
    finally:
        acq.stop()
        src.close()
        ring.close()
    return res, int(acq.lost_frames)


def _usb(seconds: float) -> dict[str, Any]:
    from driver.usb import UsbCameraSource
    from replay import umockdev_camera as U
    from replay.camera_model import CameraModel

    with tempfile.TemporaryDirectory() as d:
        rec = _recording(Path(d))
        model = CameraModel(rec, paced=False, fifo_frames=65536)
        with U.EmulatedCamera(model):
            src = UsbCameraSource(read_timeout_ms=500)
            src.open()
            block_bytes = int(src.block_bytes)
            res, lost = _measure(src, rec.layout.frame_bytes, src.fpb, seconds)
            with model.lock:
                dropped = int(getattr(model, "dropped_total", 0))
    res.update(
        source="emulated USB camera (umockdev, real libusb + pyusb), unpaced",
        lost_frames=lost + dropped,
        block_bytes=block_bytes,
    )
    return res


def _replay(seconds: float) -> dict[str, Any]:
    from replay.device import ReplayDevice

    with tempfile.TemporaryDirectory() as d:
        rec = _recording(Path(d))
        dev = ReplayDevice(rec, mode="fast", loop=True, block_frames=256)
        dev.open()
        res, lost = _measure(dev, rec.layout.frame_bytes, 256, seconds)
    res.update(
        source="replay device (memory-mapped .dat), unpaced; umockdev unavailable", lost_frames=lost
    )
    return res


def acquisition_throughput(seconds: float = 5.0) -> dict[str, Any]:
    """Measure acquisition into the ring; see the module notes for which source is used."""
    from replay import umockdev_camera as U

    ok, why = U.available()
    if ok:
        return _usb(seconds)
    wrapper = shutil.which("umockdev-wrapper")
    if wrapper:
        r = subprocess.run(
            [wrapper, sys.executable, "-m", "service.benchmarks", "--seconds", str(seconds)],
            capture_output=True,
            text=True,
            timeout=120 + seconds,
        )
        if r.returncode == 0 and r.stdout.strip():
            return json.loads(r.stdout.strip().splitlines()[-1])
        why = f"umockdev child failed ({r.returncode}): {r.stderr.strip()[-300:]}"
    res = _replay(seconds)
    res["note"] = why
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="acquisition throughput into the ring (JSON)")
    p.add_argument("--seconds", type=float, default=5.0)
    a = p.parse_args(argv)
    print(json.dumps(acquisition_throughput(a.seconds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
