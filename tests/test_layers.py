"""The layer rule, read from the source: arrows point down only (service -> replay -> driver
-> cfsr, with shm beside them: generic shared memory that imports nothing of ours), and
nothing imports service. Every module of every layer is parsed with ``ast``, imports inside
functions included, so a deferred import cannot hide an arrow that points up. The run-time
checks elsewhere cover only what ``import cfsr`` happens to load."""

from __future__ import annotations

import ast
import tomllib
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
