"""The layer rule, read from the source: arrows point down only (service -> replay -> driver
-> cfsr, with shm beside them: generic shared memory that imports nothing of ours), and
nothing imports service. Every module of every layer is parsed with ``ast``, imports inside
functions included, so a deferred import cannot hide an arrow that points up. The run-time
checks elsewhere cover only what ``import cfsr`` happens to load."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import tomllib
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[1]

#: what each layer may import of ours (besides itself)
ALLOWED: dict[str, frozenset[str]] = {
    "cfsr": frozenset(),
    "shm": frozenset(),
    "driver": frozenset({"cfsr", "shm"}),
    "replay": frozenset({"cfsr", "shm", "driver"}),
    "service": frozenset({"cfsr", "shm", "driver", "replay", "viewer"}),
}


def _layer_packages() -> dict[str, str]:
    """Installed package name -> layer (its folder), from pyproject.toml's package-dir: the
    folders install under ``cfsr_live`` (``service`` -> ``cfsr_live.service``)."""
    with open(REPO / "pyproject.toml", "rb") as f:
        dirs = tomllib.load(f)["tool"]["setuptools"]["package-dir"]
    names = {pkg: folder for pkg, folder in dirs.items() if folder in ALLOWED}
    names["cfsr"] = "cfsr"
    return names


PACKAGES = _layer_packages()


class Import(NamedTuple):
    path: Path
    line: int
    target: str  # the absolute module name imported
    in_function: bool


def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    folder = parts[0]
    pkg = next(p for p, f in PACKAGES.items() if f == folder)
    tail = parts[1:]
    if tail and tail[-1] == "__init__":
        tail = tail[:-1]
    return ".".join([pkg, *tail])


def _imports(path: Path, text: str | None = None) -> Iterator[Import]:
    """Every import of ``path`` (its source ``text`` if given), resolved to an absolute name."""
    tree = ast.parse(path.read_text() if text is None else text, str(path))
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]

    def visit(node: ast.AST, in_function: bool) -> Iterator[Import]:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef,
                                                      ast.Lambda))
            if isinstance(child, ast.Import):
                for a in child.names:
                    yield Import(path, child.lineno, a.name, in_function)
            elif isinstance(child, ast.ImportFrom):
                if child.level:  # relative: resolve against this module's package
                    base = package.split(".")
                    base = base[: len(base) - (child.level - 1)]
                    mod = ".".join([*base, child.module] if child.module else base)
                else:
                    mod = child.module or ""
                yield Import(path, child.lineno, mod, in_function)
            yield from visit(child, inner)

    yield from visit(tree, False)


def _layer_of(module: str) -> str | None:
    best = max((p for p in PACKAGES if module == p or module.startswith(p + ".")),
               key=len, default=None)
    if best is not None:
        return PACKAGES[best]
    if module == "cfsr_live" or module.startswith("cfsr_live."):
        return module.split(".")[1] if "." in module else "cfsr_live"
    return None


def _sources() -> list[Path]:
    return sorted(p for layer in ALLOWED for p in (REPO / layer).rglob("*.py"))


def _own_imports() -> list[tuple[str, Import, str]]:
    """(layer of the importing module, import, layer imported) for each import of ours."""
    out = []
    for path in _sources():
        layer = path.relative_to(REPO).parts[0]
        for imp in _imports(path):
            target = _layer_of(imp.target)
            if target is not None:
                out.append((layer, imp, target))
    return out


def test_the_parser_sees_every_layer_and_imports_inside_functions():
    """The test reads what it claims to: modules of every layer that imports ours, and
    deferred imports among them."""
    found = _own_imports()
    assert {layer for layer, _, _ in found} >= {"cfsr", "driver", "replay", "service"}
    assert any(imp.in_function for _, imp, _ in found)
    assert {p.relative_to(REPO).parts[0] for p in _sources()} == set(ALLOWED)


def test_no_import_points_up():
    wrong = [
        f"{imp.path.relative_to(REPO)}:{imp.line}: {layer} imports {imp.target}"
        f"{' (inside a function)' if imp.in_function else ''}"
        for layer, imp, target in _own_imports()
        if target != layer and target not in ALLOWED[layer]
    ]
    assert not wrong, "imports that point up or sideways:\n" + "\n".join(wrong)


def test_the_rule_catches_an_upward_import():
    """The check itself bites: a deferred ``service`` import in a cfsr module, relative
    imports resolved against the module's package."""
    probe = REPO / "cfsr" / "methods" / "_probe.py"
    src = ("def f():\n    from cfsr_live.service import app\n    return app\n"
           "from ..spikes import SpikeRecording\n")
    imps = list(_imports(probe, src))
    assert [(i.target, i.in_function) for i in imps] == [
        ("cfsr_live.service", True), ("cfsr.spikes", False)]
    assert _layer_of("cfsr_live.service.app") == "service" not in ALLOWED["cfsr"]
    assert _layer_of("cfsr_live.driver.usb") == "driver" not in ALLOWED["shm"]


# --- imports inside functions --------------------------------------------------------------

