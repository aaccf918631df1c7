"""The replay device: byte-exact blocks, loop, seek, pause/step, pacing on a fake clock,
behind-schedule skipping, and capability discovery (no camera facility on a replay)."""

from __future__ import annotations

import numpy as np
import pytest

from cfsr.datfile import read_dat, write_dat
from cfsr_live.driver.source import (
    BlockFlags,
    CameraControl,
    ReplayControl,
    SourceEnded,
    SourceState,
)
from cfsr_live.replay.device import ReplayDevice
from cfsr_live.replay.pattern import pattern_recording


@pytest.fixture(scope="module")
def dat(tmp_path_factory):
    p = tmp_path_factory.mktemp("rep") / "pat.dat"
    write_dat(p, pattern_recording(1000, height=20, width=32))
    return p


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _drain(dev, limit=10_000):
    out = []
    for _ in range(limit):
        try:
            b = dev.read_block(0)
        except SourceEnded:
            break
        if b is None:
            break
        out.append((b.index, b.data.copy(), b.flags, b.lost_before))
    return out


def test_fast_mode_is_byte_exact_and_ends(dat):
    rec = read_dat(dat)
    dev = ReplayDevice(dat, mode="unpaced", loop=False, block_frames=96)
    with dev:
        blocks = _drain(dev)
        assert dev.state == SourceState.STREAMING
        with pytest.raises(SourceEnded):
            dev.read_block(0)
    data = np.concatenate([b[1] for b in blocks])
    assert np.array_equal(data, np.asarray(rec.packed()))
    idx = [b[0] for b in blocks]
    assert idx == list(range(0, 1000, 96))
    assert blocks[-1][2] & BlockFlags.END
    assert dev.read_block(0) is None  # closed


def test_loop_keeps_the_clock_running(dat):
    rec = read_dat(dat)
    dev = ReplayDevice(dat, mode="unpaced", loop=True, block_frames=300)
    dev.open()
    blocks = [dev.read_block(0) for _ in range(6)]
    # 300, 300, 300, 100 (end of file), then the content wraps while the index continues
    assert [b.n_frames for b in blocks] == [300, 300, 300, 100, 300, 300]
    assert [b.index for b in blocks] == [0, 300, 600, 900, 1000, 1300]
    assert np.array_equal(blocks[4].data, rec.packed(0, 300))
    assert dev.get_facility(ReplayControl).state()["loops"] == 1


def test_seek_pause_step(dat):
    rec = read_dat(dat)
    dev = ReplayDevice(dat, mode="unpaced", block_frames=50)
    dev.open()
    ctl = dev.get_facility(ReplayControl)
    assert ctl is not None
    dev.read_block(0)
    ctl.seek(777)
    b = dev.read_block(0)
    assert b.flags & BlockFlags.DISCONTINUITY
    assert np.array_equal(b.data, rec.packed(777, 827))
    assert ctl.state()["position"] == 827
    ctl.pause()
    assert dev.state == SourceState.PAUSED
    assert dev.read_block(0.01) is None
    ctl.step(7)
    b = dev.read_block(0)
    assert b.n_frames == 7 and np.array_equal(b.data, rec.packed(827, 834))
    assert dev.read_block(0.01) is None
    with pytest.raises(ValueError):
        ctl.seek(1000)
    with pytest.raises(ValueError):
        ctl.set_speed(0)


def test_paced_on_a_fake_clock(dat):
    clk = FakeClock()
    dev = ReplayDevice(dat, mode="paced", block_frames=40, clock=clk, speed=1.0)
    dev.open()
    # block of 40 frames is due 40 / 40000 s = 1 ms after start
    assert dev.read_block(0) is None
    clk.t += 0.00099
    assert dev.read_block(0) is None
    clk.t += 0.00002
    b = dev.read_block(0)
    assert b is not None and b.index == 0 and b.n_frames == 40
    assert dev.read_block(0) is None
    # half speed: the next block is due 2 ms after the change
    dev.get_facility(ReplayControl).set_speed(0.5)
    clk.t += 0.0019
    assert dev.read_block(0) is None
    clk.t += 0.0002
    assert dev.read_block(0).index == 40


