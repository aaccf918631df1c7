"""``cfsr info``: geometry, duration, spike-rate statistics and problems of a spike file."""

from __future__ import annotations

import argparse
import json
import sys
import warnings

from cfsr.cli._common import add_input_arguments, open_input
from cfsr.datfile import sidecar_path
from cfsr.defects import calibrate, estimate_map, map_of, save_map, write_to_sidecar
from cfsr.stats import recording_stats


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_input_arguments(p)
    p.add_argument(
        "--all", action="store_true", help="scan every frame (default: the first 40,000 = 1 s)"
    )
    p.add_argument(
        "--save-defects",
        action="store_true",
        help="store the hot/dead pixel map found here in the recording's sidecar (a replay "
        "then starts corrected)",
    )
    p.add_argument(
        "--export-defects",
        metavar="FILE",
        help="write the hot/dead pixel map found here as a calibration file (JSON), for "
        "'cfsr reconstruct --defects FILE'",
    )
    p.add_argument(
        "--flat-field",
        action="store_true",
        help="the recording is of uniform light: also measure every pixel's gain (threshold "
        "spread) over the scanned steps and keep it with the map (--save-defects, "
        "--export-defects), for every method's output to be divided by",
    )
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from tqdm import tqdm

    # info reports a partial tail as a problem rather than refusing the file
    args.allow_partial = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = open_input(args)
    lay = rec.layout
    # what is on disk, not whether the reader filled in metadata (a partial tail adds some)
    has_sidecar = rec.path is not None and sidecar_path(rec.path).is_file()
    provisional = has_sidecar and rec.meta.get("complete") is False
    limit = None if args.all else 40_000
    total = rec.n_frames if limit is None else min(rec.n_frames, limit)
    with tqdm(
        total=total,
        unit="frame",
        disable=args.quiet or None,
        file=sys.stderr,
        desc="scanning",
        mininterval=0.5,
    ) as bar:
        st = recording_stats(rec, max_frames=limit, progress=bar.update)
    info = {
        "path": rec.path,
        "width": lay.width,
        "height": lay.height,
        "head_cols": lay.head_cols,
        "flipud": lay.flipud,
        "fliplr": lay.fliplr,
        "frame_bytes": lay.frame_bytes,
        "n_frames": rec.n_frames,
        "rate_hz": rec.rate_hz,
        "duration_s": rec.duration_s,
        "gain": rec.gain,
        "sidecar": has_sidecar,
        "sidecar_final": has_sidecar and not provisional,
        **asdict(st),
        "defects": _defects(rec, args, total),
    }
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"file        {rec.path}")
    print(
        f"geometry    {lay.width} x {lay.height} px"
        + (f" (+{lay.head_cols} head columns)" if lay.head_cols else "")
        + f", {lay.frame_bytes} bytes/frame, rows {'upside down' if lay.flipud else 'upright'}"
        + (", mirrored" if lay.fliplr else "")
    )
    print(f"duration    {rec.n_frames} steps = {rec.duration_s * 1e3:.3f} ms at {rec.rate_hz:g} Hz")
    print(
        f"sidecar     {'yes' if has_sidecar else 'no'}"
        + (" (provisional: the recording did not end cleanly; frames counted from the size)"
           if provisional else "")
        + (f", display gain {rec.gain:g} spikes/step" if rec.gain else "")
    )
    print(f"spike rate  mean {st.mean_rate:.4f} spikes/step/pixel over {st.n_scanned} steps")
    print(
        f"per pixel   min {st.pixel_rate_min:.4f}  p1 {st.pixel_rate_p01:.4f}  "
        f"median {st.pixel_rate_median:.4f}  p99 {st.pixel_rate_p99:.4f}  "
        f"max {st.pixel_rate_max:.4f}"
    )
    print(
        f"            {st.dead_fraction:.2%} never fired, {st.saturated_fraction:.2%} saturated, "
        f"{st.empty_frames} empty frames"
    )
    d = info["defects"]
    print(f"defects     {d['hot']} hot, {d['dead']} dead pixels (found in the first "
          f"{d['steps']} steps" + (f"; the sidecar's map: {d['sidecar']['hot']} hot, "
                                   f"{d['sidecar']['dead']} dead" if d["sidecar"] else "")
          + ")" + "".join(f"; {what}" for what in d["written"]))
    if d["gain"]:
        g = d["gain"]
        print(f"gain        sd {g['sd']:.2%}, p1 {g['p1']:.3f}, p99 {g['p99']:.3f} (flat field, "
              f"{d['steps']} steps)")
    if st.problems:
        print("problems:")
        for pr in st.problems:
            print(f"  - {pr}")
    else:
        print("problems:   none found")
    return 0


def _defects(rec, args: argparse.Namespace, total: int) -> dict:
    """The hot/dead pixel map found in the first 2,000 steps, or with ``--flat-field`` the
    calibration of the ``total`` scanned steps (and the sidecar's map, if any); stored or
    exported as asked."""
    import numpy as np

    found = calibrate(rec, total) if args.flat_field else estimate_map(rec, 2000)[0]
    gain = None
    if found.gain is not None:
        g = found.gain.gain[~found.mask]
        gain = {"sd": float(g.std()), "p1": float(np.quantile(g, 0.01)),
                "p99": float(np.quantile(g, 0.99))}
    given = map_of(rec)
    written = []
    if args.save_defects:
        written.append(f"stored in {write_to_sidecar(rec, found)}")
    if args.export_defects:
        written.append(f"exported to {save_map(found, args.export_defects)}")
    return {
        "hot": found.n_hot,
        "dead": found.n_dead,
        "steps": found.steps,
        "sidecar": None if given is None else {"hot": given.n_hot, "dead": given.n_dead,
                                                "steps": given.steps, "source": given.source},
        "gain": gain,
        "written": written,
    }
