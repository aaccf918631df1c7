"""The worker process: deterministic pipeline (replay fast mode + blocking ring) gives exactly
the offline reconstruction, methods switch at run time, and a crashed worker is reported and
restarted by its supervisor."""

from __future__ import annotations

import time

import numpy as np
import pytest
from livehelpers import wait_until

from cfsr.api import reconstruct_outputs
from cfsr.config import MethodConfig
from cfsr.display import to_display
from cfsr.methods.registry import get_method, resolve_params
from cfsr_live.driver.acquisition import Acquisition
from cfsr_live.replay.device import ReplayDevice
from cfsr_live.replay.pattern import pattern_recording
from cfsr_live.service.config import WorkerConfig
from cfsr_live.service.frameslot import FrameSlot
from cfsr_live.service.pacing import LATE_S, pick_tier
from cfsr_live.service.supervisor import WorkerSupervisor
from cfsr_live.shm.ring import SpikeRing

H, W, N = 24, 32, 6000
GAIN = 0.6


def _cfg(method: str = "tfp", params: dict | None = None) -> WorkerConfig:
    return WorkerConfig(MethodConfig(method, params), gain=GAIN, max_fps=200.0,
                        deterministic=True)


def _unchecked(method: str, params: dict) -> WorkerConfig:
    """A config that skipped the web side's validation (as one that validates there but
    cannot be built in the worker): the worker must reject it and keep running."""
    m = object.__new__(MethodConfig)
    object.__setattr__(m, "method", method)
    object.__setattr__(m, "params", {**resolve_params(get_method(method)), **params})
    return WorkerConfig(m, gain=GAIN, max_fps=200.0, deterministic=True)


@pytest.fixture(scope="module")
def rec():
    return pattern_recording(N, height=H, width=W, speed_px=0.004)


def _pipeline(rec, workers: int = 1):
    """Replay (fast, looping) -> blocking ring -> supervised worker of ``workers`` processes."""
    dev = ReplayDevice(rec, mode="unpaced", loop=True, block_frames=64)
    dev.open()
    ring = SpikeRing.create(8, 64, rec.layout.frame_bytes, blocking=True)
    slot = FrameSlot.create(max_pixels=H * W)
    sup = WorkerSupervisor(slot, _cfg(), workers=workers)
    sup.start(str(ring.path), rec.layout)
    assert sup.ready.wait(120), "worker did not start"
    acq = Acquisition(dev, ring)
    acq.start()
    yield dev, ring, slot, sup, acq
    acq.stop()
    sup.stop()
    ring.close()
    slot.close()


def _on_tfp(pipeline):
    """The class's pipeline back on the starting config (TFP): its tests share one pipeline
    (a start is a worker and its pool processes) and each begins where a fresh one would."""
    dev, ring, slot, sup, acq = pipeline
    assert sup.ready.wait(120), "worker did not start"
    assert sup.wait_config(sup.configure(_cfg()), 120) == ("applied", None)
    return pipeline


@pytest.fixture(scope="class")
def one_process(rec):
    yield from _pipeline(rec)


@pytest.fixture
def pipeline(one_process):
    return _on_tfp(one_process)


def _frames(slot, n, timeout=120.0, method=None):
    """``n`` new frames (of ``method``) within ``timeout`` s; AssertionError naming what came
    (how many, of which methods, the slot's counters) if they do not."""
    out, seq, other = [], None, set()

    def enough() -> bool:
        nonlocal seq
        f = slot.read(since=seq)
        if f is not None:
            seq = f.seq
            if method is None or f.method == method:
                out.append(f)
            else:
                other.add(f.method)
        return len(out) >= n

    wait_until(enough, timeout, lambda: f"{n} frames of {method or 'any method'} (got "
               f"{len(out)}; other methods seen {sorted(other)}; slot {slot.stats()})",
               interval=0.002)
    return out


def _expected(rec, method, t, params=None):
    m = get_method(method)
    before, after = m.window(resolve_params(m, params))
    tt = t % N  # the replay loops; its clock keeps counting
    if tt < before or tt + after >= N:
        return None  # window crosses the loop seam: not comparable with the file
    out = reconstruct_outputs(rec, method, [tt], params=params)[0]
    return to_display(out.rate, GAIN), out.masks


