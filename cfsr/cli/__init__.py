"""The ``cfsr`` command line (``cfsr ...`` or ``python -m cfsr ...``).

The offline commands live here, in ``cfsr/cli/<name>.py``, and need nothing beyond the base
install. Commands of other layers (``serve`` and ``record`` from the live service) join through
the ``cfsr.commands`` entry-point group, the way pytest and Flask find plugin commands, so this
package never imports anything above it: an entry point names a module that defines ``HELP``
(one line), ``add_arguments(parser)`` and ``run(args) -> int``.

Dispatch is lazy: the parser lists every command from the tables here, by name and one-line
help, and imports only the module of the command that runs (to add its arguments and run it),
so a command module imports what it needs at its top, and ``cfsr info`` never loads FastAPI
or the benchmark. ``cfsr --help`` reads a plugin command's ``HELP`` from its source (a string
literal at its top level) and imports none of them.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import importlib.util
import sys
from collections.abc import Collection
from importlib.metadata import EntryPoint, PackageNotFoundError, entry_points
from importlib.metadata import version as dist_version
from pathlib import Path

import cfsr
from cfsr.cli._extras import EXTRAS, MissingExtra, install_hint, missing_extra_message

__all__ = ["COMMANDS", "PLUGIN_GROUP", "build_parser", "main"]

#: the offline commands: name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "reconstruct": ("cfsr.cli.reconstruct", "reconstruct images from a spike file"),
    "info": ("cfsr.cli.info", "describe a spike file: geometry, duration, rates, problems"),
    "simulate": ("cfsr.cli.simulate", "simulate a scene to .dat with ground truth"),
    "evaluate": ("cfsr.cli.evaluate", "PSNR/SSIM table of methods on scenes with ground truth"),
    "methods": ("cfsr.cli.methods", "list reconstruction methods and their parameters"),
    "bench": ("cfsr.cli.bench", "benchmark run time against error, and throughput"),
    "warmup": ("cfsr.cli.warmup", "compile the reconstruction kernels now (once per install)"),
}

#: entry-point group through which other layers add commands
PLUGIN_GROUP = "cfsr.commands"

#: commands an extra brings: shown (and explained) even when that extra's part is absent.
#: ``record`` is not one: the base install records from a file or the simulator, and only its
#: ``--usb`` source says which extra it needs.
EXTRA_COMMANDS: dict[str, tuple[str, str]] = {
    "serve": ("live", "start the live service and browser viewer"),
}


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line (``cfsr serve: error: ...``) with exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def version() -> str:
    """The installed distribution's version (the package's own when run from a checkout)."""
    try:
        return dist_version("cfsr")
    except PackageNotFoundError:
        return cfsr.__version__


def _plugins() -> dict[str, EntryPoint]:
    """name -> entry point of each command registered in :data:`PLUGIN_GROUP` (not imported)."""
    out: dict[str, EntryPoint] = {}
    for ep in entry_points(group=PLUGIN_GROUP):
        if ep.name not in COMMANDS:  # a plugin never shadows an offline command
            out.setdefault(ep.name, ep)
    return out


def _plugin_help(ep: EntryPoint) -> str | None:
    """A plugin command's ``HELP`` line, read from its module's source without running it (a
    string literal assigned at the top level); None where it is not written so."""
    try:
        spec = importlib.util.find_spec(ep.module)  # imports the parent packages only
    except ImportError:
        return None
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None
    try:
        tree = ast.parse(Path(spec.origin).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return None
    for node in tree.body:
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant)
                and isinstance(node.value.value, str)
                and any(isinstance(t, ast.Name) and t.id == "HELP" for t in node.targets)):
            return node.value.value
    return None


def build_parser(full: Collection[str] | None = None) -> argparse.ArgumentParser:
    """The ``cfsr`` parser. ``full``: the commands whose modules are imported to add their
    arguments (None: every command, as the documentation checks read every option); the
    others are listed by name and help only. With ``full`` empty (``cfsr --help``) a plugin
    command's help line is read from its source (imported only where it is not a literal);
    with a command named, only that one is imported."""
    parser = _Parser(
        prog="cfsr",
        description="Spike-camera reconstruction: library, offline tools and live service. "
        "Time is in steps (1 step = 25 us at 40 kHz); rates are spikes per step.",
        epilog="Extras: "
        + "; ".join(f"cfsr[{k}] adds {v[0]}" for k, v in EXTRAS.items())
        + ". 'cfsr COMMAND --help' explains each command.",
    )
    parser.add_argument("--version", action="version", version=f"cfsr {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (modname, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_module=modname)
        if full is None or name in full:
            importlib.import_module(modname).add_arguments(p)
    plugins = _plugins()
    for name in sorted(set(plugins) | set(EXTRA_COMMANDS)):
        extra, help_ = EXTRA_COMMANDS.get(name, (None, name))
        if name in plugins and full is not None and name not in full:
            listed = help_ if full else _plugin_help(plugins[name])  # listed, not run
            if listed is not None:
                sub.add_parser(name, help=listed).set_defaults(_module=plugins[name].module)
                continue
        try:
            mod = plugins[name].load() if name in plugins else None
            problem = None if mod is not None else "not installed"
        except ImportError as exc:
            mod, problem = None, str(exc)
        if mod is not None:
            help_ = getattr(mod, "HELP", help_)
            p = sub.add_parser(name, help=help_, description=help_)
            p.set_defaults(_module=mod.__name__)
            mod.add_arguments(p)
            continue
        why = problem + (f"; {install_hint(extra)}" if extra else "")
        help_ = f"{help_} (unavailable: {why})"
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_unavailable=why)
        p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # the command is the first word (the top level has no option that takes a value)
    command = argv[0] if argv and not argv[0].startswith("-") else None
    parser = build_parser(full=[command] if command else [])
    args = parser.parse_args(argv)
    prog = f"cfsr {args.command}"
    if getattr(args, "_unavailable", None):
        print(f"{prog}: error: this command is not available: {args._unavailable}",
              file=sys.stderr)
        return 2
    mod = importlib.import_module(args._module)
    # deferred: ctypes loads when a command runs, not for --help or the web process's version()
    from cfsr._heap import keep_freed_memory

    keep_freed_memory()  # long runs reuse freed frame arrays instead of faulting pages in
    try:
        return int(mod.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except MissingExtra as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:
        msg = missing_extra_message(exc)
        if msg is None:
            raise
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        # Bad input is reported as one clear line, not a traceback.
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
