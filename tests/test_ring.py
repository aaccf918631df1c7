"""Shared-memory ring: sequence numbers, never-blocking producer, overrun detection and exact
loss accounting with a deliberately slow consumer (in-process and in another process)."""

from __future__ import annotations

import multiprocessing as mp
import threading
import time

import numpy as np
import pytest

from cfsr_live.shm.ring import SpikeRing

FB = 64  # small frames keep the tests fast; the ring does not care about geometry


def _block(index: int, n: int) -> np.ndarray:
    """Frames whose bytes encode their own step index (so torn/misplaced data is visible)."""
    idx = np.arange(index, index + n, dtype=np.int64)
    out = np.empty((n, FB), np.uint8)
    out[:] = (idx % 251)[:, None].astype(np.uint8)
    out[:, :8] = idx.view(np.uint8).reshape(n, 8)
    return out


def _check(index: int, data: np.ndarray) -> None:
    got = data[:, :8].copy().view(np.int64).ravel()
    assert (got == np.arange(index, index + len(data))).all()
    assert (data[:, 8:] == (got % 251)[:, None].astype(np.uint8)).all()


@pytest.fixture
def ring():
    r = SpikeRing.create(8, 4, FB)
    yield r
    r.close()


def test_roundtrip_in_order(ring):
    rd = ring.reader(start="latest")
    idx = 1000
    for n in (4, 3, 4, 1):
        ring.write(idx, _block(idx, n))
        idx += n
    got = []
    while (r := rd.read()) is not None:
        blk, data = r
        _check(blk.index, data)
        got.append((blk.seq, blk.index, blk.n_frames))
    assert got == [(0, 1000, 4), (1, 1004, 3), (2, 1007, 4), (3, 1011, 1)]
    assert rd.lost_frames == 0 and rd.frames_read == 12
    assert ring.head == 4 and ring.frames_published == 12
    assert rd.backlog == 0


def test_blocks_carry_the_host_time_of_their_write(ring):
    rd = ring.reader(start="latest")
    before = time.monotonic()
    ring.write(0, _block(0, 4))
    ring.write(4, _block(4, 4), t_host=12.5)
    assert rd.backlog == 2
    first, second = rd.poll(), None
    assert before <= first.t_host <= time.monotonic()
    assert rd.release(first)
    second = rd.poll()
    assert second.t_host == 12.5 and rd.backlog == 1


def test_an_oldest_reader_starts_at_the_oldest_block_still_held(ring):
    """On a lapped ring the oldest start is the oldest slot the producer has not begun to
    reuse: read from there, nothing counts as an overrun or a loss."""
    for i in range(ring.n_slots + 3):
        ring.write(4 * i, _block(4 * i, 4))
    rd = ring.reader(start="oldest")
    assert rd.backlog == ring.n_slots - 1
    got = []
    while (r := rd.read()) is not None:
        _check(r[0].index, r[1])
        got.append(r[0].seq)
    assert got == list(range(4, ring.n_slots + 3))
    assert rd.overruns == 0 and rd.lost_frames == 0


def test_lost_blocks_count_whole_blocks_overrun_and_torn(ring):
    rd = ring.reader(start="latest", keep=1)
    ring.write(0, _block(0, 4))
    assert rd.read() is not None
    for i in range(1, 12):  # 11 blocks of 4 frames: the reader (8 slots) keeps only the last
        ring.write(4 * i, _block(4 * i, 4))
    blk, _ = rd.read()
    assert blk.index == 44 and rd.overruns == 1
    assert (rd.lost_frames, rd.lost_blocks) == (40, 10)
    ring.write(48, _block(48, 4))
    held = rd.poll()
    for i in range(13, 13 + ring.n_slots):  # lapped while the view is held: torn
        ring.write(4 * i, _block(4 * i, 4))
    assert not rd.release(held)
    assert (rd.torn, rd.lost_frames, rd.lost_blocks) == (1, 44, 11)


def test_an_overrun_of_one_block_loses_one_block(ring):
    rd = ring.reader(start="latest", keep=ring.n_slots - 1)
    ring.write(0, _block(0, 4))
    assert rd.read() is not None
    for i in range(1, ring.n_slots + 1):  # one block more than the reader can still reach
        ring.write(4 * i, _block(4 * i, 4))
    blk, _ = rd.read()
    assert blk.index == 8 and (rd.overruns, rd.lost_frames, rd.lost_blocks) == (1, 4, 1)


