"""The one seqlock of the shared-memory structures (ring slots and the latest-frame slot).

A seqlock lets one writer publish a region that readers in other processes copy without any
lock, and without the writer ever waiting for them. One int64 word guards the region:

* the writer sets it to :data:`WRITING` before it touches the region, and to the region's new
  sequence number (>= 0, never reused for the same word) once it is done;
* a reader reads the word, copies what it needs, and reads the word again: the copy is good
  only if the word is a sequence number and did not change in between.

The ordering argument relies on x86-64 total store order (stores become visible in program
order), the platform this project targets; NumPy scalar stores into a shared mapping are
plain stores.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EMPTY", "WRITING", "Seqlock"]

#: the word's value while the writer is changing the region
WRITING = -1
#: the word's value before anything was published
EMPTY = -2


class Seqlock:
    """Seqlock words over an int64 array (one word per guarded region).

    Parameters
    ----------
    words : ndarray of int64, 1-D
        A view into shared memory (it may be strided, e.g. one column of slot headers).
    """

    __slots__ = ("_w",)

    def __init__(self, words: np.ndarray) -> None:
        if words.dtype != np.int64 or words.ndim != 1:
            raise ValueError(f"seqlock words must be a 1-D int64 view, got {words.dtype}")
        self._w = words

    def reset(self) -> None:
        """Mark every region as never published (on creation)."""
        self._w[:] = EMPTY

    # -- writer ---------------------------------------------------------------------------
    def begin_write(self, i: int) -> None:
        """Invalidate region ``i`` before changing it (readers now retry or discard)."""
        self._w[i] = WRITING

    def end_write(self, i: int, seq: int) -> None:
        """Publish region ``i`` as sequence number ``seq`` (>= 0; new for this word)."""
        self._w[i] = seq

    # -- readers --------------------------------------------------------------------------
    def read(self, i: int) -> int:
        """The word of region ``i``: a sequence number, :data:`WRITING` or :data:`EMPTY`."""
        return int(self._w[i])

    def unchanged(self, i: int, seq: int) -> bool:
        """True if region ``i`` still holds sequence ``seq``: a copy taken since is good."""
        return int(self._w[i]) == seq
