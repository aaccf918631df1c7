"""pytest plugin: what the run spent compiling numba kernels, in every process it started.

Sets ``CFSR_COMPILE_LOG`` (cfsr/_jit.py appends one line per outermost compile) before any
test runs, so the servers, pool processes and CLI runs the suite starts inherit it, and
prints the sum at the end: on a cold cache (as in CI) it says what the compile costs the
suite; on a warm one it should say what the tests that compile into a fresh cache on purpose
cost, and no more. A kernel compiled more than once shows where a cache was not shared (the
wheel's venvs share the checkout's: cfsr/_jit.py keys a kernel by its module and content).
"""

from __future__ import annotations

import json
import os
from collections import Counter
from pathlib import Path

import pytest

_OWN = "CFSR_COMPILE_LOG" not in os.environ


def pytest_configure(config: pytest.Config) -> None:
    if _OWN and not hasattr(config, "workerinput"):
        root = Path(config.rootpath) / ".cache"
        root.mkdir(exist_ok=True)
        path = root / f"compile-log-{os.getpid()}.jsonl"
        path.unlink(missing_ok=True)
        os.environ["CFSR_COMPILE_LOG"] = str(path)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    path = Path(os.environ.get("CFSR_COMPILE_LOG", ""))
    if not path.name or not path.is_file():
        terminalreporter.write_line("numba compiles in this run: none")
        return
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    cpu = sum(r["cpu_s"] for r in rows)
    per = Counter(r["kernel"] for r in rows)
    again = sum(n - 1 for n in per.values() if n > 1)
    procs = len({r["pid"] for r in rows})
    terminalreporter.write_line(
        f"numba compiles in this run: {len(rows)} outermost compiles in {procs} processes, "
        f"{cpu:.1f} CPU s; {again} of them a kernel compiled before in the run"
    )
    if _OWN:
        path.unlink(missing_ok=True)
