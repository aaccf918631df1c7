"""Keep freed memory in the process for the next frame (glibc ``mallopt``).

One CFSR frame allocates and frees about 30 MB of large arrays (history rates, the PatchMatch
frames and guides, their padded copies). glibc hands every block above 128 kB straight to
``mmap`` and gives it back to the kernel on ``free``, so the next frame pays a page fault for
every 4 kB it touches again: about 20 ms of a 120 ms CFSR frame on the simulated disk scene
(2 cores), measured with ``scripts/profile_cfsr.py``. Raising the ``mmap`` threshold and the
trim threshold keeps those blocks in the heap, where the next frame reuses them.

This changes a process-wide setting, so the library never calls it on import: the ``cfsr``
command line and the live worker process call :func:`keep_freed_memory` once at start, and a
program embedding the library may do the same.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

__all__ = ["keep_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Blocks up to this size come from the heap (glibc's own ceiling for the dynamic threshold).
MMAP_THRESHOLD = 32 << 20
#: Free memory at the top of the heap kept for reuse instead of returned to the kernel.
TRIM_THRESHOLD = 1 << 30

_done: bool | None = None


def keep_freed_memory() -> bool:
    """Make glibc keep freed large blocks for reuse; True when the setting took effect.

    A no-op returning False where the C library is not glibc (musl, macOS, Windows). The
    process's resident memory then stays near its peak instead of shrinking between frames.
    """
    global _done
    if _done is not None:
        return _done
    _done = False
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        ok = libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
        ok = libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1 and ok
    except (OSError, AttributeError):
        return False
    _done = ok
    return ok
