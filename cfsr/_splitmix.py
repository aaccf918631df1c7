"""splitmix64 (Steele, Lea and Flood, 2014): the counter-based hash behind every random draw
that must not depend on thread scheduling (the simulator's noise, PatchMatch's search)."""

from __future__ import annotations

import numpy as np

from cfsr._jit import njit

__all__ = ["GOLDEN", "mix64"]

#: The splitmix64 increment (2**64 / golden ratio), used to step or key a counter.
GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


@njit(helper=True)
def mix64(z):  # pragma: no cover - numba
    """splitmix64 finaliser: a well-spread 64-bit hash of ``z`` (uint64)."""
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))
