"""The reconstruction pool (cfsr.pool): frames computed side by side in processes are the
frames one process computes, bit for bit; a failing frame is reported and the pool goes on;
a dead process is an error, not a hang; nothing is left in shared memory."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

import cfsr
from cfsr.api import reconstruct_outputs
from cfsr.cli import main
from cfsr.config import MethodConfig
from cfsr.methods.registry import get_method, resolve_params
from cfsr.offline import carry_groups, pool_outputs, stream_reconstruct
from cfsr.pool import FramePool, PoolError, TaskError
from cfsr.simulate import simulate
from cfsr.spikes import as_recording


@pytest.fixture(scope="module")
def disk():
    """A small rotating disk: CFSR runs every stage on it (moving, static and still pixels)."""
    sim = simulate("disk", steps=1600, height=64, width=96, seed=1)
    return as_recording(sim.spikes)


@pytest.fixture(scope="module")
def pool():
    with FramePool(2, 1) as p:
        yield p


def _same(a, b) -> None:
    assert np.array_equal(a.rate, b.rate)
    assert sorted(a.masks) == sorted(b.masks)
    for k in a.masks:
        assert np.array_equal(a.masks[k], b.masks[k]), k


@pytest.mark.parametrize("method", ["cfsr", "csr", "tfp"])
def test_pool_outputs_equal_one_process(disk, pool, method):
    times = [30, 700, 760, 1100, 1599]  # clipped windows at both ends, and neighbours
    ref = reconstruct_outputs(disk, method, times)
    cfg = MethodConfig(method)
    got = list(pool_outputs(disk, cfg, carry_groups(cfg, times), pool=pool, carry=True))
    assert [t for t, _ in got] == sorted(times)
    for (_, o), r in zip(got, ref, strict=True):
        _same(o, r)


def test_stream_and_library_entry_points_use_the_pool_with_the_same_numbers(disk):
    times = list(range(500, 1500, 97))
    one = dict(stream_reconstruct(disk, "cfsr", times, workers=1))
    two = dict(stream_reconstruct(disk, "cfsr", times, workers=2))
    assert sorted(one) == sorted(two) == times
    for t in times:
        _same(one[t], two[t])
    # the library's front door, times in any order: the same as its one-process run
    sub = times[::-1][:4]
    assert np.array_equal(cfsr.reconstruct(disk, "cfsr", sub, workers=2),
                          cfsr.reconstruct(disk, "cfsr", sub, workers=1))


def test_a_failing_frame_is_a_task_error_and_the_process_goes_on(disk, pool):
    good = MethodConfig("tfp")
    bad = object.__new__(MethodConfig)  # skipped validation: its compute raises in the process
    object.__setattr__(bad, "method", "tfp")
    object.__setattr__(bad, "params", {**resolve_params(get_method("tfp")), "window": -5})
    k = pool.submit("bad", bad, disk.layout, disk.packed(0, 200), 0, [(0, 200, 199)])
    with pytest.raises(TaskError) as err:
        pool.collect(timeout=60)
    assert err.value.tag == "bad" and "Error" in str(err.value)
    assert k in pool.idle
    pool.submit("good", good, disk.layout, disk.packed(0, 200), 0, [(40, 200, 199)])
    r = pool.collect(timeout=60)
    assert r is not None and r.tag == "good"
    _same(r.outputs[0][1], reconstruct_outputs(disk, "tfp", [199])[0])


def test_submit_checks_its_spans(disk, pool):
    with pytest.raises(ValueError, match="outside frames"):
        pool.submit("x", MethodConfig("tfp"), disk.layout, disk.packed(0, 100), 0,
                    [(0, 101, 50)])
    assert pool.pending == 0


def test_a_dead_process_is_an_error_not_a_hang(disk):
    with FramePool(2, 1) as p:
        os.kill(p.pids[1], signal.SIGKILL)
        # collect(timeout=None) waits for ever on a hang: it must raise instead
        with pytest.raises(PoolError, match="exited"):
            p.collect(timeout=None)


def test_regions_leave_nothing_in_shared_memory(disk):
    folder = Path("/dev/shm")
    if not folder.is_dir():
        pytest.skip("no /dev/shm on this system (the regions live in the temporary folder)")
    mine = f"cfsr-pool-{os.getpid()}-"
    with FramePool(2, 1) as p:
        assert not [f for f in os.listdir(folder) if f.startswith(mine)]  # unlinked once mapped
        p.submit(1, MethodConfig("tfp"), disk.layout, disk.packed(0, 300), 0, [(0, 300, 299)])
        assert p.collect(timeout=60) is not None
    assert not [f for f in os.listdir(folder) if f.startswith(mine)]


def test_a_task_larger_than_the_region_grows_it(disk):
    with FramePool(1, 1, region_bytes=4096) as p:
        cfg = MethodConfig("tfp")
        got = list(pool_outputs(disk, cfg, [[900]], pool=p))
        assert p.region_bytes >= 160 * disk.layout.frame_bytes
    _same(got[0][1], reconstruct_outputs(disk, "tfp", [900])[0])


def test_cli_workers_give_the_same_files(tmp_path, disk):
    f = tmp_path / "in.dat"
    cfsr.write_dat(f, disk.frames(0, disk.n_frames))
    outs = {}
    for w in ("1", "2"):
        out = tmp_path / f"w{w}"
        rc = main(["reconstruct", str(f), "--method", "csr", "--times", "400:1500:100",
                   "--out", str(out), "--workers", w, "--quiet"])
        assert rc == 0
        outs[w] = out
    names = sorted(p.name for p in outs["1"].glob("*.npy"))
    assert len(names) == 11
    for n in names:
        assert np.array_equal(np.load(outs["1"] / n), np.load(outs["2"] / n)), n


def test_cli_refuses_bad_worker_counts(tmp_path, disk, capsys):
    f = tmp_path / "in.dat"
    cfsr.write_dat(f, disk.frames(0, 200))
    with pytest.raises(SystemExit):
        main(["reconstruct", str(f), "--workers", "0", "--out", str(tmp_path / "o")])
    assert "1..256" in capsys.readouterr().err


_ORPHAN = """
import os, sys, time
import numpy as np
from cfsr.config import MethodConfig
from cfsr.layout import Layout
from cfsr.pool import FramePool

