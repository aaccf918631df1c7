"""``cfsr bench``: run time against error, throughput against real time, and the
skip-what-the-scene-doesn't-need sweep.

Every figure is a ratio measured in this run: to real time (40,000 steps/s), to display rate
(25 fps), or to a baseline timed in the same process. Nothing here asserts timings.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

from cfsr import plots  # read at call time (tests stand in for matplotlib)
from cfsr.api import reconstruct_outputs
from cfsr.batch import dask_client
from cfsr.bench import FULL_GRID, QUICK_GRID, format_rows, grid_specs
from cfsr.cli._extras import install_hint, require_extra
from cfsr.datfile import read_npz
from cfsr.display import to_display
from cfsr.evaluation import (
    evaluate,
    evaluate_reds,
    find_reds_pairs,
    parse_method_spec,
    split_method_specs,
)
from cfsr.metrics import cpbd, std_metric
from cfsr.simulate import SCENES

# the checkout's root, where ../shared/data may sit beside it (not found in a wheel install)
REPO = Path(__file__).resolve().parents[2]

GOALS = {
    "acquisition": ">= 2x real time in every run, zero loss",
    "streaming_state": ">= 1x real time",
    "tfp": ">= 100 fps",
    "csr": ">= 100 fps",
    "cfsr": ">= 25 fps (display rate)",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--quick", action="store_true", help="small grid and scenes: a smoke run under two minutes"
    )
    p.add_argument(
        "--throughput",
        action="store_true",
        help="measure throughput (acquisition, streaming state, fps per method) "
        "instead of the accuracy grid",
    )
    p.add_argument(
        "--sweep",
        action="store_true",
        help="cost and error of the adaptive pipeline against the always-full one "
        "(and against adaptive with its static gate off) as the dynamic area grows "
        "(static, ~10%%, ~30%%, full motion)",
    )
    p.add_argument(
        "--tiers",
        action="store_true",
        help="CFSR quality tiers: PSNR (whole, motion) of csr, full, fast and the candidate "
        "settings tried for fast on every simulated scene, and their CPU cost on the disk",
    )
    p.add_argument(
        "--dense",
        action="store_true",
        help="CFSR dense output (16 frames 32 steps apart, work carried from frame to frame) "
        "against the same frames isolated: PSNR and CPU cost per frame, per scene",
    )
    p.add_argument(
        "--defects",
        action="store_true",
        help="every method on a clean and on a defective sensor (hot, dead pixels, threshold "
        "spread), with and without the defect correction; the defect map's precision and "
        "recall over time; the correction's cost per frame",
    )
    p.add_argument(
        "--compile",
        action="store_true",
        help="what compiling the kernels costs on an empty cache (CPU s: every method, each "
        "alone, per kernel; 3 runs, 1 with --quick) and the frame cost after it in the "
        "pool's one-thread mode",
    )
    p.add_argument(
        "--methods", help="override the grid: comma-separated specs, e.g. tfi,tfp:window=32,cfsr"
    )
    p.add_argument("--scenes", help="simulated scenes (default: all; quick: disk,car)")
    p.add_argument("--steps", type=int, help="steps simulated per scene")
    p.add_argument(
        "--data",
        type=Path,
        help="folder with synthetic/reds_base and real/uhsr.npz (default: "
        "$CFSR_SHARED_DATA or ../shared/data beside the repository, if present)",
    )
    p.add_argument("--no-data", action="store_true", help="skip REDS and uhsr even if present")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("bench-out"),
        help="folder for accuracy.json, pareto.png, throughput.json, sweep.json",
    )
    p.add_argument(
        "--json",
        type=Path,
        metavar="PATH",
        help="also write this run's JSON here (throughput: {realtime_factor, fps})",
    )
    p.add_argument(
        "--cluster",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run the accuracy grid's scenes on Dask (local cluster or ADDRESS)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def _machine() -> dict[str, Any]:
    import numba

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "python": platform.python_version(),
    }


def _data_dir(args: argparse.Namespace) -> Path | None:
    if args.no_data:
        return None
    cands = (
        [args.data]
        if args.data
        else [
            Path(os.environ["CFSR_SHARED_DATA"]) if os.environ.get("CFSR_SHARED_DATA") else None,
            REPO.parent / "shared" / "data",
        ]
    )
    for c in cands:
        if c is not None and c.is_dir():
            return c
    if args.data:
        raise ValueError(f"{args.data}: no such data folder")
    return None


def _write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, default=float))


# --------------------------------------------------------------------------- accuracy grid


def _scene_rows(job: dict[str, Any]) -> list[dict[str, Any]]:
    """One scene's rows (runs in-process or on a Dask worker)."""
    return evaluate(
        job["specs"],
        [job["scene"]],
        steps=job["steps"],
        times=job["times"],
        height=job["height"],
        width=job["width"],
        seed=0,
    )


