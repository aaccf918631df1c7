"""Reconstruction below acquisition: the live pool's processes compute frames at a higher nice
value than the reader of the camera, the ring and the recorder, once nothing can make them
compile any more.

A compile must not run there: beside two CPU-bound processes, the first CFSR frame after a
switch took 781 s with the pool at nice 10 and 114 s at nice 0 (the compile is what the user
waits for). An unprivileged process can raise a nice value but never lower it again, so a pool
process is lowered only when every kernel is in the cache (:func:`cfsr.warmup.is_warm`: a
finished warm-up of this code) and it has returned a frame (its kernels are loaded); from then
on it only loads kernels, at most, and computes frames.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable

from cfsr.warmup import is_warm

__all__ = ["FRAME_NICE", "FramePriority"]

#: the nice value pool processes compute frames at once their kernels are cached and loaded:
#: below acquisition (nice 0), so a busy machine takes CPU from frames, never from spike data
FRAME_NICE = 10


class FramePriority:
    """Lowers pool processes to :data:`FRAME_NICE` (see the module's docstring).

    ``cached`` says whether every kernel is in the cache (checked at most every ``check_s``
    seconds until it is); :meth:`lowest` is the nice value of the least nice pool process,
    what the status reports.
    """

    def __init__(
        self, nice: int = FRAME_NICE, *, cached: Callable[[], bool] = is_warm,
        check_s: float = 1.0,
    ) -> None:
        self.nice = int(nice)
        self._cached = cached
        self._check_s = check_s
        self._all_cached = False
        self._next_check = 0.0
        self._lowered: set[int] = set()

    def kernels_cached(self) -> bool:
        """Whether every kernel is cached (once true, true for good)."""
        if not self._all_cached and time.monotonic() >= self._next_check:
            self._next_check = time.monotonic() + self._check_s
            self._all_cached = bool(self._cached())
        return self._all_cached

    def lower(self, pids: Iterable[int]) -> bool:
        """Lower the processes ``pids`` (their kernels are loaded) once every kernel is
        cached; True when one was lowered now."""
        todo = [p for p in pids if p > 0 and p not in self._lowered]
        if not todo or not self.kernels_cached():
            return False
        for pid in todo:
            self._lowered.add(pid)
            try:
                if os.getpriority(os.PRIO_PROCESS, pid) < self.nice:
                    os.setpriority(os.PRIO_PROCESS, pid, self.nice)
            except OSError:  # gone (a restarted pool), or not ours to change
                continue
        return True

    @staticmethod
    def lowest(pids: Iterable[int]) -> int:
        """The least nice value among the running processes ``pids`` (0 with none)."""
        nices = []
        for pid in pids:
            try:
                nices.append(os.getpriority(os.PRIO_PROCESS, pid))
            except OSError:
                continue
        return min(nices, default=0)
