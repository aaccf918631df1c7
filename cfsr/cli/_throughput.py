"""``cfsr bench --throughput``: acquisition, streaming state and frame rates against real
time, measured in this run (ratios, never timing asserts)."""

from __future__ import annotations

import argparse
from typing import Any, NamedTuple

from cfsr._bits import pack_frames
from cfsr.bench import (
    core_forecast,
    dense_output,
    method_fps,
    method_scaling,
    pool_fps,
    streaming_state_rtf,
)
from cfsr.cli._extras import install_hint
from cfsr.cli.bench import GOALS, _machine
from cfsr.layout import Layout
from cfsr.methods import methods
from cfsr.pool import usable_cores
from cfsr.simulate import simulate


def _demo_packed(steps: int, height: int = 250, width: int = 400):
    sim = simulate("disk", steps, seed=0, height=height, width=width)
    return pack_frames(sim.spikes), Layout(width, height)


def _acquisition(args: argparse.Namespace) -> dict[str, Any]:
    """Acquisition into the ring, measured by the live layer (emulated USB camera when
    possible), which registers it in the ``cfsr.benchmarks`` entry-point group: this package
    never imports the layers above it."""
    from importlib.metadata import entry_points

    eps = [ep for ep in entry_points(group="cfsr.benchmarks") if ep.name == "acquisition"]
    if not eps:
        return {"error": "acquisition benchmark not installed"}
    try:
        acquisition_throughput = eps[0].load()
    except ImportError as exc:  # reported, not hidden
        return {"error": f"acquisition benchmark unavailable ({exc}): {install_hint('live')}"}
    return acquisition_throughput(seconds=_sizes(args).acquisition_s)


def _live(args: argparse.Namespace, bar) -> dict[str, Any]:
    """The live service's frame rate per method, CFSR tier and pool split, measured by the
    live layer (``cfsr.benchmarks`` entry point ``live``: this package never imports it)."""
    from importlib.metadata import entry_points

    eps = [ep for ep in entry_points(group="cfsr.benchmarks") if ep.name == "live"]
    if not eps:
        return {"error": "live benchmark not installed"}
    try:
        live_throughput = eps[0].load()
    except ImportError as exc:
        return {"error": f"live benchmark unavailable ({exc}): {install_hint('live')}"}
    sz = _sizes(args)
    configs = {"configs": sz.live_configs} if sz.live_configs else {}
    return live_throughput(seconds=sz.live_s, settle=sz.live_settle_s,
                           progress=lambda s: bar.set_description(s), **configs)


#: The live runs of a quick benchmark (method, CFSR tier, processes, threads each): CFSR's
#: default live setting and TFP, a smoke test of the path; the full run measures every tier
#: and split the live layer lists.
QUICK_LIVE = (("cfsr", "auto", 2, 1), ("tfp", "full", 1, 1))


#: Methods whose cost is measured at 1 and 2 threads (scaling stated, not guessed).
SCALING_METHODS = ("tfp", "csr", "cfsr")

#: Dense output (method, stride in steps, frames): outputs closer than the method's window,
#: as a slow-motion reconstruction asks for them (dense output shares work).
DENSE_OUTPUTS = (("tfstp", 1, 200), ("cfsr", 32, 8))

#: Pool splits (processes x threads each) measured for CFSR: the same cores, used as one
#: frame on every thread or as frames side by side.
POOL_SPLITS = ((1, 1), (1, 2), (2, 1))

#: Core counts the pool forecast is given for.
FORECAST_CORES = (4, 8, 16)


class Sizes(NamedTuple):
    """How much one throughput run measures: the demo's steps, the least seconds of each
    timing, the pool's frames per split, the acquisition's and each live run's seconds (and
    the live run's settling), the dense outputs, the live configurations (None: all)."""

    steps: int
    min_time: float
    pool_frames: int
    acquisition_s: float
    live_s: float
    live_settle_s: float
    dense: tuple[tuple[str, int, int], ...]
    live_configs: tuple[tuple[str, str, int, int], ...] | None


FULL = Sizes(4096, 1.0, 24, 5.0, 20.0, 3.0, DENSE_OUTPUTS, None)
QUICK = Sizes(2048, 0.3, 8, 2.0, 6.0, 3.0, DENSE_OUTPUTS, QUICK_LIVE)


def _sizes(args: argparse.Namespace) -> Sizes:
    return QUICK if args.quick else FULL


