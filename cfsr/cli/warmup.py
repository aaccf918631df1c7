"""``cfsr warmup``: compile the reconstruction kernels now, not at the first frame."""

from __future__ import annotations

import argparse
import sys

from cfsr.cli._common import jit_cache_location
from cfsr.methods import get_method
from cfsr.methods import methods as registered
from cfsr.warmup import KernelProgress, is_warm, measured_compile, warm_up


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = (
        "numba compiles each method's kernels the first time the method runs on a machine "
        "and caches them on disk (the measured CPU seconds per method are in the docs' "
        "results page); run this once after installing (or after an upgrade) so the first "
        "frame of 'cfsr reconstruct' or of the viewer does not wait. Each kernel is compiled "
        "once per machine: a process that needs one another process is compiling waits for "
        "it and loads the result. 'cfsr serve' does the same in the background."
    )
    p.add_argument(
        "--methods",
        "-m",
        help="comma-separated methods (default: all, CSR and CFSR first)",
    )
    p.add_argument(
        "--lines",
        action="store_true",
        help="one line per method on stdout ('NAME SECONDS'), for programs that follow it",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    p.add_argument(
        "--if-needed",
        action="store_true",
        help="do nothing when a complete warm-up of this code already finished here (how "
        "'./tasks' compiles at install time); methods named with --methods run regardless",
    )


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    names = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None
    try:  # names checked before any work, so a typo is one line
        names = None if names is None else [get_method(m).name for m in names]
    except ValueError as exc:
        print(f"cfsr warmup: error: {exc}", file=sys.stderr)
        return 2
    if args.if_needed and names is None and is_warm():
        return 0
    todo = names if names else list(registered())
    table = measured_compile().get("methods", {})
    # one tick per kernel of the measured table (a method missing from it counts as one)
    sizes = {m: len(table.get(m, {}).get("kernels", [])) or 1 for m in todo}
    bar = tqdm(total=sum(sizes.values()), unit="kernel", disable=args.quiet or args.lines,
               file=sys.stderr)
    ticks = dict.fromkeys(todo, 0)

    def kernel(line: str, tracker: KernelProgress) -> None:
        if args.lines:
            print(f"# {line}", flush=True)
        bar.set_description_str(line, refresh=False)
        if tracker.n > ticks[tracker.method] and ticks[tracker.method] < sizes[tracker.method]:
            bar.update(1)
            ticks[tracker.method] += 1

    def step(name: str, seconds: float) -> None:
        if args.lines:
            print(f"{name} {seconds:.3f}", flush=True)
        bar.update(sizes[name] - ticks[name])  # a cached method loads fewer kernels
        ticks[name] = sizes[name]
        bar.set_description_str(f"{name} ready in {seconds:.1f} s")

    try:
        took = warm_up(names, progress=step, kernels=kernel)
    finally:
        bar.close()
    if not args.lines and not args.quiet:
        print(f"cfsr warmup: {len(took)} method(s) ready in {sum(took.values()):.1f} s "
              f"(cached in {jit_cache_location()})", file=sys.stderr)
    return 0
