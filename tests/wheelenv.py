"""The installed wheel as a user gets it: build it from this checkout, install it into a fresh
virtual environment outside the source tree, and run its commands from a folder that is not
the checkout. Used by the packaging tests and the browser test (fixtures in conftest.py).

Not a test module. The build copies the tracked tree first: an in-place build would reuse a
stale ``build/lib`` (files deleted from the tree would still ship).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_IGNORE = shutil.ignore_patterns(
    ".git", ".venv", ".cache", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache",
    ".hypothesis", ".ruff_cache", "bench-out", "out",
)

#: what each install took (seconds), for the test report
TIMINGS: dict[str, float] = {}


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    kw.setdefault("capture_output", True)
    kw.setdefault("text", True)
    return subprocess.run(cmd, **kw)


def project_version() -> str:
    import tomllib

    data = tomllib.loads((REPO / "pyproject.toml").read_text())
    if "version" in data["project"]:
        return data["project"]["version"]
    # dynamic: setuptools reads cfsr.__version__ (a literal in cfsr/__init__.py)
    for line in (REPO / "cfsr" / "__init__.py").read_text().splitlines():
        if line.startswith("__version__"):
            return line.split("=", 1)[1].strip().strip("\"'")
    raise AssertionError("no version found")


def build_wheel(workdir: Path) -> Path:
    """``pip wheel`` of a copy of the checkout; returns the ``.whl`` path."""
    src = workdir / "src"
    shutil.copytree(REPO, src, ignore=_IGNORE)
    out = workdir / "dist"
    t0 = time.perf_counter()
    r = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
              "--disable-pip-version-check", "-q", "-w", str(out), str(src)])
    TIMINGS["build_wheel"] = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"pip wheel failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    wheels = sorted(out.glob("cfsr-*.whl"))
    if len(wheels) != 1:
        raise RuntimeError(f"expected one wheel in {out}, found {wheels}")
    return wheels[0]


def make_venv(where: Path, wheel: Path, extras: str = "") -> Path:
    """A fresh virtual environment at ``where`` with ``wheel[extras]`` installed from the
    package index (dependencies resolved as for a user); returns the venv's ``bin`` folder."""
    base = getattr(sys, "_base_executable", sys.executable)
    r = _run([base, "-m", "venv", str(where)])
    if r.returncode != 0:
        raise RuntimeError(f"venv failed: {r.stderr[-2000:]}")
    spec = f"{wheel}[{extras}]" if extras else str(wheel)
    t0 = time.perf_counter()
    r = _run([str(where / "bin" / "python"), "-m", "pip", "install", "-q",
              "--disable-pip-version-check", spec], cwd=where)
    TIMINGS[f"install[{extras or 'base'}]"] = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"pip install {spec} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    return where / "bin"


def run_cli(bindir: Path, args: list[str], cwd: Path, timeout: float = 600,
            **kw) -> subprocess.CompletedProcess:
    """Run the installed ``cfsr`` from ``cwd`` with an environment that cannot see the checkout
    (no PYTHONPATH; NUMBA_CACHE_DIR kept so kernels compile once per run)."""
    return _run([str(bindir / "cfsr"), *args], cwd=cwd, env=clean_env(bindir),
                timeout=timeout, **kw)


def clean_env(bindir: Path) -> dict[str, str]:
    """The environment of a user who activated the venv at ``bindir``."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{bindir}{os.pathsep}{env.get('PATH', '')}"
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".cache" / "numba"))
    return env