class TestOneProcess:
    """One pipeline for the class (torn down with it, so no other runs beside the next
    tests): method switches, crashes and rejected configs."""

    def test_deterministic_output_equals_offline_and_method_switch(self, rec, pipeline):
        dev, ring, slot, sup, acq = pipeline
        for method in ("tfp", "tfi"):
            if method != "tfp":
                sup.configure(_cfg(method))
            frames = _frames(slot, 12, method=method)
            compared = 0
            for f in frames:
                exp = _expected(rec, method, f.step)
                if exp is None:
                    continue
                assert np.array_equal(f.image, exp[0]), f"{method} at step {f.step} differs"
                compared += 1
            assert compared >= 3
        st = sup.stats()
        assert st.ring_lost_frames == 0  # blocking mode: the worker saw every frame
        assert st.worker_skip_frames == 0
        # the supervisor learns of an applied config from its monitor thread, which drains the
        # worker's events every 0.1 s: the frames of the new method can arrive before that
        wait_until(lambda: sup.applied_version == sup.config.version, 10, "the applied version",
                   interval=0.02)


    def test_every_registered_method_runs_in_the_worker(self, rec, pipeline):
        from cfsr.methods import methods

        dev, ring, slot, sup, acq = pipeline
        for name in methods():
            sup.configure(_cfg(name))
            got = _frames(slot, 1, method=name, timeout=180)
            assert got[0].image.shape == (H, W)
            # every mask the method declares and returns reaches the slot under its name
            # (SNM's motion mask included), none that it does not declare
            assert set(got[0].masks) <= set(get_method(name).masks), (name, set(got[0].masks))
            if name in ("snm", "csr"):
                assert set(got[0].masks) == set(get_method(name).masks), name


    def test_crash_is_reported_and_worker_restarted(self, pipeline):
        dev, ring, slot, sup, acq = pipeline
        _frames(slot, 2)
        pid, restarts = sup.pid, sup.restarts
        sup.inject("crash", code=3)
        wait_until(lambda: sup.restarts > restarts, 60, "a restart", interval=0.05)
        assert sup.restarts == restarts + 1
        assert sup.crashes[-1]["exitcode"] == 3
        assert sup.ready.wait(120)
        assert sup.pid != pid
        before = sup.stats().frames_out
        _frames(slot, 3)
        assert sup.stats().frames_out > before  # counters carried over the restart
        # an uncaught Python exception is reported with its message
        sup.inject("raise", message="boom for the test")
        wait_until(lambda: sup.restarts > restarts + 1, 60, "a second restart", interval=0.05)
        assert sup.restarts == restarts + 2
        assert "boom for the test" in (sup.crashes[-1]["message"] or "")
        assert sup.ready.wait(120)
        _frames(slot, 2)


    def test_rejected_config_keeps_the_worker_publishing(self, rec, pipeline):
        """Issue 12: one ``window=1e9`` stopped the frames for good while the heartbeat stayed
        healthy. The worker now applies a config all or nothing and answers every version."""
        dev, ring, slot, sup, acq = pipeline
        _frames(slot, 2, method="tfp")
        before = sup.applied_version
        # sent straight to the supervisor: past the web side's checks, like a config that
        # validates there but cannot be built in the worker
        bad = sup.configure(_unchecked("tfp", {"window": 1_000_000_000}))
        small = {"max_isi": 50}  # a window no larger than before (no new buffer needed)
        good = sup.configure(_cfg("tfi", small))
        frames = _frames(slot, 6, method="tfi", timeout=60)  # frames after a rejected config
        state, reason = sup.wait_config(bad, 30)
        assert state == "rejected" and "window" in reason and "1000000000" in reason
        assert sup.wait_config(good, 30) == ("applied", None)
        assert sup.applied_version == good > bad > before
        compared = 0
        for f in frames:  # still exactly the offline reconstruction
            exp = _expected(rec, "tfi", f.step, small)
            if exp is not None:
                assert np.array_equal(f.image, exp[0])
                compared += 1
        assert compared >= 2
        # the newest config rejected: the supervisor falls back to what the worker runs, so a
        # restarted worker would start with a config that works
        bad2 = sup.configure(_unchecked("tfi", {"max_isi": 1_000_000_000}))
        assert sup.wait_config(bad2, 30).state == "rejected"
        assert sup.config.method == MethodConfig("tfi", small)
        assert sup.config.version == sup.applied_version == good
        assert any("window" in e["message"] for e in sup.errors)
        _frames(slot, 2, method="tfi")


    def test_unconfirmed_config_is_not_replayed_into_a_new_worker(self, pipeline):
        dev, ring, slot, sup, acq = pipeline
        _frames(slot, 1)
        restarts = sup.restarts
        sup.inject("crash", code=3)  # dies before it reads the config below
        v = sup.configure(_cfg("tfi"))
        state, reason = sup.wait_config(v, 60)
        assert state == "rejected" and "exited" in reason
        assert sup.config.method.method == "tfp"
        wait_until(lambda: sup.restarts > restarts, 60, "a restart", interval=0.05)
        assert sup.restarts == restarts + 1 and sup.ready.wait(120)
        seq = slot.seq
        # a frame of the new worker, with the confirmed method
        f = wait_until(lambda: slot.read(since=seq), 120, "a frame after the restart",
                       interval=0.005)
        assert f.method == "tfp", "no frames of the confirmed method after the restart"
        assert sup.applied_version == sup.config.version


