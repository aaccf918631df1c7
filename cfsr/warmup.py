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

__all__ = ["warm_up", "is_warm", "marker_path", "WARM_ORDER"]

#: Methods in the order a warm-up compiles them: the costliest compilations that users reach
#: for first (CSR, CFSR), then the rest.
WARM_ORDER = ("tfi", "tfp", "csr", "cfsr", "tfa", "tfstp", "snm")

#: The scene the kernels compile on: small (the compile does not depend on the frame size), but
#: moving, so that no stage is skipped (a static window would take CFSR's static gate and leave
#: its history scan and PatchMatch uncompiled).
_SCENE = ("disk", 96, 128)


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


def marker_path() -> Path | None:
    """Where a finished warm-up of this code leaves its marker: numba's cache folder when
    ``NUMBA_CACHE_DIR`` is set, else cfsr's own ``__pycache__`` (where numba caches its
    kernels); None where that folder cannot be written (then no marker is kept)."""
    import numba

    import cfsr

    base = Path(numba.config.CACHE_DIR or Path(cfsr.__file__).parent / "__pycache__")
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
    from cfsr.simulate import simulate
    from cfsr.streaming import StreamingReconstructor

    known = list(registered())
    names = [m for m in WARM_ORDER if m in known] + [m for m in known if m not in WARM_ORDER]
    if methods is not None:
        names = [get_method(m).name for m in methods]
    need = 1
    for name in names:
        m = get_method(name)
        need = max(need, sum(m.window(resolve_params(m))) + 1)
    scene, h, w = _SCENE
    packed = pack_frames(simulate(scene, need, seed=0, height=h, width=w).spikes)
    layout = Layout(w, h)
    out: dict[str, float] = {}
    for name in names:
        t0 = time.perf_counter()
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