def test_paced_behind_schedule_skips_and_counts(dat):
    clk = FakeClock()
    dev = ReplayDevice(dat, mode="paced", block_frames=40, clock=clk, max_lag_s=0.01)
    dev.open()
    assert dev.read_block(0) is None  # the schedule starts at the first read
    clk.t += 0.001
    assert dev.read_block(0).index == 0
    clk.t += 0.5  # the reader stalled for half a second
    b = dev.read_block(0)
    assert b.flags & BlockFlags.LOSS
    assert b.lost_before > 0 and b.index == 40 + b.lost_before
    assert dev.counters().replay_behind_frames == b.lost_before
    # after the skip it is back on schedule: nothing more is due
    assert dev.read_block(0) is None or dev.read_block(0) is None



def test_the_schedule_starts_at_the_first_read_not_at_open(dat):
    """What a service does between opening a replay and reading it (making its ring, starting
    its threads) is no reader's lag: the schedule counts from the first read. It counted from
    the open, so a start that took over max_lag_s skipped frames nobody had been late for."""
    clk = FakeClock()
    dev = ReplayDevice(dat, mode="paced", block_frames=40, clock=clk, max_lag_s=0.01)
    dev.open()
    clk.t += 0.5  # the service made its ring and started the acquisition thread
    assert dev.read_block(0) is None  # the first block is due 1 ms after the first read
    clk.t += 0.001
    b = dev.read_block(0)
    assert b.index == 0 and b.lost_before == 0 and not b.flags & BlockFlags.LOSS
    assert dev.counters().replay_behind_frames == 0


def test_capability_discovery_replay_has_no_camera(dat):
    dev = ReplayDevice(dat)
    assert dev.get_facility(CameraControl) is None  # callers must check, never assume
    assert dev.get_facility(ReplayControl) is not None
    assert dev.capabilities() == ["replay"]
    assert dev.describe()["kind"] == "replay"


def test_unpaced_mode_and_its_former_name(dat, capsys):
    """The mode that delivers as fast as the reader reads is ``unpaced``; ``fast``, its former
    name (it read like CFSR's fast quality tier), still works with a deprecation message, in
    the library and on ``cfsr serve``'s command line; the state names the mode."""
    import argparse

    from cfsr_live.driver.source import ReplayMode
    from cfsr_live.service.commands import serve

    dev = ReplayDevice(dat, mode="unpaced")
    assert dev.mode is ReplayMode.UNPACED and dev.get_facility(ReplayControl).state()["mode"] \
        == "unpaced"
    with pytest.warns(DeprecationWarning, match="'unpaced'"):
        assert ReplayDevice(dat, mode="fast").mode is ReplayMode.UNPACED
    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    assert serve.build_settings(p.parse_args([])).replay_mode is ReplayMode.PACED
    mode = serve.build_settings(p.parse_args(["--replay-mode", "fast"])).replay_mode
    assert mode is ReplayMode.UNPACED and "now named --replay-mode unpaced" in \
        capsys.readouterr().err
    with pytest.raises(SystemExit):
        p.parse_args(["--replay-mode", "warp"])


def test_bad_arguments(dat):
    with pytest.raises(ValueError, match="mode"):
        ReplayDevice(dat, mode="warp")
    with pytest.raises(ValueError, match="frame range"):
        ReplayDevice(dat, start=900, end=2000)


def test_facility_interfaces_are_enforced():
    """A facility that lacks a method of its interface cannot be made (Facility is an ABC)."""
    from cfsr_live.driver.source import Facility

    class HalfReplay(ReplayControl):
        def play(self) -> None: ...

    with pytest.raises(TypeError, match="abstract"):
        HalfReplay()
    with pytest.raises(TypeError):
        Facility()
    with pytest.raises(TypeError):
        CameraControl()
