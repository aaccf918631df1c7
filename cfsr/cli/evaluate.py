"""``cfsr evaluate``: PSNR/SSIM (and mask IoU) of methods on simulated scenes, or on REDS."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cfsr.cli._common import parse_times
from cfsr.cli.simulate import SCENE_NAMES
from cfsr.evaluation import (
    evaluate,
    evaluate_reds,
    format_table,
    split_method_specs,
    summarize,
)
from cfsr.simulate import Noise


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--methods",
        "-m",
        nargs="+",
        metavar="SPEC",
        help="method specs NAME[:KEY=VALUE,...], comma or space separated, e.g. "
        "'tfi,tfp:window=32,mode=centred,tfp:window=64' (default: every registered method)",
    )
    p.add_argument(
        "--scenes",
        "-s",
        default=",".join(SCENE_NAMES),
        help=f"comma-separated scenes (default: all: {','.join(SCENE_NAMES)})",
    )
    p.add_argument(
        "--steps",
        "-n",
        type=int,
        default=1200,
        help="steps simulated per scene (default 1200 = 30 ms)",
    )
    p.add_argument(
        "--times",
        "-t",
        type=parse_times,
        help="output steps, e.g. 480,690,900 or 400:1000:200 (default: 3 steps between 40 %% "
        "and 75 %% of the run)",
    )
    p.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    p.add_argument("--height", type=int, default=250, help="frame height in pixels (250)")
    p.add_argument("--width", type=int, default=400, help="frame width in pixels (400)")
    p.add_argument(
        "--noise",
        help="simulator noise: none, spcs, shot, sensor, defects, or NAME=VALUE,... (default: each "
        "scene's own: sensor for 'noisy', none otherwise)",
    )
    p.add_argument(
        "--reds",
        type=Path,
        metavar="DIR",
        help="evaluate on REDS .dat files instead (DIR/spike/*.dat or DIR/*.dat with "
        "DIR/gt/*.png; ground truth = frame 150, brightness = rate / 0.6 * 255)",
    )
    p.add_argument("--json", type=Path, metavar="OUT.json", help="also write the rows as JSON")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    specs = split_method_specs(args.methods) if args.methods else None
    progress = not args.quiet and sys.stderr.isatty()
    if args.reds is not None:
        rows = evaluate_reds(args.reds, specs, progress=progress)
        title = f"REDS {args.reds}: ground truth frame 150, display = rate / 0.6 * 255"
        per = [r for r in rows if r["scene"] != "mean"]
        means = [r for r in rows if r["scene"] == "mean"]
    else:
        scenes = [s.strip() for s in str(args.scenes).split(",") if s.strip()]
        rows = evaluate(
            specs,
            scenes,
            steps=args.steps,
            times=args.times.resolve(args.steps) if args.times else None,
            seed=args.seed,
            height=args.height,
            width=args.width,
            noise=Noise.parse(args.noise) if args.noise else None,
            progress=progress,
        )
        t = rows[0]["times"] if rows else []
        title = (
            f"simulated {args.width} x {args.height}, {args.steps} steps, seed {args.seed}, "
            f"noise {args.noise or 'scene default'}, times {t}; display = rate / rate_scale * 255"
        )
        per = rows
        means = summarize(rows)
    print(title)
    print(format_table(per))
    if means:
        print()
        print("mean over " + ("files" if args.reds is not None else "scenes") + ":")
        print(format_table(means))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"title": title, "rows": rows}, indent=2))
        print(f"rows written to {args.json}", file=sys.stderr)
    return 0
