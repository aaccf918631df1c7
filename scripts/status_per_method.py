"""Start ``cfsr serve`` on the demo, switch through every method, and print /api/status figures.

Used for the live-service report: real-time factor, output fps, compute, latency and the drop
counters per stage, for each method, with one WebSocket viewer attached (as a browser would).
Run: ``.venv/bin/python scripts/status_per_method.py [--seconds 8] [--port 8765]``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys

import httpx
import websockets


async def _viewer(url: str, stop: asyncio.Event) -> None:
    async with websockets.connect(url, max_size=None) as ws:
        while not stop.is_set():
            try:
                await asyncio.wait_for(ws.recv(), 1.0)
            except TimeoutError:
                pass


async def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--port", type=int, default=8765)
    a = ap.parse_args()
    base = f"http://127.0.0.1:{a.port}"
    proc = subprocess.Popen([sys.executable, "-m", "cfsr", "serve", "--port", str(a.port),
                             "--log-level", "warning"])
    try:
        async with httpx.AsyncClient(base_url=base, timeout=10) as c:
            for _ in range(300):
                try:
                    if (await c.get("/healthz")).status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                await asyncio.sleep(0.5)
            methods = list((await c.get("/api/methods")).json())
            names = [m["name"] if isinstance(m, dict) else m for m in methods]
            stop = asyncio.Event()
            viewer = asyncio.create_task(_viewer(f"ws://127.0.0.1:{a.port}/ws", stop))
            rows = []
            for name in names:
                await c.put("/api/config", json={"method": name})
                await asyncio.sleep(3.0)  # let the worker apply it and compile once
                s0 = (await c.get("/api/status")).json()
                await asyncio.sleep(a.seconds)
                s1 = (await c.get("/api/status")).json()
                d = {k: s1["drops"][k] - s0["drops"][k]
                     for k in ("usb", "replay", "ring", "worker", "clients")}
                rows.append({"method": name, "rtf": s1["real_time_factor"],
                             "input": s1["input_steps_per_s"], "fps": s1["output_fps"],
                             "compute_ms": s1["compute_ms"], "latency_ms": s1["latency_ms"],
                             "drops": d, "window_s": a.seconds})
                print(json.dumps(rows[-1]), flush=True)
            stop.set()
            await viewer
    finally:
        proc.terminate()
        proc.wait(10)
    print(f"{'method':7s} {'RTF':>5s} {'input/s':>8s} {'fps':>6s} {'compute':>8s} "
          f"{'latency':>8s}  drops in {a.seconds:g} s (usb/replay/ring/worker skipped/clients)")
    for r in rows:
        d = r["drops"]
        print(f"{r['method']:7s} {r['rtf']:5.2f} {r['input']:8.0f} {r['fps']:6.1f} "
              f"{r['compute_ms']:6.0f}ms {r['latency_ms']:6.0f}ms  {d['usb']}/{d['replay']}/"
              f"{d['ring']}/{d['worker']}/{d['clients']}")
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
