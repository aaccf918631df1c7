"""Helper threads for the OpenCV calls that run on one core (Gaussian blur, MOG).

OpenCV blurs an image as small as a PatchMatch guide, and runs ``bgsegm`` MOG, on one core
whatever ``cv2.setNumThreads`` says; both release the GIL, so independent parts (frames, or
pixels: MOG's model is per pixel) run side by side on Python threads. The parts are as many
as numba's threads, so ``NUMBA_NUM_THREADS`` / ``numba.set_num_threads`` limit the whole
pipeline (the 1-thread figure of ``cfsr bench --throughput`` stays one thread).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from numba import get_num_threads

__all__ = ["helper_pool", "in_parts", "parts_for"]

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def helper_pool() -> ThreadPoolExecutor:
    """The helper threads (created on first use; one fewer than the cores: the caller's
    thread takes a part too)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(
                max_workers=max(1, (os.cpu_count() or 1) - 1), thread_name_prefix="cfsr-helper"
            )
        return _POOL


def parts_for(n: int, min_size: int = 1) -> int:
    """How many parts ``n`` independent items split into: numba's thread count, at most
    ``n // min_size`` (a part smaller than ``min_size`` costs more to hand over than it saves),
    at least 1."""
    return max(1, min(get_num_threads(), n // max(1, int(min_size))))


def in_parts(fn: Callable[[int], None], parts: int) -> None:
    """Run ``fn(0) .. fn(parts - 1)`` side by side: part 0 on the calling thread, the others
    on the helper threads; returns when all are done (re-raising the first error)."""
    jobs = [helper_pool().submit(fn, i) for i in range(1, parts)]
    err: BaseException | None = None
    try:
        fn(0)
    except BaseException as exc:  # the helpers' parts still finish before it is raised
        err = exc
    for j in jobs:
        try:
            j.result()
        except BaseException as exc:
            err = err or exc
    if err is not None:
        raise err


def _forget_pool() -> None:
    # a forked child inherits the pool object but not its threads: jobs would never run
    global _POOL, _POOL_LOCK
    _POOL = None
    _POOL_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)