def test_a_slow_first_frame_is_reported_and_not_taken_for_a_hang(rec):
    """The first frame under a config may wait on numba's compiler for minutes on a machine's
    first use: the worker reports how long it has been computing, and neither the supervisor
    (hang_timeout far shorter than the wait) nor the pool's watchdog restarts it."""
    dev = ReplayDevice(rec, mode="unpaced", loop=True, block_frames=64)
    dev.open()
    ring = SpikeRing.create(8, 64, rec.layout.frame_bytes, blocking=True)
    slot = FrameSlot.create(max_pixels=H * W)
    # 3 s, not 1: on a loaded 2-core host one loop of the worker (a block copy, a frame in
    # process) can hold its heartbeat past a second; the first frame still waits 2.7x longer
    sup = WorkerSupervisor(slot, _cfg(), hang_timeout=3.0)
    acq = Acquisition(dev, ring)
    try:
        sup.start(str(ring.path), rec.layout)
        assert sup.ready.wait(120), "worker did not start"
        acq.start()
        _frames(slot, 2)
        sup.inject("slow_first", seconds=8.0)  # longer than hang_timeout
        v = sup.configure(_cfg("tfi"))
        wait_until(
            lambda: (sup.status(40_000.0).status.first_frame_s or 0) > 3.5,
            30,
            "the pending first frame in the status",
            interval=0.05,
        )
        _frames(slot, 2, method="tfi")
        assert sup.restarts == 0, sup.crashes
        assert sup.status(40_000.0).status.first_frame_s is None
        assert sup.applied_version == v
    finally:
        acq.stop()
        sup.stop()
        ring.close()
        slot.close()


@pytest.fixture(scope="class")
def two_processes(rec):
    yield from _pipeline(rec, workers=2)


@pytest.fixture
def pool_pipeline(two_processes):
    """The deterministic pipeline with a pool of two reconstruction processes."""
    return _on_tfp(two_processes)


def test_pick_tier_holds_the_budget():
    """The auto rule: full while full frames fit the budget; else the share of full frames
    that keeps the mean cost within it; fast only when even fast frames do not fit."""
    assert pick_tier(None, None, 50.0, 0.0)[0] == "full"  # not measured: try it
    assert pick_tier(40.0, 10.0, 50.0, 0.0)[0] == "full"
    assert pick_tier(100.0, None, 50.0, 0.0)[0] == "fast"
    for full, fast, budget in ((100.0, 20.0, 50.0), (90.0, 30.0, 80.0), (200.0, 10.0, 11.0)):
        credit, tiers = 0.0, []
        for _ in range(400):
            tier, credit = pick_tier(full, fast, budget, credit)
            tiers.append(tier)
        mean = sum(full if x == "full" else fast for x in tiers) / len(tiers)
        assert mean <= budget + 1e-9 and mean >= budget - (full - fast) / len(tiers) - 1e-9
        assert "full" in tiers and "fast" in tiers
    tiers = [pick_tier(100.0, 60.0, 50.0, 0.0)[0] for _ in range(10)]
    assert set(tiers) == {"fast"}


