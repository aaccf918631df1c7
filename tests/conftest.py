"""Shared pytest fixtures.

* ``shared_data``: the project's ``../shared/data`` folder (REDS and uhsr samples); tests that
  use it skip with a reason when it is absent -- the product never needs it.
* ``require_tier(name, ok, why)``: system-dependent tiers (umockdev USB, Chromium) skip on a
  developer machine that lacks them, but FAIL under ``CI=true``, where they must run.
* The quick tier (``./tasks test --quick`` = ``pytest -m "not slow"``): every module's unit
  tests and small integration tests. ``slow`` is applied here, by what a test uses (a real
  server or a worker pipeline, in its body or its fixtures; the wheel; a system tier; a whole
  module of long runs), never by hand per test, so a new test that starts a server leaves the
  quick tier by itself.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from compile_report import pytest_configure, pytest_terminal_summary  # noqa: F401 (hooks)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("CFSR_SHARED_DATA", REPO.parent / "shared" / "data"))
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
# every server the suite starts would otherwise compile all kernels in the background on its
# first start (cfsr_live.service.kernel_warmup); tests/test_kernel_warmup.py turns it on where
# it tests it
os.environ.setdefault("CFSR_WARMUP", "0")


#: fixtures a quick run cannot afford that no name below gives away: the built wheel and its
#: venvs, the shared data's large recordings
SLOW_FIXTURES = frozenset({
    "wheel_file", "base_install", "live_install", "shared_data", "reds_files",
})
#: names whose use in a test's body or in a fixture it uses means it starts a real server or
#: a worker process
SLOW_NAMES = frozenset({"LiveServer", "WorkerSupervisor", "_pipeline"})
#: modules that are long runs as a whole: accuracy tables, the benchmark, the million-step
#: stream, the fault matrices (a server per row group), kernel compiles into fresh caches
SLOW_MODULES = frozenset({
    "test_accuracy_sim", "test_accuracy_data", "test_bench", "test_stress_long",
    "test_fault_matrix", "test_fault_matrix_hostile", "test_kernel_warmup",
})
#: system tiers are never quick (they are the slowest starts of all)
SYSTEM_MARKERS = ("usb", "browser", "packaging", "fuzz")


def _code_names(code) -> set[str]:
    """Global names a function's code (and the code nested in it) refers to."""
    names = set(code.co_names)
    for const in code.co_consts:
        if hasattr(const, "co_names"):
            names |= _code_names(const)
    return names


def _is_slow(item: pytest.Item) -> bool:
    if item.get_closest_marker("slow") or any(item.get_closest_marker(m)
                                               for m in SYSTEM_MARKERS):
        return True
    if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())):
        return True
    module = getattr(item, "module", None)  # None for items that are not Python functions
    if module is not None and module.__name__.rpartition(".")[2] in SLOW_MODULES:
        return True
    # the test's body, and the fixtures it uses (a new fixture that starts a server or a
    # pipeline is found by what it calls, without a list to keep)
    funcs = [getattr(item, "function", None)]
    info = getattr(item, "_fixtureinfo", None)
    if info is not None:
        funcs += [d.func for defs in info.name2fixturedefs.values() for d in defs]
    return any(SLOW_NAMES & _code_names(f.__code__) for f in funcs
               if hasattr(f, "__code__"))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if _is_slow(item) and not item.get_closest_marker("slow"):
            item.add_marker(pytest.mark.slow)


def require_tier(name: str, ok: bool, why: str) -> None:
    """Skip (developer machine) or fail (CI) when system tier ``name`` cannot start."""
    if ok:
        return
    msg = f"{name} tier cannot start: {why}"
    if IN_CI:
        pytest.fail(msg + " (CI=true: this tier must run, install it in .ci/run)")
    pytest.skip(msg)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent (optional test data)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def reds_files(shared_data: Path) -> list[tuple[Path, Path]]:
    """(spike .dat, ground-truth .png) pairs of the REDS samples."""
    base = shared_data / "synthetic" / "reds_base"
    pairs = []
    for dat in sorted((base / "spike").glob("*.dat")):
        png = base / "gt" / (dat.stem + ".png")
        if png.exists():
            pairs.append((dat, png))
    if not pairs:
        pytest.skip(f"no REDS samples under {base}")
    return pairs


# -- the installed wheel (tests/wheelenv.py): built once per run, installed outside the tree ----
def _install_or_tier(make):
    try:
        return make()
    except (RuntimeError, OSError) as exc:
        # no package index reachable on a developer machine: skip; in CI this tier must run
        require_tier("packaging", False, str(exc)[-1500:])


@pytest.fixture(scope="session")
def wheel_file(tmp_path_factory) -> Path:
    from wheelenv import build_wheel

    return _install_or_tier(lambda: build_wheel(tmp_path_factory.mktemp("wheel")))


@pytest.fixture(scope="session")
def base_install(tmp_path_factory, wheel_file) -> Path:
    """``bin`` folder of a fresh venv with ``pip install cfsr`` (no extras)."""
    from wheelenv import make_venv

    return _install_or_tier(
        lambda: make_venv(tmp_path_factory.mktemp("venv-base") / "venv", wheel_file)
    )


@pytest.fixture(scope="session")
def live_install(tmp_path_factory, wheel_file) -> Path:
    """``bin`` folder of a fresh venv with ``pip install cfsr[live]``."""
    from wheelenv import make_venv

    return _install_or_tier(
        lambda: make_venv(tmp_path_factory.mktemp("venv-live") / "venv", wheel_file, "live")
    )
