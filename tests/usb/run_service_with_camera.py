"""Run ``cfsr serve`` in this process with an emulated USB camera attached (umockdev).

Must itself run under ``umockdev-wrapper``. Usage::

    umockdev-wrapper python tests/usb/run_service_with_camera.py --dat X.dat [--paced]
        [--state-file S.json] [--faults "2.0:unplug:0.5,4.0:stall"] -- serve --usb --port P ...

Faults are injected at the given seconds after the camera appears; the model's counters are
written to ``--state-file`` every 0.2 s so a test can compare them with ``/api/status``.

It imports the project as installed in the interpreter that runs it (``./tasks`` installs it
in ``.venv``, editable), like every other entry point: run as a script, its own folder and
not the checkout is first on ``sys.path``, and a path inserted by hand would hide a broken
install.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path


def main() -> int:
    argv = sys.argv[1:]
    if "--" not in argv:
        print("usage: ... -- serve ARGS", file=sys.stderr)
        return 2
    cut = argv.index("--")
    ap = argparse.ArgumentParser()
    ap.add_argument("--dat", required=True)
    ap.add_argument("--paced", action="store_true")
    ap.add_argument("--rate", type=float, default=40000.0)
    ap.add_argument("--state-file")
    ap.add_argument("--faults", default="")
    a = ap.parse_args(argv[:cut])

    from cfsr.datfile import read_dat
    from cfsr_live.replay.camera_model import CameraModel
    from cfsr_live.replay.umockdev_camera import EmulatedCamera

    model = CameraModel(read_dat(a.dat), paced=a.paced, rate_hz=a.rate)
    cam = EmulatedCamera(model).start()
    t0 = time.monotonic()
    schedule = []
    for item in filter(None, a.faults.split(",")):
        parts = item.split(":")
        schedule.append((float(parts[0]), parts[1], float(parts[2]) if len(parts) > 2 else 0.2))
    stop = threading.Event()

    def background() -> None:
        pending = sorted(schedule)
        while not stop.wait(0.05):
            now = time.monotonic() - t0
            while pending and pending[0][0] <= now:
                _, kind, secs = pending.pop(0)
                model.inject(kind, seconds=secs)
            if a.state_file:
                with model.lock:
                    st = {
                        "expected_loss": model.expected_loss,
                        "dropped_total": model.dropped_total,
                        "mangled_frames": model.mangled_frames,
                        "blocks_sent": model.blocks_sent,
                        "frames_sent": model.frames_sent,
                        "events": list(model.events),
                        "faults_pending": len(model.faults) + len(pending),
                    }
                tmp = a.state_file + ".tmp"
                Path(tmp).write_text(json.dumps(st))
                os.replace(tmp, a.state_file)

    th = threading.Thread(target=background, daemon=True)
    th.start()
    from cfsr.cli import main as cli_main

    try:
        return cli_main(argv[cut + 1 :])
    finally:
        stop.set()
        th.join(2)
        cam.stop()


if __name__ == "__main__":
    sys.exit(main())
