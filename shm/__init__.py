"""Shared memory between the service's processes: the spike ring and the latest-frame slot.

Both are memory-mapped files (in ``/dev/shm`` when it has room) that one process creates and
others attach to by path, and both publish with the same seqlock (:mod:`cfsr_live.shm.seqlock`): a
writer that never waits for readers, readers that copy and then check they were not written
over. They live here, below ``driver`` (which fills the ring) and ``service`` (whose worker
reads the ring and fills the slot), because they are neither camera code nor application
code: plumbing between processes that imports nothing of ours, not even ``cfsr``.

Modules: :mod:`cfsr_live.shm.files` (create, attach, release, stale-file cleanup),
:mod:`cfsr_live.shm.seqlock`,
:mod:`cfsr_live.shm.ring` (:class:`SpikeRing`), :mod:`cfsr_live.shm.frameslot` (:class:`FrameSlot`).
"""
