"""Helpers shared by the offline sub-commands (argument parsing of times, params, inputs)."""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from cfsr.datfile import read_spikes
from cfsr.warmup import KernelProgress, cache_dir, measured_compile, warm_up


class TimeSpec:
    """Output steps from ``"300,500"`` or ranges ``"START:STOP[:STRIDE]"`` (STOP exclusive;
    an empty STOP means the end of each recording, e.g. ``"0::100"``)."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.parts: list[tuple[int, int | None, int]] = []
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            try:
                if ":" in part:
                    bits = part.split(":")
                    if len(bits) not in (2, 3):
                        raise ValueError
                    a = int(bits[0] or 0)
                    b = int(bits[1]) if bits[1] else None
                    st = int(bits[2]) if len(bits) == 3 and bits[2] else 1
                    if st <= 0:
                        raise argparse.ArgumentTypeError(f"stride must be positive in {part!r}")
                    self.parts.append((a, b, st))
                else:
                    t = int(part)
                    self.parts.append((t, t + 1, 1))
            except ValueError:
                raise argparse.ArgumentTypeError(
                    f"bad time {part!r}; use integers (steps) or START:STOP[:STRIDE]"
                ) from None
        if not self.parts:
            raise argparse.ArgumentTypeError(f"no times in {text!r}")

    def resolve(self, n_frames: int) -> list[int]:
        """The steps, each checked against the recording's ``n_frames`` steps before any list
        is made: ``0:100000000:1`` on a short file is one line, not gigabytes of step numbers
        first."""
        out: list[int] = []
        for a, b, st in self.parts:
            stop = n_frames if b is None else b
            if not (0 <= a < n_frames and a < stop <= n_frames):
                last = f"{stop - 1}" if stop - 1 > a else f"{a}"
                shown = f"{a}" if last == f"{a}" else f"{a}..{last}"
                raise ValueError(f"--times {self.text[:80]!r}: steps {shown} lie outside the "
                                 f"recording (0..{n_frames - 1})")
            out.extend(range(a, stop, st))
        if not out:
            raise ValueError(
                f"--times {self.text!r} selects no step of a {n_frames}-step recording"
            )
        return out


def parse_times(text: str) -> TimeSpec:
    return TimeSpec(text)


def parse_params(items: list[str] | None) -> dict[str, Any]:
    """``["window=32", "mode=centred"]`` -> dict of strings (coerced later by the method)."""
    params: dict[str, Any] = {}
    for item in items or []:
        for kv in item.split(","):
            if not kv.strip():
                continue
            if "=" not in kv:
                raise argparse.ArgumentTypeError(f"bad parameter {kv!r}; use NAME=VALUE")
            k, v = kv.split("=", 1)
            params[k.strip()] = v.strip()
    return params


def count_type(lo: int, hi: int, what: str, *, auto: bool = False):
    """An argparse type for a whole number of ``what`` in [lo, hi] (``auto``: the word
    'auto' is also taken, as None)."""
    alt = " or 'auto'" if auto else ""

    def parse(text: str) -> int | None:
        if auto and text.strip().lower() == "auto":
            return None
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: give a whole number{alt}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"{v} {what}: give {lo}..{hi}{alt}")
        return v

    return parse


def available_memory() -> int:
    """Bytes of memory the system can give without swapping (``MemAvailable``; the free
    physical pages where that is unknown)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 1 << 62  # unknown: no bound from here


def free_disk(path) -> tuple[int, str]:
    """Free bytes on the disk that would hold ``path``, and the folder measured (the nearest
    one that exists)."""
    import shutil
    from pathlib import Path

    folder = Path(path).absolute().parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return shutil.disk_usage(folder).free, str(folder)


def add_pool_arguments(p: argparse.ArgumentParser, workers_help: str) -> None:
    """``--workers`` (default None: the command's choice, see ``workers_help``) and
    ``--threads``: the reconstruction pool (:class:`cfsr.pool.FramePool`) of a command."""
    p.add_argument("--workers", type=count_type(1, 256, "workers", auto=True), default=None,
                   help=workers_help)
    p.add_argument("--threads", type=count_type(1, 256, "threads"), default=1,
                   help="numba/OpenCV threads in each reconstruction process (default 1: on a "
                   "small machine frames side by side beat threads on one frame)")


def add_input_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="spike recording: .dat (SpikeCV/Spike-Zoo layout) or .npz")
    g = p.add_argument_group("file layout (default: from the sidecar, else 400 x 250)")
    g.add_argument("--width", type=int, help="image width in pixels (without head columns)")
    g.add_argument("--height", type=int, help="image height in pixels")
    g.add_argument(
        "--head-cols", type=int, help="extra stored columns to drop (16 for 416-wide raw)"
    )
    g.add_argument(
        "--no-flipud",
        dest="flipud",
        action="store_false",
        default=None,
        help="rows are stored upright (e.g. SPCS simulator output)",
    )
    g.add_argument("--fliplr", action="store_true", default=None, help="columns stored mirrored")
    g.add_argument(
        "--allow-partial",
        action="store_true",
        help="drop an incomplete trailing frame instead of failing (reported)",
    )
    g.add_argument(
        "--key",
        metavar="NAME",
        help=".npz only: the array that holds the spikes (default: spk, or the only 3-D array)",
    )


def open_input(args: argparse.Namespace):
    key = getattr(args, "key", None)
    if str(args.input).lower().endswith(".npz"):
        return read_spikes(args.input, key=key)
    if key is not None:
        raise ValueError(f"--key {key}: only an .npz input has named arrays")
    return read_spikes(
        args.input,
        width=args.width,
        height=args.height,
        head_cols=args.head_cols,
        flipud=args.flipud,
        fliplr=args.fliplr,
        allow_partial=args.allow_partial,
    )


def jit_cache_location() -> str:
    """Where numba keeps the compiled kernels (:func:`cfsr.warmup.cache_dir`)."""
    return str(cache_dir())


def compile_first(method: str, *, quiet: bool = False) -> None:
    """Compile (or load from the cache) ``method``'s kernels in this process before the
    first frame, with a progress bar per kernel (name, n of N, CPU seconds against the
    measured ones) on stderr: on a machine's first use the wait is the compiler's, and says
    so, instead of a frame counter standing still. A cached method loads in about a second
    and shows nothing. Processes started afterwards (the pool) load what this one compiled."""
    from tqdm import tqdm

    table = measured_compile().get("methods", {}).get(method, {})
    bar = tqdm(total=len(table.get("kernels", [])) or None, unit="kernel",
               disable=quiet or None, file=sys.stderr, mininterval=0.5, delay=1.0,
               desc=f"compiling {method}")

    def kernel(line: str, tracker: KernelProgress) -> None:
        bar.set_description_str(f"compiling {line}", refresh=False)
        bar.update(max(0, tracker.n - bar.n))

    with bar:
        warm_up([method], kernels=kernel)
