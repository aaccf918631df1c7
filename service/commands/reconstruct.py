"""``cfsr reconstruct``: images (and masks) from a spike file, through the streaming path."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.commands._common import add_input_arguments, open_input, parse_params, parse_times


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
        help="output steps, e.g. 300,500 or 100:2000:100 (START:STOP:STRIDE)",
    )
    p.add_argument(
        "--out",
        "-o",
        type=Path,
        default=Path("out"),
        help="output folder: tSTEP.npy (float32 rates, spikes/step, H x W, upright) "
        "and tSTEP.png (8-bit preview); default ./out",
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
        "--video",
        type=Path,
        metavar="OUT.mp4",
        help="render the --times range to a video (mp4) instead of/in addition to files",
    )
    p.add_argument("--fps", type=float, default=25.0, help="video frame rate (default 25)")
    p.add_argument("--no-files", action="store_true", help="with --video, skip the .npy/.png files")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image
    from tqdm import tqdm

    from cfsr.display import auto_gain, to_display
    from cfsr.methods import get_method, resolve_params
    from cfsr.offline import stream_reconstruct

    rec = open_input(args)
    if args.times is None:
        raise ValueError("--times is required (e.g. --times 300,500 or --times 0:4000:100)")
    params = parse_params(args.param)
    m = get_method(args.method)
    resolve_params(m, params, args.preset)  # validate before any work
    gain = args.gain if args.gain is not None else rec.gain
    write_files = not (args.video and args.no_files)
    if write_files:
        args.out.mkdir(parents=True, exist_ok=True)
    writer = None
    if args.video:
        import cv2

        args.video.parent.mkdir(parents=True, exist_ok=True)
        h, w = rec.layout.height, rec.layout.width
        writer = cv2.VideoWriter(
            str(args.video), cv2.VideoWriter_fourcc(*"mp4v"), args.fps, (w, h), False
        )
        if not writer.isOpened():
            raise OSError(f"{args.video}: cannot open a video writer (mp4v)")
        if gain is None:
            # One gain for the whole video, so brightness does not flicker frame to frame.
            first = next(
                stream_reconstruct(
                    rec, args.method, args.times[:1], params=params, preset=args.preset
                )
            )[1]
            gain = auto_gain(first.rate)
    times = sorted(set(args.times))
    bar = tqdm(
        total=len(times),
        unit="frame",
        desc=f"{m.name}",
        disable=args.quiet or None,
        file=sys.stderr,
        mininterval=0.5,
    )
    n = 0
    try:
        for t, out in stream_reconstruct(
            rec, args.method, times, params=params, preset=args.preset
        ):
            img8 = to_display(out.rate, gain)
            if write_files:
                np.save(args.out / f"t{t}.npy", out.rate.astype(np.float32))
                Image.fromarray(img8).save(args.out / f"t{t}.png")
                if args.masks:
                    for name, mask in out.masks.items():
                        np.save(args.out / f"t{t}_mask_{name}.npy", mask.astype(bool))
                        Image.fromarray(mask.astype(np.uint8) * 255).save(
                            args.out / f"t{t}_mask_{name}.png"
                        )
            if writer is not None:
                writer.write(img8)
            n += 1
            bar.update()
    finally:
        bar.close()
        if writer is not None:
            writer.release()
    if args.masks and not m.masks:
        print(f"note: method {m.name} returns no masks", file=sys.stderr)
    where = [str(args.out)] if write_files else []
    if args.video:
        where.append(str(args.video))
    print(f"{n} frame(s) of {m.name} written to {', '.join(where)}")
    return 0
