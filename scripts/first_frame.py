"""Time to the first frame of a method after a switch in the live service, and the CPU the
server and its children spent until then.

Usage: ``python scripts/first_frame.py [--method cfsr] [--cache DIR] [--busy N] [--port P]``

Starts ``cfsr serve`` on the built-in demo with the background warm-up on, as a first start
after ``pip install`` does (``--cache`` an empty folder: nothing compiled; an existing one:
what it holds), waits for its first frame, switches to ``--method`` and polls
``/api/frame.png`` until a frame of that method comes. ``--busy N`` runs N CPU-bound
processes beside it meanwhile. Prints one JSON line: seconds from the switch to the frame,
what the viewer showed meanwhile (the ladder's rungs), the CPU seconds of the server's
process tree (live processes, and children it reaped, such as the finished warm-up), and
the machine's load.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

TICK = os.sysconf("SC_CLK_TCK")


def _cpu_tree(pid: int) -> float:
    """CPU seconds of ``pid`` and its live descendants, plus the children they reaped."""
    total = 0.0
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            stat = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            kids = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:
            continue
        # fields after the name: utime stime cutime cstime are the 12th-15th
        total += sum(int(x) for x in stat[11:15]) / TICK
        todo += [int(k) for k in kids]
    return total


def _get(url: str, timeout: float = 5.0) -> tuple[int, dict[str, str]]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            r.read()
            return r.status, dict(r.headers)
    except Exception:  # noqa: BLE001 - not up yet, or no frame yet
        return 0, {}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", default="cfsr")
    ap.add_argument("--cache", help="NUMBA_CACHE_DIR (default: a new empty folder)")
    ap.add_argument("--busy", type=int, default=0, help="CPU-bound processes beside it")
    ap.add_argument("--port", type=int, default=8765)
    ap.add_argument("--timeout", type=float, default=1800)
    args = ap.parse_args()
    cache = args.cache or tempfile.mkdtemp(prefix="cfsr-cache-")
    env = {**os.environ, "NUMBA_CACHE_DIR": cache, "CFSR_WARMUP": "1"}
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(args.busy)]
    base = f"http://127.0.0.1:{args.port}"
    t0 = time.monotonic()
    srv = subprocess.Popen([sys.executable, "-m", "cfsr", "serve", "--port", str(args.port)],
                           env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while _get(f"{base}/api/frame.png?wait=1")[0] != 200:
            if srv.poll() is not None or time.monotonic() - t0 > args.timeout:
                raise SystemExit("the server did not show a first frame")
            time.sleep(0.2)
        started = time.monotonic() - t0
        req = urllib.request.Request(f"{base}/api/config", method="PUT",
                                     data=json.dumps({"method": args.method}).encode(),
                                     headers={"Content-Type": "application/json"})
        t_switch = time.monotonic()
        urllib.request.urlopen(req, timeout=60).read()
        shown: dict[str, float] = {}
        while True:
            code, head = _get(f"{base}/api/frame.png?wait=0")
            m = head.get("X-Method") or head.get("x-method")
            if code == 200 and m and m not in shown:
                shown[m] = round(time.monotonic() - t_switch, 2)
            if m == args.method:
                break
            if time.monotonic() - t_switch > args.timeout:
                raise SystemExit(f"no {args.method} frame in {args.timeout} s")
            time.sleep(0.1)
        took = time.monotonic() - t_switch
        cpu = _cpu_tree(srv.pid)
    finally:
        srv.terminate()
        srv.wait(30)
        for h in hogs:
            h.kill()
    print(json.dumps({"method": args.method, "switch_to_frame_s": round(took, 2),
                      "server_first_frame_s": round(started, 2), "shown_after_s": shown,
                      "cpu_s_server_tree": round(cpu, 1), "busy": args.busy,
                      "load": os.getloadavg()[0], "cache": "given" if args.cache else "empty"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
