"""The static gate (:mod:`cfsr.methods.cfsr.static_gate`): a window whose counts did not change is
CFSR's TFP at once; anything that moves, or a gate switched off, takes the whole pipeline."""

from __future__ import annotations

import numpy as np
import pytest

import cfsr
from cfsr._bits import pack_frames, unpack_layout
from cfsr._words import PackedWindow
from cfsr.layout import Layout
from cfsr.methods.cfsr import pipeline
from cfsr.methods.cfsr.static_gate import span_counts, static_gate
from cfsr.methods.tfp import count_spikes, static_rate, tfp_rate


def _integrate_and_fire(rate: np.ndarray, steps: int, seed: int = 0) -> np.ndarray:
    """Spikes of pixels of constant brightness ``rate`` (spikes per step), random phases."""
    acc = np.random.default_rng(seed).random(rate.shape)
    out = np.zeros((steps, *rate.shape), np.uint8)
    for t in range(steps):
        acc += rate
        out[t] = acc >= 1.0
        acc -= out[t]
    return out


def _static(steps=900, h=24, w=36, seed=0):
    rate = 0.02 + 0.9 * np.random.default_rng(seed + 1).random((h, w))
    return _integrate_and_fire(rate, steps, seed)


@pytest.mark.parametrize(
    "flipud,fliplr,head", [(True, False, 0), (False, True, 8), (True, True, 8)]
)
def test_span_counts_equal_the_unpacked_count_for_every_layout(flipud, fliplr, head):
    rng = np.random.default_rng(5)
    lay = Layout(24, 16, head_cols=head, flipud=flipud, fliplr=fliplr)
    packed = rng.integers(0, 256, (300, lay.frame_bytes), dtype=np.uint8)
    frames = unpack_layout(packed, lay)
    src = PackedWindow.from_packed(packed, lay)
    for a, b in ((0, 300), (17, 200), (250, 251)):
        np.testing.assert_array_equal(span_counts(src, a, b), count_spikes(frames, a, b))


def test_a_static_scene_passes_and_its_counts_are_the_recent_span():
    s = _static()
    src = PackedWindow.from_frames(s)
    got = static_gate(src, 801, 160, 1)
    assert got is not None
    np.testing.assert_array_equal(got, count_spikes(s, 641, 801))
    assert static_gate(src, 801, 160, -1) is None  # gate off
    assert static_gate(src, 300, 160, 1) is None  # the two spans do not fit before step 0


def test_one_pixel_that_changes_by_two_spikes_fails_the_gate():
    s = _static()
    src = PackedWindow.from_frames(s)
    assert static_gate(src, 801, 160, 1) is not None
    moved = s.copy()
    y, x = 7, 30
    quiet = np.flatnonzero(moved[641:801, y, x] == 0)[:2] + 641
    moved[quiet, y, x] = 1  # two more spikes in the recent span at one pixel
    assert static_gate(PackedWindow.from_frames(moved), 801, 160, 1) is None
    assert static_gate(PackedWindow.from_frames(moved), 801, 160, 2) is not None


def test_head_columns_are_not_pixels():
    lay = Layout(32, 8, head_cols=8)
    frames = _static(600, 8, 32)
    packed = pack_frames(np.concatenate([frames, np.zeros((600, 8, 8), np.uint8)], axis=2))
    noisy = packed.reshape(600, 8, 5).copy()
    noisy[::3, :, 4] = 0xFF  # the head columns fire in bursts: no image pixel changed
    src = PackedWindow.from_packed(noisy.reshape(600, -1), lay)
    assert static_gate(src, 500, 160, 1) is not None


def test_cfsr_takes_the_gate_on_a_static_window_and_equals_the_full_pipeline(monkeypatch):
    s = _static()
    t = 700
    full, mf = cfsr.reconstruct(s, "cfsr", [t], return_masks=True, adaptive=False)

    def no_history(*args, **kw):
        raise AssertionError("the coarse-to-fine stages ran on a gated window")

    with monkeypatch.context() as mp:
        mp.setattr(pipeline, "history_scan", no_history)
        got, mg = cfsr.reconstruct(s, "cfsr", [t], return_masks=True)
    np.testing.assert_array_equal(got, full)
    # the default estimator over its default span, 160 steps centred on t
    want = static_rate(s, t, window=160, mode="centred", estimator="isi", max_isi=200)
    np.testing.assert_array_equal(got[0], np.clip(want, 0, 1))
    assert not mg["fine"].any() and not mg["coarse"].any()
    # the paper's TFP
    got = cfsr.reconstruct(s, "cfsr", [t], static_estimator="tfp")
    np.testing.assert_array_equal(
        got[0], np.clip(tfp_rate(s, t, window=160, mode="centred"), 0, 1)
    )
    # another TFP span than the gate's: the output is still that span's static estimate
    for est in ("tfp", "isi"):
        got = cfsr.reconstruct(
            s, "cfsr", [t], tfp_window=40, tfp_mode="centred", static_estimator=est
        )
        want = static_rate(s, t, window=40, mode="centred", estimator=est, max_isi=200)
        np.testing.assert_array_equal(got[0], want)