if __name__ == "__main__":
    lay = Layout(400, 250)
    packed = np.random.default_rng(0).integers(0, 256, (200, lay.frame_bytes), np.uint8)
    p = FramePool(2, 1)
    for k in range(2):  # results of 400 x 250 frames that nobody collects fill the pipes
        p.submit(k, MethodConfig("tfp"), lay, packed, 0, [(40, 200, 199)])
    print(" ".join(map(str, p.pids)), flush=True)
    time.sleep(3)
    os._exit(0)  # the owner dies without closing the pool
"""


def test_a_pool_whose_owner_dies_leaves_no_process(tmp_path):
    import subprocess
    import sys

    script = tmp_path / "orphan.py"
    script.write_text(_ORPHAN)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         timeout=90)
    pids = [int(x) for x in out.stdout.split()]
    assert len(pids) == 2, out.stderr

    def alive(pid: int) -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        with open(f"/proc/{pid}/stat") as f:  # a zombie is gone for our purpose
            return f.read().split(")")[-1].split()[0] != "Z"

    end = time.monotonic() + 20
    while time.monotonic() < end and any(alive(p) for p in pids):
        time.sleep(0.2)
    assert not [p for p in pids if alive(p)], "pool processes outlived their owner"


def test_a_released_queue_frees_its_semaphores_in_the_callers_thread():
    """A queue's semaphores are unlinked by the thread that drops the queue, not later by its
    feeder thread: a process that leaves right after a close (the live worker does) would
    otherwise kill the feeder half-way and the resource tracker would report a leak."""
    import gc
    import multiprocessing as mp

    from cfsr.procs import release_queue

    if not Path("/dev/shm").is_dir():
        pytest.skip("POSIX semaphores are not files in /dev/shm on this system")
    gc.disable()  # the release must not depend on a collection
    try:
        for _ in range(20):  # the feeder's end races the drop: a few tries show it
            q = mp.get_context("spawn").Queue()
            q.put(("task", 1))  # starts the feeder thread, which holds the write lock
            names = [lk._semlock.name.lstrip("/") for lk in (q._rlock, q._wlock, q._sem)]
            release_queue(q)
            del q
            left = [n for n in names if (Path("/dev/shm") / f"sem.{n}").exists()]
            assert left == [], f"semaphores still linked after the queue was dropped: {left}"
    finally:
        gc.enable()


# A user's first script, as the README writes it: no main guard. Its pool processes must not
# run it again (spawn re-imports __main__), whether it is a file or read from stdin.
_GUARDLESS = """
import sys
import numpy as np
import cfsr
from cfsr.simulate import simulate
from cfsr.spikes import as_recording

