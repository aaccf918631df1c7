"""Compile the reconstruction kernels ahead of their first use.

numba compiles a kernel the first time it runs and keeps the machine code in its on-disk cache
(``NUMBA_CACHE_DIR``, else ``__pycache__`` beside the installed modules). On a fresh install the
first CSR or CFSR frame therefore waits on the compiler (the measured CPU seconds per method
ship with the package: :func:`measured_compile`), while a process that finds the kernels cached
loads them in well under a second per method; each kernel is compiled once, by whichever
process needs it first (:mod:`cfsr._jit`). :func:`warm_up` pays that cost at a moment of the
user's choosing:
``cfsr warmup`` after ``pip install``, or ``cfsr serve`` in a low-priority background process
on its first start (with its progress in the viewer), so that switching to CFSR later finds the
kernels ready.

Each method runs once on a small moving scene through the streaming reconstructor
(:class:`~cfsr.streaming.StreamingReconstructor`), the path of both the offline CLI and the
live worker, so the kernels compiled are the ones those use (numba specialises on argument
types, not sizes: the 400 x 250 frames of a camera, or a memory-mapped file, reuse them). A
marker file (:func:`marker_path`) records that a warm-up of this code finished, so a server can
skip it at its next start.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

import cfsr
from cfsr._bits import _unpack_kernel, pack_frames
from cfsr._jit import kernel_name, on_compile
from cfsr.layout import Layout
from cfsr.methods import get_method, resolve_params
from cfsr.methods import methods as registered
from cfsr.streaming import StreamingReconstructor

__all__ = [
    "warm_up",
    "is_warm",
    "marker_path",
    "cache_dir",
    "WARM_ORDER",
    "KernelProgress",
    "measured_compile",
    "compile_profile",
]

#: Methods in the order a warm-up compiles them: the costliest compilations that users reach
#: for first (CSR, CFSR), then the rest.
WARM_ORDER = ("tfi", "tfp", "csr", "cfsr", "tfa", "tfstp", "snm")

#: Rows and columns of the scene the kernels compile on: small (the compile does not depend on
#: the frame size).
_SHAPE = (96, 128)


def _moving_spikes(n: int, h: int, w: int, vanish: int) -> np.ndarray:
    """``(n, h, w)`` uint8 spikes, integrate-and-fire with threshold 1, of a still texture
    (0.05-0.3 spikes/step) with a textured band sliding over it (0.5 px per step, 0.01-0.9
    spikes/step) and a bright block (0.8) that leaves at step ``vanish``.

    Every stage of CFSR runs on it, so every kernel compiles: the band is motion (a static
    window would take CFSR's static gate and leave its history scan and PatchMatch uncompiled;
    its dark pixels reach the distinct-interval test's theta, so the coarse mask and the
    dynamic stages run), the place the block left is a *ghost* (still by t, in MOG's history
    before t: the two-sided objects' future test runs). Made with NumPy rather than the
    simulator, whose own kernels would compile first (15-30 s of a warm-up on 2 cores).
    """
    rng = np.random.default_rng(0)
    still = rng.uniform(0.05, 0.3, (h, w)).astype(np.float32)
    band = rng.uniform(0.01, 0.9, (h // 3, 2 * w)).astype(np.float32)
    acc = rng.uniform(0.0, 1.0, (h, w)).astype(np.float32)
    out = np.empty((n, h, w), np.uint8)
    rate = still.copy()
    block = (slice(2 * (h // 3) + 4, h - 4), slice(w // 4, w // 2))  # below the band
    for t in range(n):
        x = (t // 2) % w
        rate[h // 3 : h // 3 + band.shape[0]] = band[:, x : x + w]
        rate[block] = 0.8 if t < vanish else still[block]
        acc += rate
        fired = acc >= 1.0
        acc[fired] -= 1.0
        out[t] = fired
    return out


def _fingerprint() -> str:
    """Hash of what the compiled kernels depend on: the versions of cfsr and numba and the
    content of every cfsr module (a fresh clone or a reinstall of the same code keeps it)."""
    import numba

    root = Path(cfsr.__file__).parent
    h = hashlib.sha256(f"{cfsr.__version__} {numba.__version__}".encode())
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def measured_compile() -> dict[str, Any]:
    """The compile figures measured by ``cfsr bench`` on an empty cache and shipped with the
    package (``_compile_table.json``): per method, ``kernels`` (the cfsr kernels it compiles
    when nothing is cached, in order) and ``cpu_s`` (CPU seconds of that compile), with the
    machine they were measured on. Empty when the table is absent."""
    path = Path(__file__).with_name("_compile_table.json")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def compile_profile(methods: Sequence[str] | None = None) -> dict[str, Any]:
    """Warm ``methods`` up (:func:`warm_up`) and measure what numba spent compiling: per
    method, the CPU seconds of the warm-up and the cfsr kernels it compiled (in order); per
    kernel, its own CPU seconds (its compile without the callees that compile separately).
    Run it on an empty cache (``NUMBA_CACHE_DIR`` set to a new folder), or it measures
    cache loads. This is what ``cfsr bench --compile`` runs in each of its processes."""
    from numba.core import event

    stack: list[list[Any]] = []
    own: dict[str, float] = {}
    order: list[str] = []

    class Listener(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            stack.append([kernel_name(ev.data["dispatcher"].py_func), time.process_time(), 0.0])

        def on_end(self, ev: event.Event) -> None:
            name, t0, inner = stack.pop()
            took = time.process_time() - t0
            own[name] = own.get(name, 0.0) + took - inner
            if name.startswith("cfsr."):
                order.append(name)
            if stack:
                stack[-1][2] += took

    listener = Listener()
    event.register("numba:compile", listener)
    per: dict[str, dict[str, Any]] = {}
    mark = [time.process_time(), 0]

    def done(name: str, seconds: float) -> None:
        now = time.process_time()
        per[name] = {"cpu_s": now - mark[0], "wall_s": seconds, "kernels": order[mark[1]:]}
        mark[:] = [now, len(order)]

    try:
        warm_up(methods, progress=done)
    finally:
        event.unregister("numba:compile", listener)
    return {"methods": per, "kernels": own, "cpu_s": sum(m["cpu_s"] for m in per.values())}


class KernelProgress:
    """Per-kernel progress of one method's compile, read from :func:`cfsr._jit.on_compile`
    events: the kernel being compiled (or waited for, while another process compiles it),
    ``n`` of ``N`` (``N`` from :func:`measured_compile`; kernels loaded from the cache count
    too), the CPU seconds spent so far, and the measured CPU seconds of the whole method.

    ``report(text, self)`` is called at each event with the line :meth:`line` gives."""

    def __init__(
        self, method: str, report: Callable[[str, KernelProgress], None] | None = None
    ) -> None:
        table = measured_compile().get("methods", {}).get(method, {})
        self.method = method
        self.total = len(table.get("kernels", [])) or None
        self.estimate_s: float | None = table.get("cpu_s")
        self.n = 0
        self._report = report
        self._t0 = time.process_time()

    @property
    def cpu_s(self) -> float:
        """CPU seconds this process spent since the method's compile began."""
        return time.process_time() - self._t0

    def line(self, kernel: str | None, waiting: bool = False) -> str:
        of = f"/{self.total}" if self.total else ""
        est = f" of ~{self.estimate_s:.0f}" if self.estimate_s else ""
        what = "" if kernel is None else (
            f" {'waiting for' if waiting else 'compiling'} {kernel.rsplit('.', 1)[-1]}"
        )
        return f"{self.method}: kernel {self.n}{of}{what}, {self.cpu_s:.1f}{est} CPU s"

    def __call__(self, event: str, act: Any) -> None:
        if event in ("end", "load"):
            self.n += 1
        if self._report is not None:
            self._report(self.line(act.kernel, act.waiting), self)


def cache_dir() -> Path:
    """The folder numba caches cfsr's kernels in: ``NUMBA_CACHE_DIR`` when set, else the one
    numba's own locator picks (cfsr's ``__pycache__`` where it can be written, as in a user's
    virtual environment; else numba's per-user cache folder, as for a system-wide install)."""
    import numba

    if numba.config.CACHE_DIR:
        return Path(numba.config.CACHE_DIR)

    try:  # numba exposes no public accessor for a dispatcher's cache folder
        return Path(_unpack_kernel._cache._cache_path)
    except AttributeError:  # pragma: no cover - another numba's internals
        return Path(cfsr.__file__).parent / "__pycache__"


def marker_path() -> Path | None:
    """Where a finished warm-up of this code leaves its marker: the folder numba caches the
    kernels in (:func:`cache_dir`); None where it cannot be written (then no marker is kept)."""
    base = cache_dir()
    try:
        base.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return base / f"cfsr-warm-{_fingerprint()}" if os.access(base, os.W_OK) else None


def is_warm() -> bool:
    """True when a warm-up of this code (same versions and sources) has finished here."""
    m = marker_path()
    return m is not None and m.exists()


def warm_up(
    methods: Sequence[str] | None = None,
    *,
    progress: Callable[[str, float], None] | None = None,
    kernels: Callable[[str, KernelProgress], None] | None = None,
) -> dict[str, float]:
    """Run each method once so numba compiles (or loads from its cache) every kernel it uses.

    Parameters
    ----------
    methods : sequence of str, optional
        Method names (default: every registered method, in :data:`WARM_ORDER`).
    progress : callable, optional
        Called as ``progress(name, seconds)`` after each method.
    kernels : callable, optional
        Called as ``kernels(line, tracker)`` at each kernel compiled, loaded or waited for
        (``line``: the :class:`KernelProgress` text; ``tracker``: its counts).

    Returns
    -------
    dict of str to float
        Seconds each method took (compile or cache load, plus one small frame).

    Notes
    -----
    When every registered method was warmed, the marker of :func:`marker_path` is written.
    """
    known = list(registered())
    names = [m for m in WARM_ORDER if m in known] + [m for m in known if m not in WARM_ORDER]
    if methods is not None:
        names = [get_method(m).name for m in methods]
    h, w = _SHAPE
    layout = Layout(w, h)
    out: dict[str, float] = {}

    for name in names:
        t0 = time.perf_counter()
        tracker = KernelProgress(name, kernels)
        stop = on_compile(tracker)
        m = get_method(name)
        before, after = m.window(resolve_params(m))
        need = before + after + 1  # the frame computed is the one at `before`
        packed = pack_frames(_moving_spikes(need, h, w, vanish=max(0, before - 100)))
        sr = StreamingReconstructor(name, layout, slack=need)
        sr.push(packed, 0)
        out_t = sr.latest_step()
        assert out_t is not None
        try:
            rate = sr.compute(out_t).rate
        finally:
            stop()
        if not np.isfinite(rate).all():  # a warm-up that computes garbage must not pass
            raise RuntimeError(f"warm-up of {name} gave non-finite rates")
        out[name] = time.perf_counter() - t0
        if progress is not None:
            progress(name, out[name])
    if set(known) <= set(out):
        marker = marker_path()
        if marker is not None:
            marker.write_text(" ".join(f"{k}={v:.2f}" for k, v in out.items()) + "\n")
    return out