def test_a_moving_scene_or_a_gate_switched_off_takes_the_whole_pipeline(monkeypatch):
    from cfsr.simulate import simulate

    calls = []
    history = pipeline.history_scan

    def counted(*args, **kw):
        calls.append(1)
        return history(*args, **kw)

    monkeypatch.setattr(pipeline, "history_scan", counted)
    sim = simulate("disk", 900, seed=0, height=60, width=80)
    cfsr.reconstruct(sim.spikes, "cfsr", [700])
    assert calls == [1]
    cfsr.reconstruct(_static(), "cfsr", [700], static_tol=-1)
    assert calls == [1, 1]


@pytest.mark.parametrize("mode", ["trailing", "centred"])
def test_the_streaming_window_holds_the_gates_spans_with_a_short_history(monkeypatch, mode):
    """The streaming reconstructor hands a method exactly the steps its window asks for: with
    a short history the window must still reach back over the gate's two spans."""
    from cfsr.streaming import StreamingReconstructor

    s = _static(900, 8, 16)
    short = {"mog_frames": 1, "T": 20, "max_isi": 20, "pm_count": 2, "tfp_mode": mode}
    sr = StreamingReconstructor("cfsr", Layout(16, 8), params=short, slack=900)
    sr.push(pack_frames(s), 0)

    def no_history(*args, **kw):
        raise AssertionError("the coarse-to-fine stages ran on a gated window")

    monkeypatch.setattr(pipeline, "history_scan", no_history)
    out = sr.compute(sr.latest_step())
    assert not out.masks["fine"].any()


@pytest.mark.parametrize("where", ["first", "middle", "last", "none"])
def test_the_early_exit_gate_decides_as_the_two_counts_do_on_a_camera_frame(where):
    # the gate stops at the first chunk (512 stored pixels) that changed, visiting chunks in
    # a stride through the frame: a single changed pixel anywhere must still be found, and a
    # passing gate returns every pixel's count
    lay = Layout(400, 250)
    rate = np.random.default_rng(3).uniform(0.01, 0.6, (250, 400))
    s = _integrate_and_fire(rate, 340, seed=4)
    y, x = {"first": (0, 0), "middle": (131, 207), "last": (249, 399), "none": (0, 0)}[where]
    if where != "none":
        quiet = np.flatnonzero(s[180:340, y, x] == 0)[:3] + 180
        s[quiet, y, x] = 1
    src = PackedWindow.from_packed(pack_frames(s), lay)
    recent, before = span_counts(src, 180, 340), span_counts(src, 20, 180)
    got = static_gate(src, 340, 160, 1)
    if np.abs(recent - before).max() <= 1:
        assert got is not None
        np.testing.assert_array_equal(got, recent)
    else:
        assert where != "none" and got is None


@pytest.mark.parametrize("flipud,fliplr", [(False, False), (True, True)])
def test_the_gate_per_tile_marks_a_changed_tile_and_its_neighbours(flipud, fliplr):
    # one pixel changes by three spikes: its 16 x 16 tile and the tiles around it are active,
    # the rest of the frame is not (the gate per tile sees what the whole-frame gate sees)
    from cfsr.methods.cfsr.static_gate import active_tiles

    lay = Layout(100, 70, flipud=flipud, fliplr=fliplr)
    rate = np.random.default_rng(8).uniform(0.01, 0.6, (70, 100))
    s = _integrate_and_fire(rate, 340, seed=2)
    src = PackedWindow.from_packed(pack_frames(s, flipud=flipud, fliplr=fliplr), lay)
    assert not active_tiles(src, 340, 160, 1, 16).any()  # static: no tile changed
    y, x = 37, 50  # tile (2, 3)
    quiet = np.flatnonzero(s[180:340, y, x] == 0)[:3] + 180
    s[quiet, y, x] = 1
    src = PackedWindow.from_packed(pack_frames(s, flipud=flipud, fliplr=fliplr), lay)
    got = active_tiles(src, 340, 160, 1, 16)
    assert got.flags.c_contiguous  # a width of 100 px is not a whole number of tiles
    want = np.zeros((70, 100), bool)
    want[16:64, 32:80] = True  # tile rows 1-3, tile columns 2-4
    np.testing.assert_array_equal(got, want)
    assert not active_tiles(src, 340, 160, 3, 16).any()  # a change within tol
    assert active_tiles(src, 340, 160, -1, 16) is None  # gate off: no tile is static
    assert active_tiles(src, 300, 160, 1, 16) is None  # the spans do not fit before step 0
    far = active_tiles(src, 340, 160, 1, 16, margin=0)
    np.testing.assert_array_equal(far, np.pad(np.ones((16, 16), bool), ((32, 22), (48, 36))))
