"""The ``cfsr`` command line. Each sub-command lives in ``service/commands/<name>.py``.

Sub-command modules are imported lazily by name so ``cfsr info`` never loads FastAPI and
``cfsr serve`` never pays for the simulator until it needs it.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module, one-line help); the module defines ``add_arguments(parser)`` and ``run(args)``.
COMMANDS: dict[str, tuple[str, str]] = {
    "serve": ("service.commands.serve", "start the live service and browser viewer"),
    "reconstruct": ("service.commands.reconstruct", "reconstruct images from a spike file"),
    "info": ("service.commands.info", "describe a spike file: geometry, duration, rates, problems"),
    "simulate": ("service.commands.simulate", "simulate a scene to .dat with ground truth"),
    "evaluate": (
        "service.commands.evaluate",
        "PSNR/SSIM table of methods on scenes with ground truth",
    ),
    "record": ("service.commands.record", "record spikes from a source to .dat + sidecar"),
    "bench": ("service.commands.bench", "benchmark run time against error, and throughput"),
    "methods": ("service.commands.methods", "list reconstruction methods and their parameters"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cfsr",
        description="Spike-camera reconstruction: library, offline tools and live service. "
        "Time is in steps (1 step = 25 us at 40 kHz); rates are spikes per step.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (modname, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_module=modname)
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name != modname:
                raise
            p.set_defaults(_missing=True)
            continue
        mod.add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_missing", False):
        parser.error(f"command {args.command!r} is not available in this build")
    mod = importlib.import_module(args._module)
    from cfsr._heap import keep_freed_memory

    keep_freed_memory()  # long runs reuse freed frame arrays instead of faulting pages in
    try:
        return int(mod.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError) as exc:
        # Bad input is reported as one clear line, not a traceback.
        print(f"cfsr {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
