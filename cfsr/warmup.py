"""Compile the reconstruction kernels ahead of their first use.

numba compiles a kernel the first time it runs and keeps the machine code in its on-disk cache
(``NUMBA_CACHE_DIR``, else ``__pycache__`` beside the installed modules). On a fresh install the
first CSR or CFSR frame therefore waits on the compiler for most of a minute (issue 14: 41-55 s
for CFSR on a 2-core host), while a process that finds the kernels cached loads them in well
under a second per method. :func:`warm_up` pays that cost at a moment of the user's choosing:
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
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

__all__ = ["warm_up", "is_warm", "marker_path", "cache_dir", "WARM_ORDER"]

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
    size and modification time of every cfsr module (numba's own cache keys on the latter)."""
    import numba

    import cfsr

    root = Path(cfsr.__file__).parent
    h = hashlib.sha256(f"{cfsr.__version__} {numba.__version__}".encode())
    for p in sorted(root.rglob("*.py")):
        st = p.stat()
        h.update(f"{p.relative_to(root)} {st.st_size} {st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:16]


def cache_dir() -> Path:
    """The folder numba caches cfsr's kernels in: ``NUMBA_CACHE_DIR`` when set, else the one
    numba's own locator picks (cfsr's ``__pycache__`` where it can be written, as in a user's
    virtual environment; else numba's per-user cache folder, as for a system-wide install)."""
    import numba

    import cfsr

    if numba.config.CACHE_DIR:
        return Path(numba.config.CACHE_DIR)
    from cfsr._bits import _unpack_kernel

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
) -> dict[str, float]:
    """Run each method once so numba compiles (or loads from its cache) every kernel it uses.

    Parameters
    ----------
    methods : sequence of str, optional
        Method names (default: every registered method, in :data:`WARM_ORDER`).
    progress : callable, optional
        Called as ``progress(name, seconds)`` after each method.

    Returns
    -------
    dict of str to float
        Seconds each method took (compile or cache load, plus one small frame).

    Notes
    -----
    When every registered method was warmed, the marker of :func:`marker_path` is written.
    """
    from cfsr._bits import pack_frames
    from cfsr.layout import Layout
    from cfsr.methods import get_method, resolve_params
    from cfsr.methods import methods as registered
    from cfsr.streaming import StreamingReconstructor

    known = list(registered())
    names = [m for m in WARM_ORDER if m in known] + [m for m in known if m not in WARM_ORDER]
    if methods is not None:
        names = [get_method(m).name for m in methods]
    h, w = _SHAPE
    layout = Layout(w, h)
    out: dict[str, float] = {}
    for name in names:
        t0 = time.perf_counter()
        m = get_method(name)
        before, after = m.window(resolve_params(m))
        need = before + after + 1  # the frame computed is the one at `before`
        packed = pack_frames(_moving_spikes(need, h, w, vanish=max(0, before - 100)))
        sr = StreamingReconstructor(name, layout, slack=need)
        sr.push(packed, 0)
        out_t = sr.latest_step()
        assert out_t is not None
        rate = sr.compute(out_t).rate
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
