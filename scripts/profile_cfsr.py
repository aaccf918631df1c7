"""Where one CFSR frame's time goes: stage timings on a simulated scene (400 x 250).

Usage: ``python scripts/profile_cfsr.py [scene] [--radius R] [--always-full] [--no-keep-heap]
[--set KEY=VALUE ...]``
(scene: disk, fan, car, static, lowlight; default disk; ``--radius`` sets the disk's radius,
240 covers the whole frame as in ``cfsr bench --sweep``). Times the newest computable step of
a 4096-step recording through the streaming reconstructor, as ``cfsr bench --throughput``
does, after warm-up calls, and prints the mean milliseconds of each pipeline stage over 20
frames.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import time

from cfsr._bits import pack_frames
from cfsr._heap import keep_freed_memory
from cfsr.layout import Layout
from cfsr.simulate import make_scene, simulate
from cfsr.streaming import StreamingReconstructor

#: (module of cfsr.methods.cfsr that calls it, name): the stages timed
STAGES = (
    ("pipeline", "history_scan"),
    ("history", "static_kernel"),
    ("history", "dynamic_kernel"),
    ("fusion", "atsr_fuse"),
    ("fine_mask", "history_objects"),
    ("fine_mask", "future_objects"),
    ("fine_mask", "fine_mask"),
    ("fine_mask", "still_pixels"),
    ("refinement", "pm_frames"),
    ("refinement", "patchmatch_fuse"),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default="disk")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument(
        "--no-keep-heap", action="store_true", help="leave glibc's malloc settings as they are"
    )
    ap.add_argument("--radius", type=int, help="disk radius, pixels (the sweep's 56/98/240)")
    ap.add_argument(
        "--always-full", action="store_true", help="adaptive=False: every stage on every pixel"
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a cfsr parameter (repeatable), e.g. mog_sides=past",
    )
    args = ap.parse_args()
    if not args.no_keep_heap:
        keep_freed_memory()
    spent: dict[str, float] = collections.defaultdict(float)

    def timed(name, fn):
        def run(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[name] += time.perf_counter() - t0

        return run

    for module, name in STAGES:
        mod = importlib.import_module(f"cfsr.methods.cfsr.{module}")
        setattr(mod, name, timed(name, getattr(mod, name)))
    opts = {} if args.radius is None else {"radius": args.radius}
    scene = make_scene(args.scene, height=250, width=400, **opts)
    sim = simulate(scene, 4096, seed=0)
    params: dict[str, object] = {"adaptive": not args.always_full}
    for item in args.set:
        key, _, value = item.partition("=")
        params[key] = value
    sr = StreamingReconstructor("cfsr", Layout(400, 250), params=params, slack=4096)
    sr.push(pack_frames(sim.spikes), 0)
    t = sr.latest_step()
    for _ in range(3):
        sr.compute(t)
    spent.clear()
    t0 = time.perf_counter()
    for _ in range(args.frames):
        sr.compute(t)
    total = (time.perf_counter() - t0) / args.frames
    print(f"{args.scene}: {total * 1e3:.1f} ms per frame ({1 / total:.1f} fps)")
    for _, name in STAGES:
        if name in spent:
            print(f"  {name:18s} {spent[name] / args.frames * 1e3:7.1f} ms")


if __name__ == "__main__":
    main()