def _warm_up(specs: list[str]) -> None:
    """Compile every kernel once on a tiny scene so timings exclude JIT compilation."""
    evaluate(specs, ["disk"], steps=700, times=[600], height=48, width=64)


def _accuracy(args: argparse.Namespace, bar) -> dict[str, Any]:
    grid = (
        split_method_specs(args.methods)
        if args.methods
        else (QUICK_GRID if args.quick else FULL_GRID)
    )
    specs, skipped = grid_specs(grid)
    if not specs:
        raise ValueError(f"none of the methods {list(grid)} is available")
    scenes = (
        [s.strip() for s in args.scenes.split(",")]
        if args.scenes
        else (["disk", "car"] if args.quick else list(SCENES))
    )
    steps = args.steps or (1000 if args.quick else 2000)
    times = [steps // 2] if args.quick else [steps // 2 - 200, steps // 2, steps // 2 + 200]
    bar.set_description("warming up")
    _warm_up(specs)
    jobs = [
        {"specs": specs, "scene": s, "steps": steps, "times": times, "height": 250, "width": 400}
        for s in scenes
    ]
    rows: list[dict[str, Any]] = []
    bar.reset(total=len(jobs) + 2)
    bar.set_description("scenes")
    if args.cluster:
        from dask.distributed import as_completed

        client, local = dask_client(args.cluster)
        try:
            for fut in as_completed([client.submit(_scene_rows, j, pure=False) for j in jobs]):
                rows.extend(fut.result())
                bar.update()
        finally:
            client.close()
            if local:
                local.close()
    else:
        for j in jobs:
            rows.extend(_scene_rows(j))
            bar.update()
    data = _data_dir(args)
    noref: list[dict[str, Any]] = []
    if data is not None:
        reds = data / "synthetic" / "reds_base"
        if reds.is_dir() and find_reds_pairs(reds):
            bar.set_description("REDS")
            for r in evaluate_reds(reds, specs):
                r["scene"] = "reds:" + str(r.get("scene", r.get("file", "")))
                rows.append(r)
        bar.update()
        uhsr = data / "real" / "uhsr.npz"
        if uhsr.exists():
            bar.set_description("uhsr")
            noref = _uhsr_rows(uhsr, specs)
        bar.update()
    for r in rows:
        ms = r.get("ms_per_frame")
        r["display_rtf"] = (1000.0 / ms / 25.0) if ms else None
    return {"rows": rows, "noref": noref, "skipped": skipped, "steps": steps, "times": times}


def _uhsr_rows(path: Path, specs: list[str]) -> list[dict[str, Any]]:
    """STD and CPBD (no reference) of every method on the real uhsr capture, as in Table 1."""
    import numpy as np

    rec = read_npz(path)
    t = rec.n_frames // 2
    # one display gain for every method, as the paper's Table 1 compares them: the 99.5th
    # percentile of the whole capture's mean rate (a per-image gain would stretch noise)
    gain = float(np.percentile(rec.frames(0, rec.n_frames).mean(axis=0), 99.5)) or 1.0
    rows = []
    for s in specs:
        spec = parse_method_spec(s)
        t0 = time.perf_counter()
        out = reconstruct_outputs(rec, spec.name, [t], preset=spec.preset, params=spec.params)[0]
        dt = time.perf_counter() - t0
        img = to_display(out.rate, gain)
        rows.append(
            {
                "method": spec.label,
                "name": spec.name,
                "scene": "uhsr (real)",
                "std": std_metric(img),
                "cpbd": cpbd(img),
                "ms_per_frame": dt * 1e3,
            }
        )
    return rows


# --------------------------------------------------------------------------- CLI


#: the benchmark's parts besides the accuracy grid: (flag, module, runner, printer, JSON name);
#: each module is imported only when its part runs (numba, Dask, the service stay unloaded)
_PARTS = (
    ("throughput", "cfsr.cli._throughput", "throughput", "print_throughput", "throughput.json"),
    ("defects", "cfsr.cli._defects", "defects_bench", "print_defects", "defects.json"),
    ("compile", "cfsr.cli._compile", "compile_bench", "print_compile", "compile.json"),
    ("tiers", "cfsr.cli._sweep", "tiers", "print_tiers", "tiers.json"),
    ("dense", "cfsr.cli._sweep", "tiers", "print_tiers", "dense.json"),
    ("sweep", "cfsr.cli._sweep", "sweep", "print_sweep", "sweep.json"),
)


def _part(args: argparse.Namespace) -> tuple[Any, Any, str]:
    """The runner, the printer and the JSON name of the part ``args`` asks for (the accuracy
    grid when no part flag is given)."""
    for flag, module, runner, printer, name in _PARTS:
        if getattr(args, flag, False):
            mod = importlib.import_module(module)
            return getattr(mod, runner), getattr(mod, printer), name
    return _accuracy, lambda res: _print_accuracy(res, args), "accuracy.json"


def _print_accuracy(res: dict[str, Any], args: argparse.Namespace) -> None:
    """The accuracy grid's tables, and its Pareto plot where matplotlib is installed."""
    cols = [
        ("method", "method", ""),
        ("scene", "scene", ""),
        ("ms_per_frame", "ms/frame", ".1f"),
        ("display_rtf", "x RT@25fps", ".2f"),
        ("psnr_all", "PSNR all", ".2f"),
        ("psnr_motion", "PSNR motion", ".2f"),
        ("ssim", "SSIM", ".3f"),
        ("iou_coarse", "IoU coarse", ".2f"),
        ("iou_fine", "IoU fine", ".2f"),
    ]
    print(format_rows(res["rows"], cols))
    if res["noref"]:
        print()
        print(
            format_rows(
                res["noref"],
                [
                    ("method", "method", ""),
                    ("scene", "scene", ""),
                    ("std", "STD", ".2f"),
                    ("cpbd", "CPBD", ".3f"),
                    ("ms_per_frame", "ms/frame", ".1f"),
                ],
            )
        )
        print("CPBD rewards noise: read it beside STD and the PSNR table, never alone.")
    if res["skipped"]:
        print(f"skipped (not in this build): {', '.join(res['skipped'])}")
    # the tables and the JSON are the results; the plot is extra (cfsr[bench])
    if plots.have_matplotlib():
        png = plots.plot_pareto(
            [r for r in res["rows"] if not r["scene"].startswith("reds:")],
            str(args.out / "pareto.png"),
        )
        print(f"plot: {png}")
    else:
        print(f"plot skipped: matplotlib is not installed ({install_hint('bench')})")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    # checked before the run, not after minutes of work
    if getattr(args, "cluster", None):
        require_extra("cluster")
    args.out.mkdir(parents=True, exist_ok=True)
    runner, printer, name = _part(args)
    t_start = time.perf_counter()
    with tqdm(total=1, disable=args.quiet or None, file=sys.stderr, mininterval=0.5) as bar:
        res = runner(args, bar)
    res["seconds"] = time.perf_counter() - t_start
    res.setdefault("machine", _machine())
    _write_json(args.out / name, res)
    if args.json:
        _write_json(args.json, res)
    printer(res)
    print(
        f"JSON: {args.out / name}"
        + (f" and {args.json}" if args.json else "")
        + f"  ({res['seconds']:.0f} s)"
    )
    return 0
