"""The helper threads (cfsr._pool) and what runs on them: parts side by side, same numbers."""

from __future__ import annotations

import threading

import numba
import numpy as np
import pytest

from cfsr._pool import helper_pool, in_parts, parts_for
from cfsr.methods.mog import _MIN_PART, mog_background


def test_in_parts_runs_every_part_once_and_raises_a_parts_error():
    seen: list[int] = []
    lock = threading.Lock()

    def part(i: int) -> None:
        with lock:
            seen.append(i)

    in_parts(part, 3)
    assert sorted(seen) == [0, 1, 2]

    done: list[int] = []

    def failing(i: int) -> None:
        if i == 1:
            raise ValueError("part 1")
        done.append(i)

    with pytest.raises(ValueError, match="part 1"):
        in_parts(failing, 2)
    assert done == [0]  # the caller's part ran; the error came back from the helper


def test_parts_follow_numbas_threads_and_the_smallest_part():
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        assert parts_for(10**6) == 1  # NUMBA_NUM_THREADS=1 keeps the pipeline on one core
        numba.set_num_threads(old)
        assert parts_for(10**6) == old
        assert parts_for(100, min_size=60) == 1
        assert parts_for(0) == 1
    finally:
        numba.set_num_threads(old)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs two numba threads")
@pytest.mark.parametrize("shape", [(12, 1, 3 * _MIN_PART + 17), (12, 180, 160), (5, 97, 211)])
def test_mog_split_over_threads_gives_the_one_thread_result(shape):
    """MOG's model is per pixel: the pixels split over two threads give exactly the mask and
    background of one model over the whole frame."""
    rng = np.random.default_rng(sum(shape))
    base = rng.integers(0, 256, shape[1:])
    f = np.clip(base + rng.normal(0, 20, shape), 0, 255).astype(np.uint8)
    f[:, ::7] = rng.integers(0, 256, f[:, ::7].shape)  # pixels that never settle (median B)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = mog_background(f, history=12)
        numba.set_num_threads(2)
        assert parts_for(shape[1] * shape[2], _MIN_PART) == 2
        two = mog_background(f, history=12)
    finally:
        numba.set_num_threads(old)
    np.testing.assert_array_equal(one[0], two[0])
    np.testing.assert_array_equal(one[1], two[1])
    assert one[0].shape == shape[1:] and one[1].dtype == np.float32


def _helpers_in_child(q) -> None:
    q.put(helper_pool().submit(lambda: 41 + 1).result(timeout=20))


@pytest.mark.skipif(
    "fork" not in __import__("multiprocessing").get_all_start_methods(),
    reason="needs the fork start method (POSIX)",
)
def test_helper_threads_work_in_a_forked_child():
    """A child forked after the helpers ran gets a fresh pool (the parent's threads do not
    survive the fork, and jobs on the inherited pool would never run)."""
    import multiprocessing as mp

    assert helper_pool().submit(lambda: 1).result(timeout=20) == 1  # the parent's threads exist
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    proc = ctx.Process(target=_helpers_in_child, args=(q,))
    proc.start()
    try:
        assert q.get(timeout=30) == 42
    finally:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.kill()