class TestTwoProcesses:
    """The pipeline with a pool of two processes, one for the class."""

    def test_two_workers_publish_the_offline_frames_in_step_order(self, rec, pool_pipeline):
        """Frames computed side by side are the offline frames, shown in increasing step; the
        status says how many processes run and counts what was computed but not shown."""
        dev, ring, slot, sup, acq = pool_pipeline
        for method in ("tfp", "csr"):
            if method != "tfp":
                sup.configure(_cfg(method))
            frames = _frames(slot, 12, method=method)
            steps = [f.step for f in frames]
            assert steps == sorted(steps) and len(set(steps)) == len(steps)
            compared = 0
            for f in frames:
                exp = _expected(rec, method, f.step)
                if exp is not None:
                    assert np.array_equal(f.image, exp[0]), f"{method} at step {f.step} differs"
                    compared += 1
            assert compared >= 3
        st = sup.status(40_000.0).status
        assert st.workers == 2 and st.threads_per_worker == 1
        assert st.frames_out >= 24
        # results wait for every older step of their config before they are shown, so two
        # processes never show a step out of order (what finishes early waits, it is not dropped)
        assert st.dropped_order == 0, st
        assert sup.stats().ring_lost_frames == 0

    def test_auto_quality_shows_fast_frames_when_full_ones_cannot_hold_the_rate(
        self, rec, pool_pipeline
    ):
        """CFSR under quality = auto at a frame rate full frames cannot hold: fast frames are
        shown and the status counts each tier and names the tier shown; quality = full then
        shows full frames only, and its shares count from the change."""
        dev, ring, slot, sup, acq = pool_pipeline
        cfg = WorkerConfig(MethodConfig("cfsr"), gain=GAIN, max_fps=1000.0, deterministic=True,
                           quality="auto")
        sup.configure(cfg)
        _frames(slot, 16, method="cfsr", timeout=240)
        q = sup.status(40_000.0).status.quality
        assert q.mode == "auto" and q.shown in ("full", "fast")
        assert q.fast >= 8, q
        sup.configure(WorkerConfig(MethodConfig("cfsr", {"quality": "full"}), gain=GAIN,
                                   max_fps=1000.0, deterministic=True, quality="full"))
        wait_until(lambda: sup.applied_version == sup.config.version, 30, "the applied version")
        _frames(slot, 4, method="cfsr", timeout=120)
        # the shares start again with the mode: the fast frames of auto are not counted
        q1 = sup.status(40_000.0).status.quality
        assert q1.mode == "full" and q1.fast == 0 and q1.full >= 1 and q1.shown == "full", q1


    def test_frames_of_a_ready_method_stand_in_while_a_first_frame_waits(
        self, rec, pool_pipeline
    ):
        """A first frame that waits (as on numba's compiler): TFP frames keep coming meanwhile,
        and the status names the stand-in; then the chosen method's frames take over."""
        dev, ring, slot, sup, acq = pool_pipeline
        _frames(slot, 2, method="tfp")
        sup.inject("slow_first", seconds=4.0)
        sup.configure(_cfg("csr"))
        wait_until(lambda: sup.status(40_000.0).status.fallback_method == "tfp", 30,
                   "the stand-in named in the status", interval=0.05)
        seq = slot.seq
        stand_in = _frames(slot, 4, method="tfp", timeout=30)  # the first may be the one shown
        assert sum(f.seq > seq for f in stand_in) >= 3
        _frames(slot, 2, method="csr", timeout=60)
        st = sup.status(40_000.0).status
        assert st.fallback_method is None and st.fallback_frames >= 3


@pytest.fixture
def fresh_pool(rec):
    """A pipeline of two processes of its own: the climb TFP -> CSR -> CFSR is that of a
    pool whose processes have computed no CSR or CFSR frame yet (the class's pool has)."""
    yield from _pipeline(rec, workers=2)