def test_slots_for_holds_the_frames_asked_within_the_byte_cap():
    big = 1 << 30
    assert SpikeRing.slots_for(1000, 4, FB, max_bytes=big) == 250
    assert SpikeRing.slots_for(1001, 4, FB, max_bytes=big) == 251  # whole frames, rounded up
    assert SpikeRing.slots_for(10, 4, FB, max_bytes=big) == 8  # min_slots
    cap = 2 * 4096 + 20 * (64 + 4 * FB)  # the header's pages and 20 slots
    n = SpikeRing.slots_for(1000, 4, FB, max_bytes=cap)
    assert n == 20 and SpikeRing.nbytes_for(n, 4, FB) <= cap
    with pytest.raises(ValueError, match="over the ring's cap"):
        SpikeRing.slots_for(1000, 4, FB, max_bytes=cap // 4)


def test_ring_sizes_are_checked():
    small = SpikeRing.create(2, 1, FB)  # the smallest ring: two slots of one frame
    small.close()
    for args in ((1, 4, FB), (8, 0, FB), (8, 4, 0)):
        with pytest.raises(ValueError):
            SpikeRing.create(*args)


def test_large_block_is_split_and_flags_kept(ring):
    rd = ring.reader()
    ring.write(0, _block(0, 10), flags=1, lost_before=7)
    blocks = []
    while (r := rd.read()) is not None:
        blocks.append(r[0])
        _check(r[0].index, r[1])
    assert [b.n_frames for b in blocks] == [4, 4, 2]
    assert [b.flags for b in blocks] == [1, 0, 0]
    assert [b.lost_before for b in blocks] == [7, 0, 0]


def test_producer_never_blocks_and_overrun_is_counted_exactly(ring):
    rd = ring.reader(start="latest", keep=2)
    total = 0
    idx = 0
    read_frames = 0
    # the consumer reads one block every 5 writes: it is overrun again and again
    for k in range(200):
        n = 1 + k % 4
        ring.write(idx, _block(idx, n))
        idx += n
        total += n
        if k % 5 == 4:
            r = rd.read()
            if r is not None:
                _check(r[0].index, r[1])
                read_frames += r[0].n_frames
    while (r := rd.read()) is not None:
        _check(r[0].index, r[1])
        read_frames += r[0].n_frames
    assert rd.overruns > 0
    assert ring.producer_waits == 0
    # every frame published is either read or counted lost, none twice
    assert read_frames == rd.frames_read
    assert rd.frames_read + rd.lost_frames == total


def test_torn_read_is_detected(ring):
    rd = ring.reader()
    ring.write(0, _block(0, 4))
    blk = rd.poll()
    assert blk is not None
    for i in range(1, 9):  # the producer laps the reader while it holds the view
        ring.write(4 * i, _block(4 * i, 4))
    assert rd.release(blk) is False
    assert rd.torn == 1 and rd.lost_frames >= 4


def test_blocking_mode_waits_for_registered_consumer():
    ring = SpikeRing.create(4, 2, FB, blocking=True)
    try:
        rd = ring.reader(start="latest", register=True)
        got: list[int] = []
        done = threading.Event()

        def consume():
            while not done.is_set() or rd.backlog:
                r = rd.read()
                if r is None:
                    time.sleep(0.001)
                    continue
                _check(r[0].index, r[1])
                got.extend(range(r[0].index, r[0].index + r[0].n_frames))
                time.sleep(0.002)  # slow consumer

        th = threading.Thread(target=consume)
        th.start()
        for i in range(40):
            ring.write(2 * i, _block(2 * i, 2))
        done.set()
        th.join(10)
        assert got == list(range(80))  # nothing lost: the producer waited
        assert rd.lost_frames == 0 and ring.producer_waits > 0
        rd.close()
    finally:
        ring.close()


def _slow_consumer(path: str, n_expected_frames: int, q) -> None:
    r = SpikeRing.attach(path)
    rd = r.reader(start="oldest", keep=1)
    q.put("attached")  # the producer starts writing only now
    bad = 0
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        blk = rd.poll()
        if blk is None:
            if r.finished and rd.backlog == 0:
                break
            time.sleep(0.001)
            continue
        data = blk.data.copy()
        time.sleep(0.003)  # deliberately slow: the producer laps us
        if rd.release(blk):
            try:
                _check(blk.index, data)
            except AssertionError:
                bad += 1
    q.put((rd.frames_read, rd.lost_frames, rd.overruns, rd.torn, bad))


def test_slow_consumer_in_another_process():
    ring = SpikeRing.create(16, 8, FB)
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    n_blocks, per = 3000, 8
    p = ctx.Process(target=_slow_consumer, args=(str(ring.path), n_blocks * per, q))
    p.start()
    try:
        assert q.get(timeout=60) == "attached"  # it starts from the oldest block held
        for i in range(n_blocks):
            ring.write(i * per, _block(i * per, per))
            if i % 50 == 0:
                time.sleep(0.001)
        ring.finish()  # tell the consumer we are done (without unmapping yet)
        frames_read, lost, overruns, torn, bad = q.get(timeout=30)
        p.join(10)
    finally:
        if p.is_alive():
            p.kill()
        ring.close()
    assert bad == 0, "a validated block held wrong data"
    assert overruns > 0 and lost > 0
    # the ring was empty when the consumer attached: every frame is either read or counted
    # lost, those lapped before its first poll too
    assert frames_read + lost == n_blocks * per, (frames_read, lost)


def test_skip_to_latest_counts_skipped_not_lost(ring):
    rd = ring.reader(start="oldest")
    ring.write(0, _block(0, 4))
    assert rd.read() is not None
    for i in range(1, 6):  # 5 blocks of 4 frames; the reader keeps only the newest one
        ring.write(4 * i, _block(4 * i, 4))
    rd.skip_to_latest(1)
    blk, data = rd.read()
    _check(blk.index, data)
    assert blk.index == 20
    assert rd.skipped_frames == 16 and rd.lost_frames == 0


def test_finish_is_seen_by_an_attached_reader(ring):
    other = SpikeRing.attach(ring.path)
    try:
        assert not other.finished
        ring.finish()
        assert other.finished
    finally:
        other.close()



def test_a_new_rings_pages_are_faulted_in_when_it_is_made():
    """A ring's memory is touched when the ring is made, not during the stream's first lap:
    there each block's page faults made a write take 8 ms instead of under 1, and a paced
    replay fell 0.1 s behind at every start (about 4,100 frames skipped)."""
    import resource

    ring = SpikeRing.create(16, 64, 4096)  # 4 MiB: a page per frame
    try:
        data = np.ones((64 * 16, 4096), np.uint8)  # its own pages faulted in here
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for i in range(16):  # one lap
            ring.write(64 * i, data[64 * i : 64 * (i + 1)])
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
        assert faults < 64 * 16 // 10, f"{faults} page faults writing a lap of 1024 pages"
    finally:
        ring.close()


def test_seqlock_words():
    from cfsr_live.shm.seqlock import EMPTY, WRITING, Seqlock

    words = np.zeros(3, np.int64)
    lock = Seqlock(words)
    lock.reset()
    assert lock.read(1) == EMPTY
    lock.begin_write(1)
    assert lock.read(1) == WRITING and not lock.unchanged(1, 0)
    lock.end_write(1, 7)
    assert lock.unchanged(1, 7) and lock.read(0) == EMPTY
    with pytest.raises(ValueError):
        Seqlock(np.zeros(3, np.float64))


def test_shm_imports_nothing_of_ours():
    """``shm`` sits below ``driver`` and ``service``: generic plumbing (shared files, the
    seqlock, the spike ring) that imports none of them (nor ``cfsr``), so both may import it
    without an arrow pointing up; what a frame is belongs to the service (its frame slot)."""
    import subprocess
    import sys

    code = (
        "import sys, cfsr_live.shm.files, cfsr_live.shm.seqlock, cfsr_live.shm.ring\n"
        "bad = [m for m in ('cfsr', 'cfsr_live.driver', 'cfsr_live.replay', 'cfsr_live.service') "
        "if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