rec = as_recording(simulate("disk", steps=400, height=32, width=48, seed=3).spikes)
times = list(range(100, 300, 10))
pooled = cfsr.reconstruct(rec, "tfp", times, workers=2)
again = cfsr.reconstruct(rec, "tfp", times, workers=2)  # the same pool, not a new one
alone = cfsr.reconstruct(rec, "tfp", times, workers=1)
from cfsr import pool
print("same", np.array_equal(pooled, alone) and np.array_equal(again, alone))
print("pids", *pool._shared.pids)
"""


@pytest.mark.parametrize("how", ["file", "stdin"])
def test_a_script_without_a_main_guard_gets_the_frames(tmp_path, how):
    import subprocess
    import sys

    script = tmp_path / "first.py"
    script.write_text(_GUARDLESS)
    if how == "file":
        r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                           timeout=300, cwd=tmp_path)
    else:
        r = subprocess.run([sys.executable, "-"], input=_GUARDLESS, capture_output=True,
                           text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "same True" in r.stdout, r.stdout
    assert "bootstrapping" not in r.stderr and "Traceback" not in r.stderr, r.stderr[-3000:]


def test_the_shared_pool_is_started_once_and_reused(disk):
    from cfsr import pool as poolmod

    poolmod.close_shared_pool()
    times = list(range(200, 1400, 150))
    a = cfsr.reconstruct(disk, "tfp", times, workers=2)
    first = list(poolmod._shared.pids)
    b = cfsr.reconstruct(disk, "tfp", times[::-1], workers=2)
    assert poolmod._shared.pids == first, "a second call started new processes"
    assert np.array_equal(a, b[::-1])
    poolmod.close_shared_pool()
    assert poolmod._shared is None


def test_a_compiling_process_beats_and_is_told_from_a_hung_one(disk, tmp_path, monkeypatch):
    """A pool process compiling kernels (an empty cache) reports it every second: its owner
    sees what it compiles, and once the task is done, that the compile ended."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "empty-cache"))  # the children's
    with FramePool(1, 1) as p:
        # TFA: a few seconds of compiling (several beats), where CSR took 20 CPU s; the beat
        # is the pool's, whatever the method
        cfg = MethodConfig("tfa")
        before, after = cfg.window
        t = before + 10
        p.submit(1, cfg, disk.layout, disk.packed(0, t + after + 1), 0, [(0, t + after + 1, t)])
        seen = set()
        r = None
        while r is None:
            r = p.collect(timeout=0.2)
            beat = p.compiling(0)
            if beat is not None:
                seen.add(beat.kernel)
                assert beat.cpu_s >= 0 and beat.kernels >= 0
        assert any(k.startswith("cfsr.") for k in seen), seen
        end = time.monotonic() + 10  # the beat after the compile says it ended
        while p.compiling(0) is not None and time.monotonic() < end:
            p.collect(timeout=0.2)
        assert p.compiling(0) is None and p.compile_ended(0) > 0
