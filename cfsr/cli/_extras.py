"""Optional parts of the install (pip extras) and the one-line error that names the missing one.

The base install (``pip install cfsr``) is the library and the offline CLI. Each extra adds
what one kind of user needs; a command that needs an extra checks for it before doing any
work, and says which extra to install instead of failing with an import traceback.
"""

from __future__ import annotations

import importlib.util

__all__ = ["EXTRAS", "MissingExtra", "extra_for_module", "missing_extra_message", "require_extra"]

#: extra -> (what it brings, top-level modules it provides). Module names, not distributions:
#: pyusb imports as ``usb``, prometheus-client as ``prometheus_client``.
EXTRAS: dict[str, tuple[str, tuple[str, ...]]] = {
    "live": (
        "the live service (cfsr serve) or the USB camera (cfsr record --usb)",
        ("fastapi", "uvicorn", "websockets", "prometheus_client", "usb"),
    ),
    "cluster": ("reconstruction on a Dask cluster (--cluster)", ("dask", "distributed")),
    "bench": ("the benchmark's plots (pareto.png)", ("matplotlib",)),
}


class MissingExtra(RuntimeError):
    """A command needs an optional extra that is not installed (the CLI exits with status 2)."""


def _missing(modules: tuple[str, ...] | list[str]) -> list[str]:
    out = []
    for name in modules:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            out.append(name)
    return out


def install_hint(extra: str) -> str:
    return f"pip install 'cfsr[{extra}]'"


def require_extra(extra: str, modules: tuple[str, ...] | list[str] | None = None) -> None:
    """Raise :class:`MissingExtra` unless every module of ``extra`` (or ``modules``) imports.

    Uses ``importlib.util.find_spec``, so nothing is imported by the check itself.
    """
    what, default = EXTRAS[extra]
    missing = _missing(modules if modules is not None else default)
    if missing:
        raise MissingExtra(
            f"{what} needs the '{extra}' extra (missing: {', '.join(missing)}): "
            f"{install_hint(extra)}"
        )


def extra_for_module(name: str | None) -> str | None:
    """The extra that provides top-level module ``name`` (``None`` if none does)."""
    top = (name or "").split(".", 1)[0]
    for extra, (_, mods) in EXTRAS.items():
        if top in mods:
            return extra
    return None


def missing_extra_message(exc: ModuleNotFoundError) -> str | None:
    """One line for an import of an optional module that failed, or ``None`` if the module
    belongs to no extra (a real bug, which should show its traceback)."""
    extra = extra_for_module(exc.name)
    if extra is None:
        return None
    return f"this needs the '{extra}' extra (no module {exc.name!r}): {install_hint(extra)}"
