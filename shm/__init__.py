"""Shared memory between the service's processes: generic seqlocked regions and the spike ring.

Memory-mapped files (in ``/dev/shm`` when it has room) that one process creates and others
attach to by path, published with one seqlock (:mod:`cfsr_live.shm.seqlock`): a writer that
never waits for readers, readers that copy and then check they were not written over. They
live here, below ``driver`` (which fills the ring) and ``service`` (whose worker reads the
ring and fills its frame slot, :mod:`cfsr_live.service.frameslot`, laid out by the frame
schema), because they are neither camera code nor application code: plumbing between
processes that imports nothing of ours, not even ``cfsr``, and knows nothing of frames,
masks or counters.

Modules: :mod:`cfsr_live.shm.files` (create, attach, release, stale-file cleanup),
:mod:`cfsr_live.shm.seqlock`, :mod:`cfsr_live.shm.ring` (:class:`SpikeRing`).
"""
