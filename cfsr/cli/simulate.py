"""``cfsr simulate``: a synthetic scene to ``.dat`` + sidecar + ground truth (``.gt.npz``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cfsr.cli._common import count_type
from cfsr.datfile import MAX_FRAMES, MAX_SIDE_PX
from cfsr.simulate import SCENES, Noise, check_dat_sizes, gt_path, make_scene, simulate_to_dat

# Kept in sync with cfsr.simulate.SCENES (checked by the tests); listed here so that
# ``cfsr --help`` does not import numba.
SCENE_NAMES = (
    "disk",
    "fan",
    "car",
    "static",
    "lowlight",
    "dim",
    "noisy",
    "blades",
    "vibrate",
    "vibrate_mover",
    "drift",
    "pan",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    # bounds only (the file format's: cfsr.datfile); what the machine has is checked in run()

    p.add_argument(
        "scene",
        help=f"scene to render: {', '.join(SCENE_NAMES)}",
    )
    p.add_argument(
        "--steps",
        "-n",
        type=count_type(1, MAX_FRAMES, "steps"),
        default=2000,
        help="frames to simulate (1 step = 25 us at 40 kHz); default 2000 (50 ms); the .dat "
        "must fit the free disk space",
    )
    p.add_argument(
        "--out",
        "-o",
        type=Path,
        required=True,
        metavar="OUT.dat",
        help="spike file to write; OUT.dat.json (sidecar) and OUT.gt.npz go beside it",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--height", type=count_type(1, MAX_SIDE_PX, "pixels"), default=250,
                   help="frame height in pixels (250)")
    p.add_argument("--width", type=count_type(1, MAX_SIDE_PX, "pixels"), default=400,
                   help="frame width in pixels (400); width x height at most 2**24")
    p.add_argument(
        "--gain",
        type=float,
        help="charge per step at intensity 1, in thresholds (default 0.5 x scene illumination, "
        "so white fires 0.5 spikes/step)",
    )
    p.add_argument(
        "--threshold", type=float, default=1.0, help="nominal firing threshold (default 1.0)"
    )
    p.add_argument(
        "--noise",
        help="sensor noise: a preset (none, spcs, shot, sensor, defects) and/or NAME=VALUE "
        "items, e.g. 'spcs' or 'spcs,electrons_per_spike=100' or 'dark_rate=0.002' "
        "(threshold_sd, gain_sd, dark_rate, dark_sd, electrons_per_spike, hot_fraction, "
        "hot_rate, dead_fraction); default: the scene's own (sensor for 'noisy', none "
        "otherwise)",
    )
    p.add_argument("--start", type=count_type(0, MAX_FRAMES, "steps"), default=0,
                   help=f"scene step of the first frame, 0..{MAX_FRAMES} (default 0)")
    p.add_argument(
        "--gt-every",
        type=count_type(0, MAX_FRAMES, "steps"),
        default=100,
        metavar="K",
        help="store ground truth (image, motion mask) every K frames; 0 for none (default "
        "100); it is held in memory until written, so it must fit half the memory available",
    )
    p.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a scene option, repeatable: e.g. vibrate: amplitude=3 hz=200 (px, Hz); "
        "drift: speed=0.02 angle=30 (px/step, degrees); pan: speed=0.01; disk: rpm=1000",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def _scene_options(items: list[str]) -> dict[str, float | bool]:
    """``KEY=VALUE`` scene options: numbers as floats, true/false as booleans."""
    out: dict[str, float | bool] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--option {item!r}: use KEY=VALUE")
        v = value.strip().lower()
        if v in ("true", "false"):
            out[key.strip()] = v == "true"
            continue
        try:
            out[key.strip()] = float(v)
        except ValueError:
            raise ValueError(
                f"--option {item!r}: the value must be a number or true/false"
            ) from None
    return out


def check_sizes(args: argparse.Namespace) -> None:
    """Refuse, before anything is allocated or written, a simulation the machine cannot hold
    (:func:`cfsr.simulate.check_dat_sizes`, which ``simulate_to_dat`` also applies), naming
    the flag, the value and the limit (ValueError: exit 2)."""
    check_dat_sizes(args.steps, args.height, args.width, args.out, start=args.start,
                    gt_every=args.gt_every,
                    names={k: "--" + k.replace("_", "-")
                           for k in ("steps", "height", "width", "start", "gt_every")})


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    name = str(args.scene).strip().lower()
    if name not in SCENES:
        raise ValueError(f"unknown scene {args.scene!r}; choices: {', '.join(SCENES)}")
    check_sizes(args)
    noise = Noise.parse(args.noise) if args.noise else None  # validate before any work
    scene = make_scene(name, height=args.height, width=args.width, **_scene_options(args.option))
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
    with tqdm(
        total=args.steps,
        unit="step",
        unit_scale=True,
        desc=f"simulate {name}",
        disable=args.quiet or None,
        file=sys.stderr,
        mininterval=0.5,
    ) as bar:
        path = simulate_to_dat(
            scene,
            args.steps,
            out,
            seed=args.seed,
            gt_every=args.gt_every or None,
            gain=args.gain,
            threshold=args.threshold,
            noise=noise,
            start=args.start,
            progress=bar.update,
        )
    size_mb = path.stat().st_size / 1e6
    print(
        f"{args.steps} steps of {name} ({scene.width} x {scene.height}) written to {path} "
        f"({size_mb:.1f} MB), sidecar {path.name}.json"
        + (f", ground truth {gt_path(path).name}" if args.gt_every else "")
    )
    return 0