#: in-function imports of our own modules that cfsr/ and service/ may keep, at most: a
#: deferred import hides the module graph from a reader, so one stays only where it keeps a
#: heavy or system-bound import (numba kernels, FastAPI, pyusb, OpenCV contrib, a
#: subcommand's stack) away from a light path, and says so
MAX_DEFERRED = 40
#: the note a deferred import carries on its line or on the line above its block of imports
DEFERRED_NOTE = re.compile(r"#\s*deferred:\s*\S")
#: the folders the limit applies to
DEFERRED_SCOPE = ("cfsr", "service")


class Deferred(NamedTuple):
    path: Path
    line: int
    says_why: bool


def _deferred(path: Path, text: str | None = None) -> list[Deferred]:
    """Each import statement of ours inside a function of ``path`` (its source ``text`` if
    given), and whether a ``# deferred: why`` note covers it: on one of its own lines, or on
    the line above the run of import statements it belongs to (blank lines between them
    allowed, as isort separates groups)."""
    text = path.read_text() if text is None else text
    lines = text.splitlines()
    spans = {n.lineno: n.end_lineno or n.lineno for n in ast.walk(ast.parse(text, str(path)))
             if isinstance(n, (ast.Import, ast.ImportFrom))}
    ends = {end: start for start, end in spans.items()}
    out: dict[int, Deferred] = {}  # one per statement, however many names it imports
    for imp in _imports(path, text):
        if not imp.in_function or _layer_of(imp.target) is None or imp.line in out:
            continue
        start = above = imp.line
        while above - 1 in ends or (above > 1 and not lines[above - 2].strip()):
            above -= 1  # climb the run of imports above this one (blank lines between groups)
            if above in ends:
                start = above = ends[above]
        near = lines[start - 2: start - 1] + lines[imp.line - 1: spans[imp.line]]
        out[imp.line] = Deferred(path, imp.line, any(DEFERRED_NOTE.search(t) for t in near))
    return list(out.values())


def _all_deferred() -> list[Deferred]:
    return [d for layer in DEFERRED_SCOPE for p in sorted((REPO / layer).rglob("*.py"))
            for d in _deferred(p)]


def test_own_imports_sit_at_the_top_unless_they_say_why():
    found = _all_deferred()
    silent = [f"{d.path.relative_to(REPO)}:{d.line}" for d in found if not d.says_why]
    assert not silent, ("imports of our own modules inside functions, with no '# deferred: "
                        "why' note (move them to the top, or say what they keep away):\n"
                        + "\n".join(silent))
    by_file = Counter(str(d.path.relative_to(REPO)) for d in found)
    assert len(found) <= MAX_DEFERRED, (
        f"{len(found)} in-function imports of our own modules in "
        f"{'/, '.join(DEFERRED_SCOPE)}/ (at most {MAX_DEFERRED}):\n"
        + "\n".join(f"{n:4d} {f}" for f, n in by_file.most_common()))


def test_the_deferred_rule_sees_silent_and_noted_imports():
    """The check bites: a silent deferred import of ours is found, a noted one (on its line,
    above it, or above its run of imports) passes, and imports of other packages and at the
    top are not counted."""
    probe = REPO / "cfsr" / "cli" / "_probe.py"
    src = ("import numpy\n"
           "from cfsr.layout import Layout\n"
           "def f():\n"
           "    import json\n"
           "    from cfsr.spikes import SpikeRecording\n"
           "    from ..datfile import (  # deferred: a reason\n"
           "        read_dat,\n"
           "    )\n"
           "    # deferred: another reason\n"
           "    import cfsr.display\n"
           "    from cfsr_live.service import app\n"
           "\n"
           "    # deferred: a third\n"
           "    import numpy\n"
           "\n"
           "    from cfsr import spikes\n"
           "\n"
           "    x = 1\n"
           "    from cfsr import methods\n"
           "    return Layout, SpikeRecording, read_dat, app, spikes, methods, x\n")
    assert [(d.line, d.says_why) for d in _deferred(probe, src)] == [
        (5, False), (6, True), (10, True), (11, True), (16, True), (19, False)]


# --- the CLI loads the command it runs, and no other -----------------------------------------

def _cli_modules_after(argv: list[str]) -> list[str]:
    """The command modules (offline and plugin) loaded by ``cfsr ARGV`` in a fresh process."""
    code = ("import contextlib, io, sys\n"
            "from cfsr.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try:\n"
            f"        main({argv!r})\n"
            "    except SystemExit:\n"
            "        pass\n"
            "print(' '.join(sorted(m for m in sys.modules if m.startswith(\n"
            "    ('cfsr.cli.', 'cfsr_live.service.commands.')) and '._' not in m)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True, env={**os.environ, "CFSR_WARMUP": "0"})
    return out.stdout.split()


def test_the_cli_imports_only_the_command_it_runs():
    """Dispatch is lazy: ``cfsr --help`` lists every command (plugins' help read from their
    source) and imports none of their modules; a command imports its own module only."""
    assert _cli_modules_after(["--help"]) == []
    assert _cli_modules_after(["methods"]) == ["cfsr.cli.methods"]
    assert _cli_modules_after(["serve", "--help"]) == ["cfsr_live.service.commands.serve"]
