"""``cfsr bench --compile``: what compiling the kernels costs, and what a frame costs after.

Each measurement runs in a new process on an empty numba cache, as on a fresh install: every
method together (the warm-up, in its order: kernels shared by several methods compile under
the first), then each method alone (what its first use costs), then the frame cost of CSR and
CFSR in the pool's one-thread mode on the cache the first run filled. The CPU seconds are the
processes' own (``time.process_time``), so other work on the machine changes them little.
``scripts/results.py`` turns the JSON into the docs' table and into the measured table the
progress bars estimate from (``cfsr/_compile_table.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from typing import Any

from cfsr.methods import methods as registered
from cfsr.warmup import WARM_ORDER

_PROFILE = "import json; from cfsr.warmup import compile_profile as p; print(json.dumps(p({})))"

_FRAMES = """
import json, time, numba, cv2, numpy as np
numba.set_num_threads(1); cv2.setNumThreads(1)
from cfsr._bits import pack_frames
from cfsr._heap import keep_freed_memory
from cfsr.layout import Layout
from cfsr.streaming import StreamingReconstructor
from cfsr.warmup import _moving_spikes
keep_freed_memory()
packed = pack_frames(_moving_spikes(1600, 250, 400, vanish=900))
out = {}
for m in ("csr", "cfsr"):
    sr = StreamingReconstructor(m, Layout(400, 250), slack=1600)
    sr.push(packed, 0)
    t = sr.latest_step()
    for k in range(3):
        sr.compute(t - k)
    cpu = []
    for k in range(FRAMES):
        c0 = time.process_time()
        sr.compute(t - 3 - k)
        cpu.append(1e3 * (time.process_time() - c0))
    out[m] = float(np.median(cpu))
print(json.dumps(out))
"""


#: the pool's start on a filled cache: two one-thread processes from spawn to their first CFSR
#: frame, less what a second round of frames takes once they run (the frames themselves)
_POOL = """
import json, time
from cfsr._bits import pack_frames
from cfsr.config import MethodConfig
from cfsr.layout import Layout
from cfsr.pool import FramePool
from cfsr.warmup import _moving_spikes
packed = pack_frames(_moving_spikes(1600, 250, 400, vanish=900))
layout = Layout(400, 250)
cfg = MethodConfig("cfsr", None)
before, after = cfg.window
n = len(packed)
def one_round(p, ts):
    for t in ts:
        a, b = t - before, t + after + 1
        p.submit(t, cfg, layout, packed[a:b], a, [(a, b, t)])
    while p.pending:
        p.collect()
starts = []
for _ in range(RUNS):
    t0 = time.perf_counter()
    with FramePool(2, 1, region_bytes=(before + after + 1) * layout.frame_bytes) as p:
        one_round(p, [n - after - 1, n - after - 9])
        first = time.perf_counter() - t0
        t1 = time.perf_counter()
        one_round(p, [n - after - 17, n - after - 25])
        frames = time.perf_counter() - t1
    starts.append(first - frames)
print(json.dumps({"pool_start_s": sorted(starts)[len(starts) // 2]}))
"""


def _child(code: str, cache: str) -> dict[str, Any]:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=3600)
    if r.returncode:
        raise RuntimeError(f"compile measurement failed: {r.stderr.strip()[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _spread(values: list[float]) -> dict[str, float]:
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def compile_bench(args: argparse.Namespace, bar: Any) -> dict[str, Any]:
    """The compile figures: ``runs`` repetitions (1 with ``--quick``, else 3) of every
    method together and each alone, on empty caches, and the one-thread frame cost."""
    known = list(registered())
    names = [m for m in WARM_ORDER if m in known] + [m for m in known if m not in WARM_ORDER]
    runs = 1 if args.quick else 3
    bar.reset(total=runs * (len(names) + 2))
    together, alone, frames, pool = [], {m: [] for m in names}, [], []
    for _ in range(runs):
        with tempfile.TemporaryDirectory(prefix="cfsr-compile-") as cache:
            bar.set_description_str("compile: all methods")
            together.append(_child(_PROFILE.format("None"), cache))
            bar.update()
            bar.set_description_str("frame cost, one thread")
            frames.append(_child(_FRAMES.replace("FRAMES", "5" if args.quick else "12"), cache))
            bar.set_description_str("pool start")
            pool.append(_child(_POOL.replace("RUNS", "1" if args.quick else "3"), cache))
            bar.update()
        for m in names:
            with tempfile.TemporaryDirectory(prefix="cfsr-compile-") as cache:
                bar.set_description_str(f"compile: {m} alone")
                alone[m].append(_child(_PROFILE.format(repr([m])), cache))
                bar.update()
    kernels: dict[str, list[float]] = {}
    for run in together:
        for k, v in run["kernels"].items():
            kernels.setdefault(k, []).append(v)
    return {
        "runs": runs,
        "all_cpu_s": _spread([r["cpu_s"] for r in together]),
        "in_all_cpu_s": {m: _spread([r["methods"][m]["cpu_s"] for r in together])
                         for m in names},
        "alone": {
            m: {"cpu_s": _spread([r["cpu_s"] for r in alone[m]]),
                "kernels": alone[m][-1]["methods"][m]["kernels"]}
            for m in names
        },
        "kernels_cpu_s": {k: statistics.median(v) for k, v in
                          sorted(kernels.items(), key=lambda kv: -statistics.median(kv[1]))},
        "frame_cpu_ms_one_thread": {m: _spread([f[m] for f in frames]) for m in ("csr", "cfsr")},
        "pool_start_s": _spread([r["pool_start_s"] for r in pool]),
    }


def print_compile(res: dict[str, Any]) -> None:
    a = res["all_cpu_s"]
    print(f"all methods, empty cache: {a['median']:.1f} CPU s "
          f"({a['min']:.1f}-{a['max']:.1f}, {res['runs']} run(s))")
    for m, row in res["alone"].items():
        c = row["cpu_s"]
        print(f"  {m:6s} alone {c['median']:6.1f} CPU s, {len(row['kernels'])} kernels")
    for m, f in res["frame_cpu_ms_one_thread"].items():
        print(f"  {m} frame, one thread: {f['median']:.1f} ms CPU")
    ps = res["pool_start_s"]
    print(f"  pool of 2 processes, start to ready: {ps['median']:.2f} s "
          f"({ps['min']:.2f}-{ps['max']:.2f})")
