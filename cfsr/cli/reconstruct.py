"""``cfsr reconstruct``: images (and masks) from spike files, through the streaming path.

One file or a folder of recordings; in this process, or split into chunks on a Dask cluster
(``--cluster`` for a local one, ``--cluster tcp://HOST:8786`` for a running scheduler).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cfsr.batch import ChunkTask, plan_chunks, run_batch
from cfsr.cli._common import (
    add_input_arguments,
    add_pool_arguments,
    compile_first,
    open_input,
    parse_params,
    parse_times,
)
from cfsr.cli._extras import require_extra
from cfsr.defects import with_defects
from cfsr.display import auto_gain, to_display
from cfsr.methods import get_method, resolve_params
from cfsr.offline import stream_reconstruct


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_input_arguments(p)
    p.add_argument(
        "--method",
        "-m",
        default="tfp",
        help="reconstruction method (see 'cfsr methods'); default tfp",
    )
    p.add_argument(
        "--times",
        "-t",
        type=parse_times,
        required=True,
        help="output steps: 300,500 or ranges START:STOP:STRIDE (STOP exclusive; "
        "empty STOP = end of recording, e.g. 0::100)",
    )
    p.add_argument(
        "--out",
        "-o",
        type=Path,
        default=Path("out"),
        help="output folder: tSTEP.npy (float32 rates, spikes/step, H x W, upright) "
        "and tSTEP.png (8-bit preview); for a folder input, one sub-folder per "
        "recording; default ./out",
    )
    p.add_argument(
        "--param",
        "-p",
        action="append",
        metavar="NAME=VALUE",
        help="method parameter, repeatable (e.g. -p window=32 -p mode=centred)",
    )
    p.add_argument("--preset", help="named parameter preset, e.g. 'paper' or 'simulated'")
    p.add_argument(
        "--masks",
        action="store_true",
        help="also write each mask the method returns: tSTEP_mask_NAME.npy/.png",
    )
    p.add_argument(
        "--gain",
        type=float,
        help="rate (spikes/step) shown as white in previews/video; default: the "
        "sidecar's gain, else the 99.5th percentile of each image",
    )
    p.add_argument(
        "--defects",
        default="sidecar",
        metavar="sidecar|auto|off|FILE",
        help="hot and dead pixel correction before the method: 'sidecar' (default) uses the "
        "map in the recording's sidecar ('cfsr info --save-defects' puts one there) and "
        "leaves a recording without one as it is; 'auto' uses the sidecar's map, else one "
        "found in the first 2,000 steps; 'off' keeps the spikes as recorded; FILE is a "
        "calibration map (JSON, 'cfsr info --export-defects')",
    )
    p.add_argument(
        "--video",
        type=Path,
        metavar="OUT.mp4",
        help="also render the --times range of a single file to a video (mp4)",
    )
    p.add_argument("--fps", type=float, default=25.0, help="video frame rate (default 25)")
    p.add_argument("--no-files", action="store_true", help="with --video, skip the .npy/.png files")
    p.add_argument(
        "--cluster",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run chunks on Dask: a local cluster, or the scheduler at ADDRESS",
    )
    p.add_argument(
        "--chunk-steps",
        type=int,
        default=40_000,
        help="output steps per chunk task (default 40000 = 1 s of recording)",
    )
    add_pool_arguments(
        p,
        "reconstruction processes, each on its own frames (default 'auto': one per core when "
        "the frames are costly enough to pay for starting them; same output either way)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def _inputs(path: Path) -> list[Path]:
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in (".dat", ".npz"))
        if not files:
            raise ValueError(f"{path}: folder holds no .dat or .npz recordings")
        return files
    return [path]


def _read_kwargs(args: argparse.Namespace) -> dict:
    keys = ("width", "height", "head_cols", "flipud", "fliplr", "allow_partial")
    return {k: getattr(args, k) for k in keys if getattr(args, k) not in (None, False)}


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    if args.cluster:
        require_extra("cluster")
    params = parse_params(args.param)
    m = get_method(args.method)
    resolve_params(m, params, args.preset)  # validate before any work
    src = Path(args.input)
    files = _inputs(src)
    if args.video and len(files) > 1:
        raise ValueError("--video needs a single input file")
    tasks = []
    total = 0
    for f in files:
        args.input = str(f)
        rec = open_input(args)  # validates every file up front
        try:  # every step checked against the recording before a list of them is made
            times = args.times.resolve(rec.n_frames)
        except ValueError as exc:
            raise ValueError(f"{f}: {exc}") from None
        if args.video:
            _video(args, rec, m.name, times, params)
            if args.no_files:
                continue
        out = args.out if not src.is_dir() else args.out / f.stem
        total += len(set(times))
        for group in plan_chunks(times, args.chunk_steps):
            tasks.append(
                ChunkTask(
                    str(f),
                    m.name,
                    group,
                    str(out),
                    params,
                    args.preset,
                    args.masks,
                    args.gain,
                    _read_kwargs(args),
                    args.workers,
                    args.threads,
                    args.defects,
                )
            )
    bar = tqdm(
        total=total,
        unit="frame",
        desc=m.name,
        disable=args.quiet or None,
        file=sys.stderr,
        mininterval=0.5,
    )
    if tasks:
        compile_first(m.name, quiet=args.quiet)
    with bar:
        results = run_batch(tasks, cluster=args.cluster, progress=bar.update)
    n = sum(r["frames"] for r in results)
    if args.masks and not m.masks:
        print(f"note: method {m.name} returns no masks", file=sys.stderr)
    where = "" if not tasks else f" to {args.out}"
    on = f" on {len({r['worker_pid'] for r in results})} worker(s)" if args.cluster else ""
    if n:
        print(f"{n} frame(s) of {m.name} written{where}{on}")
    if args.video:
        print(f"video written to {args.video}")
    return 0


def _video(args: argparse.Namespace, rec, method: str, times: list[int], params: dict) -> None:
    import cv2
    from tqdm import tqdm

    args.video.parent.mkdir(parents=True, exist_ok=True)
    h, w = rec.layout.height, rec.layout.width
    writer = cv2.VideoWriter(
        str(args.video), cv2.VideoWriter_fourcc(*"mp4v"), args.fps, (w, h), False
    )
    if not writer.isOpened():
        raise OSError(f"{args.video}: cannot open a video writer (mp4v)")
    gain = args.gain if args.gain is not None else rec.gain
    compile_first(method, quiet=args.quiet)
    try:
        with tqdm(
            total=len(set(times)),
            unit="frame",
            desc=f"{method} video",
            disable=args.quiet or None,
            file=sys.stderr,
            mininterval=0.5,
        ) as bar:
            for _, out in stream_reconstruct(
                with_defects(rec, args.defects),
                method,
                times,
                params=params,
                preset=args.preset,
                workers=args.workers,
                threads=args.threads,
            ):
                if gain is None:
                    # one gain for the whole video, so brightness does not flicker
                    gain = auto_gain(out.rate)
                writer.write(to_display(out.rate, gain))
                bar.update()
    finally:
        writer.release()