def test_while_cfsr_compiles_the_picture_climbs_to_csr_with_its_progress(rec, fresh_pool):
    """A CFSR first frame held as by a compile (each process reports it every second):
    TFP stands in at once, then CSR from the idle process, named in the status with what
    the first frame waits on; then CFSR takes over and the stand-ins stop."""
    dev, ring, slot, sup, acq = fresh_pool
    _frames(slot, 2, method="tfp")
    # held long enough for the idle process to load CSR's kernels and show two of its frames
    # on a busy host (the rung's frames come at most 5 a second)
    sup.inject("slow_first", seconds=30.0)
    sup.configure(_cfg("cfsr"))
    wait_until(lambda: sup.status(40_000.0).status.fallback_method == "csr", 60,
               lambda: f"CSR named as the stand-in (status "
               f"{sup.status(40_000.0).status.fallback_method})", interval=0.05)
    # the rung reaches the status through the frame slot's counters, what the first frame
    # waits on through the worker's event queue: the two may land a moment apart
    wait_until(lambda: (c := sup.status(40_000.0).status.compiling) is not None
               and c.method == "cfsr", 10,
               lambda: f"CFSR's compile named (status {sup.status(40_000.0).status.compiling})",
               interval=0.05)
    st = sup.status(40_000.0).status
    assert st.compiling is not None and st.compiling.kernel  # what it waits on, named
    _frames(slot, 2, method="csr", timeout=30)
    _frames(slot, 2, method="cfsr", timeout=120)
    st = sup.status(40_000.0).status
    assert st.fallback_method is None and st.compiling is None


def test_a_restarted_step_clock_shows_its_frames_at_once(rec):
    """The step clock starts again (a camera that restarted its counter; another source on
    the same ring): the new clock's frames are shown at once. The worker used to wait until
    the new clock passed the old one, as long as the old source had played: it submitted
    nothing older than its last frame and took the new frames' arrival from the old steps
    (so they were dropped as late)."""
    from cfsr_live.driver.source import BlockFlags

    ring = SpikeRing.create(8, 64, rec.layout.frame_bytes, blocking=True)
    slot = FrameSlot.create(max_pixels=H * W)
    sup = WorkerSupervisor(slot, _cfg(), workers=2)
    rng = np.random.default_rng(0)

    def play(start: int, n: int, flags: int = 0) -> None:
        for a in range(start, start + n, 64):
            data = rng.integers(0, 256, (64, rec.layout.frame_bytes), dtype=np.uint8)
            ring.write(a, data, flags=flags if a == start else 0)

    try:
        sup.start(str(ring.path), rec.layout)
        assert sup.ready.wait(120), "worker did not start"
        old_end = 64 * 64
        play(0, old_end)
        wait_until(lambda: (f := slot.read()) is not None and f.step > old_end // 2, 120,
                   "frames of the first clock")
        # not a wait for a condition: the first clock's blocks must become older than a frame
        # may be late, as after a source that played a while
        time.sleep(LATE_S + 0.5)
        new_end = 64 * 12
        play(0, new_end, BlockFlags.DISCONTINUITY)  # the counter starts again at 0
        # the old worker never shows a step below the old clock's last one, so a frame of
        # the new clock within the deadline is the check (measured: 3.4 s with the start)
        wait_until(lambda: (f := slot.read()) is not None and f.step < new_end, 20,
                   lambda: f"a frame of the new clock (latest {slot.read().step}, "
                   f"dropped late {slot.stats().dropped_late})")
    finally:
        sup.stop()
        ring.close()
        slot.close()


def test_a_worker_started_on_a_paused_replay_shows_what_the_ring_holds(rec):
    """The worker reads the ring from the oldest block it still holds: a replay paused before
    the worker's first frame (or before it started at all), then sought and stepped, leaves its
    data in the ring and writes nothing more. The worker's reader started at the ring's head
    and never saw those blocks, so no frame came until the replay played on."""
    ring = SpikeRing.create(16, 64, rec.layout.frame_bytes)  # paced: the producer never waits
    slot = FrameSlot.create(max_pixels=H * W)
    paced = WorkerConfig(MethodConfig("tfp"), gain=GAIN, max_fps=200.0)
    sup = WorkerSupervisor(slot, paced, workers=1)
    try:
        for a in range(0, 64 * 8, 64):  # what the replay delivered before it paused
            ring.write(a, rec.packed(a, a + 64))
        sup.start(str(ring.path), rec.layout)
        assert sup.ready.wait(120), "worker did not start"
        wait_until(lambda: (f := slot.read()) is not None and f.method == "tfp", 120,
                   lambda: f"a frame from the blocks held (slot {slot.stats()})")
    finally:
        sup.stop()
        ring.close()
        slot.close()