def throughput(args: argparse.Namespace, bar) -> dict[str, Any]:
    sz = _sizes(args)
    bar.set_description("simulating")
    packed, layout = _demo_packed(sz.steps)
    cores = usable_cores()
    splits = [(w, t) for w, t in POOL_SPLITS if w * t <= cores]
    bar.reset(
        total=3 + len(methods()) + len(SCALING_METHODS) + len(sz.dense) + len(splits)
    )
    bar.set_description("streaming state")
    rtf = {"streaming_state": streaming_state_rtf(packed, layout)}
    bar.update()
    bar.set_description("acquisition")
    acq = _acquisition(args)
    rtf["acquisition"] = acq.get("realtime_factor")
    bar.update()
    fps: dict[str, float] = {}
    detail: dict[str, Any] = {}
    for name in methods():
        bar.set_description(f"fps {name}")
        try:
            r = method_fps(packed, layout, name, min_time=sz.min_time)
        except ValueError as exc:
            detail[name] = {"error": str(exc)}
        else:
            fps[name] = r["fps"]
            detail[name] = r
        bar.update()
    scaling: dict[str, Any] = {}
    for name in SCALING_METHODS:
        bar.set_description(f"threads {name}")
        scaling[name] = method_scaling(
            packed, layout, name, threads=(1, 2), min_time=sz.min_time
        )
        bar.update()
    dense: dict[str, Any] = {}
    for name, stride, count in sz.dense:
        bar.set_description(f"dense {name}")
        dense[name] = dense_output(
            packed, layout, name, stride=stride, count=count, min_time=sz.min_time
        )
        bar.update()
    pool: dict[str, Any] = {"method": "cfsr", "cores": cores, "splits": []}
    for w, t in splits:
        bar.set_description(f"pool cfsr {w}x{t}")
        pool["splits"].append(
            pool_fps(packed, layout, "cfsr", workers=w, threads=t, frames=sz.pool_frames)
        )
        bar.update()
    one = next((r for r in pool["splits"] if r["workers"] == r["threads"] == 1), None)
    best = max(pool["splits"], key=lambda r: r["fps"], default=None)
    if one is not None and best is not None:
        widest = max(
            (r for r in pool["splits"] if r["threads"] == 1), key=lambda r: r["workers"]
        )
        pool["best"] = best
        pool["forecast"] = core_forecast(one["ms_per_frame"], widest, FORECAST_CORES)
    live = _live(args, bar)
    bar.update()
    return {
        "realtime_factor": rtf,
        "fps": fps,
        "scaling": scaling,
        "dense": dense,
        "pool": pool,
        "live": live,
        "acquisition": acq,
        "methods": detail,
        "goals": GOALS,
        "frame": f"{layout.width} x {layout.height}",
        "machine": _machine(),
    }


def print_throughput(res: dict[str, Any]) -> None:
    rtf, fps = res["realtime_factor"], res["fps"]
    print(
        f"throughput at {res['frame']} on {res['machine']['cores']} cores ({res['machine']['cpu']})"
    )
    print(f"  {'figure':28s} {'measured':>12s}   goal")
    for k in ("acquisition", "streaming_state"):
        v = rtf.get(k)
        shown = "n/a" if v is None else f"{v:.2f}x RT"
        print(f"  {k + ' (x real time)':28s} {shown:>12s}   {GOALS[k]}")
    acq = res.get("acquisition", {})
    for part, label in (("end_to_end", "end to end"), ("driver", "driver alone")):
        fig = acq.get(part) or {}
        if fig.get("realtime_factor") is not None:
            print(
                f"    {label}: {fig['realtime_factor']:.2f}x RT median of {fig.get('n_runs', 1)}"
                f" runs ({fig['realtime_factor_min']:.2f}-{fig['realtime_factor_max']:.2f}),"
                f" lost {fig.get('lost_frames', '?')} frames; {fig.get('source', '')}"
            )
        elif fig.get("error"):
            print(f"    {label}: {fig['error']}")
    if acq.get("source") and not acq.get("end_to_end"):
        print(f"    acquisition via {acq['source']}, lost {acq.get('lost_frames', '?')} frames")
    if acq.get("error"):
        print(f"    {acq['error']}")
    for k, v in fps.items():
        print(f"  {k + ' (fps, 400 x 250)':28s} {v:12.1f}   {GOALS.get(k, '')}")
    scaling = res.get("scaling", {})
    if scaling:
        print("  ms per frame by threads (numba + OpenCV), parallel fraction p (Amdahl),")
        print("  and the speed-up over 1 thread that p predicts at 8 / 16 threads:")
        for k, sc in scaling.items():
            ms = "  ".join(f"{t} thr {v:7.2f}" for t, v in sc["ms_per_frame"].items())
            p = sc.get("parallel_fraction")
            pred = sc.get("predicted_speedup", {})
            extra = (
                f"  p = {p:.2f}, {pred[8]:.1f}x / {pred[16]:.1f}x" if p is not None else ""
            )
            print(f"    {k:6s} {ms}{extra}")
    pool = res.get("pool", {})
    if pool.get("splits"):
        print(f"  {pool['method']} frames side by side (pool: processes x threads each):")
        for r in pool["splits"]:
            mem = r.get("rss_mb_per_worker")
            print(
                f"    {r['workers']} x {r['threads']}: {r['fps']:6.1f} fps"
                f" ({r['ms_per_frame']:6.1f} ms/frame)"
                + (f", {mem:.0f} MB resident per process" if mem else "")
            )
        fc = pool.get("forecast")
        if fc:
            print(
                f"    forecast, one process per core at this machine's efficiency "
                f"({fc['efficiency']:.2f}): "
                + ", ".join(f"{c} cores {v:.0f} fps" for c, v in fc["fps"].items())
            )
    live = res.get("live", {})
    if live.get("runs"):
        print(f"  live service on the demo (frames/s published, max_fps {live['max_fps']:g}):")
        for r in live["runs"]:
            tier = f" {r['quality']}" if r.get("quality") else ""
            head = f"    {r['method']}{tier} {r['workers']} x {r['threads']}:"
            if "error" in r:
                print(f"{head} {r['error']}")
                continue
            mix = (
                f", {r['full_frames']} full / {r['fast_frames']} fast"
                if r.get("quality") == "auto" else ""
            )
            print(
                f"{head} {r['fps']:5.1f} fps{mix}, compute {r['compute_ms']:.0f} ms,"
                f" latency {r['latency_ms']:.0f} ms, dropped {r['dropped_late']} late /"
                f" {r['dropped_order']} out of order"
            )
    elif live.get("error"):
        print(f"  live: {live['error']}")
    dense = res.get("dense", {})
    if dense:
        print("  dense output (one stream, outputs `stride` steps apart) against isolated frames:")
        for k, d in dense.items():
            print(
                f"    {k:6s} stride {d['stride']:3d}: {d['ms_per_frame']:7.2f} ms/frame,"
                f" isolated {d['isolated_ms_per_frame']:7.2f} ({d['speedup']:.1f}x)"
            )
