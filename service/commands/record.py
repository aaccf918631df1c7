"""``cfsr record``: record spikes from a source (USB camera, replay, simulator) to .dat + sidecar,
headless. The sidecar carries the drop map (frames lost and where). Needs the ``live`` extra for
the USB camera (pyusb); replay and simulator sources need only the base install."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from cfsr_live.driver.source import SourceEnded
from cfsr_live.service import sources
from cfsr_live.service.recorder import FolderDatWriter, size_cap

HELP = "record spikes from a source (USB camera, replay, simulator) to .dat + sidecar"


def add_arguments(p: argparse.ArgumentParser) -> None:
    # each kind of source adds its own flags (cfsr_live.service.sources); one must be given
    src = p.add_mutually_exclusive_group(required=True)
    for kind in sources.kinds():
        kind.add_select_argument(src, "record")
    for kind in sources.kinds():
        kind.add_arguments(p, "record")
    p.add_argument("-o", "--output", type=Path, required=True, help="output .dat")
    lim = p.add_mutually_exclusive_group(required=True)
    lim.add_argument("--frames", type=int, help="frames (steps) to record")
    lim.add_argument("--seconds", type=float, help="sensor seconds to record")
    p.add_argument("--max-bytes", type=int, metavar="N",
                   help="size cap of OUTPUT in bytes; recording stops cleanly there (default "
                   "and upper limit: the free space less 64 MB)")
    p.add_argument("--force", action="store_true", help="overwrite OUTPUT")


def _writer(out: Path, info, meta: dict, *, force: bool):
    """The output's writer: created exclusively and never through a link (a name that
    appeared meanwhile, or a dangling link planted there, is refused); ``force`` removes
    what is there first (the link itself, not what it points to)."""
    folder = out.resolve().parent if not out.is_symlink() else out.absolute().parent
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        if force:
            for name in (out.name, out.name + ".json"):
                try:
                    os.unlink(name, dir_fd=fd)
                except FileNotFoundError:
                    pass
        try:
            return FolderDatWriter(fd, out.name, info.layout, rate_hz=info.rate_hz, meta=meta,
                                   display_path=out)
        except FileExistsError:
            raise ValueError(f"{out} (or its sidecar) exists (use --force to overwrite)") from None
    finally:
        os.close(fd)


def run(args: argparse.Namespace) -> int:
    out: Path = args.output
    if os.path.lexists(out) and not args.force:
        raise ValueError(f"{out} exists (use --force to overwrite)")

    picked = [(k, s) for k in sources.kinds() if (s := k.spec_from_args(args)) is not None]
    if not picked:  # a flag given an empty value (--sim '')
        raise ValueError("no source given (see 'cfsr record --help')")
    kind, spec = picked[0]
    kind.check_installed()
    # a file or a simulation is converted as fast as it can be written (nothing skipped), a
    # recording once (no loop)
    src = kind.open(spec, sources.OpenOptions(loop=False, unpaced=True))
    with src:
        info = src.info
        want = args.frames if args.frames is not None else int(round(args.seconds * info.rate_hz))
        if want < 1:
            raise ValueError("nothing to record: ask for at least one frame")

        fb = info.layout.frame_bytes
        cap = size_cap(out.resolve().parent, args.max_bytes, fb, f"one frame ({fb} bytes)")
        if want * fb > cap:
            print(f"cfsr record: capped at {cap // fb} frames ({cap / 1e6:.1f} MB)",
                  file=sys.stderr)
            want = cap // fb
        drop_map: list[list[int | str]] = []
        got = 0
        t0 = time.monotonic()
        meta = {"source": info.to_dict()}
        if info.meta.get("gain"):
            meta["gain"] = info.meta["gain"]
        wr = _writer(out, info, meta, force=args.force)
        lost = 0
        try:
            next_index = None
            while got < want:
                try:
                    blk = src.read_block(1.0)
                except SourceEnded:
                    break
                if blk is None:
                    if time.monotonic() - t0 > 10 and got == 0:
                        raise OSError(f"{info.name}: no data within 10 s")
                    continue
                if blk.lost_before:
                    drop_map.append([blk.index - blk.lost_before, blk.lost_before, "source"])
                elif next_index is not None and blk.index != next_index:
                    drop_map.append([next_index, 0, "discontinuity"])
                data = blk.data[: want - got]
                wr.write_packed(data)
                got += data.shape[0]
                next_index = blk.index + blk.n_frames
            lost = sum(int(d[1]) for d in drop_map)
            wr.meta.update(
                {"drop_map": drop_map, "lost_frames": lost, "clean_capture": lost == 0}
            )
        finally:
            if wr.n_frames:
                wr.close()
            else:  # nothing came: no empty .dat (which nothing opens) is left behind
                wr.discard()
        if not got:
            raise OSError(f"{info.name}: no frame came; nothing written to {out}")
    dt = time.monotonic() - t0
    print(
        f"cfsr record: {got} frames ({got / info.rate_hz:.3f} s of sensor time) from "
        f"{info.name} to {out} in {dt:.2f} s; lost {lost} frames"
    )
    return 0
