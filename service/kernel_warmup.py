"""The kernel warm-up's supervisor: a first ``cfsr serve`` compiles every method's kernels in
the background, in a child process this module starts, follows and reports.

On a fresh install numba compiles a method's kernels when the worker first runs it. The server
therefore starts ``cfsr warmup`` (:mod:`cfsr.warmup`) once, in its own process at the
reconstruction's CPU priority (:data:`RECONSTRUCTION_NICE`, the pool's), and reports its
progress, kernel by kernel, in ``GET /api/status`` (``kernels``) and the viewer. The kernels
land in numba's on-disk cache, from which the worker
loads them in well under a second when the user switches method. A server whose kernels are
already cached (the marker of :func:`cfsr.warmup.is_warm`) starts no warm-up.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from typing import Literal

from pydantic import BaseModel, Field

from cfsr.methods import methods as registered
from cfsr.warmup import WARM_ORDER, is_warm

__all__ = ["KernelWarmup", "KernelStatus", "warmup_enabled", "RECONSTRUCTION_NICE"]

#: ``CFSR_WARMUP=0`` turns the background warm-up off (the test suite does, except where it
#: tests it, so that each server it starts does not compile in the background)
ENV = "CFSR_WARMUP"

State = Literal["off", "ready", "compiling", "done", "stopped", "failed"]


def warmup_enabled() -> bool:
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "false", "no", "off")


class KernelStatus(BaseModel):
    """Where the background compilation of the reconstruction kernels stands."""

    state: State = Field(
        "off",
        description="off: not run (disabled); ready: the kernels were cached already; "
        "compiling: in progress; done: finished; stopped: the server stopped it; failed: it "
        "ended with an error",
    )
    ready: list[str] = Field(default_factory=list, description="methods compiled so far")
    pending: list[str] = Field(default_factory=list, description="methods still to compile")
    current: str | None = Field(
        None, description="the method being compiled now (the first pending one)"
    )
    elapsed_s: float | None = Field(None, description="seconds since the warm-up started")
    kernel: str | None = Field(
        None, description="the latest per-kernel progress line of the method compiling: its "
        "kernel n of N, the kernel compiling (or waited for while another process compiles "
        "it) and the CPU seconds so far against the measured ones"
    )
    pid: int | None = Field(None, description="the warm-up process while it runs")
    error: str | None = None


#: the nice value of what reconstructs: the worker's pool processes and this warm-up. They
#: run at one value because they share the kernels' compile locks (cfsr._jit): a warm-up at a
#: lower priority holding a lock crawled while the pool waited for it (the first CFSR frame
#: came 2-3 times later). 0, not above: at 10, beside two CPU-bound processes, the first CFSR
#: frame took 781 s (measured by scripts/first_frame.py --busy 2)
RECONSTRUCTION_NICE = 0


def _child_setup() -> None:  # pragma: no cover - runs in the child before exec
    """Reconstruction's CPU priority, and (Linux) end with the server even when killed."""
    if RECONSTRUCTION_NICE:
        os.nice(RECONSTRUCTION_NICE)
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class KernelWarmup:
    """One background ``cfsr warmup --lines`` process and what it has reported."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[str] | None = None
        self._reader: threading.Thread | None = None
        self._status = KernelStatus()
        self._t0 = 0.0

    def start(self, first: str | None = None, methods: list[str] | None = None) -> None:
        """Start compiling in the background unless the kernels are cached (or it is
        disabled); ``first``: the method to compile first (the one the worker runs);
        ``methods``: which (default: all, in :data:`cfsr.warmup.WARM_ORDER`)."""
        if not warmup_enabled():
            return
        known = list(registered())
        if is_warm():
            self._status = KernelStatus(state="ready", ready=known)
            return
        order = [m for m in WARM_ORDER if m in known] + [m for m in known if m not in WARM_ORDER]
        if methods is not None:
            order = [m for m in order if m in methods]
        if first in order:
            order.remove(first)
            order.insert(0, first)
        cmd = [sys.executable, "-m", "cfsr", "warmup", "--lines", "--methods", ",".join(order)]
        self._t0 = time.monotonic()
        self._status = KernelStatus(state="compiling", pending=order, elapsed_s=0.0)
        self._proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,  # one pipe, read to its end: no full pipe can block it
            stdin=subprocess.DEVNULL,
            text=True,
            preexec_fn=_child_setup,
        )
        self._reader = threading.Thread(target=self._follow, name="cfsr-warmup", daemon=True)
        self._reader.start()

    def _follow(self) -> None:
        proc = self._proc
        assert proc is not None and proc.stdout is not None
        last = ""  # the last line that is not a method's progress: the error, if any
        for line in proc.stdout:
            name = line.split(" ", 1)[0].strip()
            with self._lock:
                st = self._status
                if line.startswith("# "):  # a kernel's progress
                    st.kernel = line[2:].strip()[:300]
                elif name in st.pending:
                    st.pending.remove(name)
                    st.ready.append(name)
                elif line.strip():
                    last = line.strip()
        code = proc.wait()
        with self._lock:
            st = self._status
            st.elapsed_s = time.monotonic() - self._t0
            if code == 0 and not st.pending:
                st.state = "done"
            elif st.state == "compiling":
                st.state = "failed"
                st.error = f"exit status {code}" + (f": {last}" if last else "")

    def status(self) -> KernelStatus:
        with self._lock:
            st = self._status.model_copy(deep=True)
        if st.state == "compiling":
            st.current = st.pending[0] if st.pending else None
            st.elapsed_s = time.monotonic() - self._t0
            st.pid = self._proc.pid if self._proc is not None else None
        return st

    def stop(self) -> None:
        """Stop a warm-up still running (what it compiled stays cached)."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            with self._lock:
                self._status.state = "stopped"
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self._reader is not None:
            self._reader.join(timeout=5)
