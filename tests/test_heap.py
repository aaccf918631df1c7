"""cfsr._heap: freed frame arrays stay in the process for the next frame (glibc)."""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

import numpy as np
import pytest

from cfsr._heap import keep_freed_memory

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (n, ctypes.c_size_t)
        for n in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


def test_idempotent_bool():
    first = keep_freed_memory()
    assert isinstance(first, bool)
    assert keep_freed_memory() is first


@pytest.mark.skipif(not GLIBC, reason="mallopt is a glibc setting; other C libraries: no-op")
def test_freed_block_stays_in_heap():
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    if not hasattr(libc, "mallinfo2"):
        pytest.skip("glibc older than 2.33 has no mallinfo2 to observe the heap")
    libc.mallinfo2.restype = _MallInfo2
    assert keep_freed_memory() is True
    size = 24 << 20  # above glibc's default 128 kB mmap threshold, like a frame's arrays
    a = np.ones(size // 8)
    mapped = libc.mallinfo2().hblkhd
    del a
    info = libc.mallinfo2()
    # the block came from the heap (not a separate mapping) and its memory is kept free there
    assert info.hblkhd <= mapped
    assert info.fordblks >= size
