"""Hot and dead pixels: the online map, the correction in the spikes, the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from cfsr import Layout, StreamingReconstructor
from cfsr._bits import pack_frames, unpack_layout
from cfsr.defects import (
    DefectCorrector,
    DefectMap,
    DefectParams,
    classify,
    correct_packed,
    corrected,
    load_map,
    plan_donors,
    save_map,
    score_map,
)
from cfsr.simulate import Scene, simulate
from cfsr.spikes import SpikeRecording

H, W = 48, 64


def _flat(rate: float = 0.25) -> np.ndarray:
    return np.full((H, W), rate)


def _gauss(img: np.ndarray, cy: float, cx: float, peak: float, sd: float) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return img + peak * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * sd * sd))


def test_classify_flags_isolated_hot_and_silent_dead_pixels_only():
    steps = 2000
    r = _flat(0.2)
    r[10, 10] += 0.125  # hot, the faintest of the simulator's
    r[11, 11] += 0.25  # hot, touching the first
    r = _gauss(r, 30, 40, 0.3, 0.7)  # a star (a sharp lens: 0.7 px blur)
    r[20:24, 5:9] = 0.45  # a lamp: a small bright patch
    counts = np.round(r * steps).astype(np.int64)
    counts[40, 50] = 0  # dead
    m = classify(counts, steps)
    assert set(zip(*np.nonzero(m.hot), strict=True)) == {(10, 10), (11, 11)}
    assert set(zip(*np.nonzero(m.dead), strict=True)) == {(40, 50)}
    assert (m.n_hot, m.n_dead, m.steps) == (2, 1, steps)


def test_classify_waits_for_its_warm_up_and_spares_dark_pixels():
    counts = np.zeros((H, W), np.int64)
    counts[5, 5] = 100
    assert classify(counts, 100).mask.sum() == 0  # before min_steps: nothing
    # a pixel that never fired in a dark neighbourhood is not dead: nothing promised a spike
    dark = np.full((H, W), 3, np.int64)
    dark[9, 9] = 0
    assert not classify(dark, 2000).dead.any()


def _packed(frames: np.ndarray, layout: Layout) -> np.ndarray:
    """Pack upright frames as ``layout`` stores them (head columns at the right of the rows
    of the flipped image)."""
    stored = frames[:, ::-1] if layout.flipud else frames
    stored = stored[:, :, ::-1] if layout.fliplr else stored
    pad = np.zeros(frames.shape[:2] + (layout.head_cols,), np.uint8)
    return pack_frames(np.concatenate([stored, pad], axis=2), flipud=False)


@pytest.mark.parametrize("layout", [Layout(W, H), Layout(W - 8, H, head_cols=8, fliplr=True)])
def test_correction_gives_a_defect_its_donors_spikes_and_touches_nothing_else(layout):
    rng = np.random.default_rng(0)
    frames = (rng.random((50, layout.height, layout.width)) < 0.3).astype(np.uint8)
    hot = np.zeros(layout.shape, bool)
    hot[0, 0] = hot[7, 9] = True
    dmap = DefectMap(hot, np.zeros_like(hot))
    plan = plan_donors(dmap, layout)
    packed = _packed(frames, layout)
    out = unpack_layout(correct_packed(packed, plan), layout)
    assert np.array_equal(unpack_layout(packed, layout), frames)  # the input is left alone
    keep = ~hot
    assert np.array_equal(out[:, keep], frames[:, keep])
    for y, x in zip(*np.nonzero(hot), strict=True):
        assert any(np.array_equal(out[:, y, x], frames[:, y + dy, x + dx])
                   for dy, dx in ((0, -1), (0, 1), (-1, 0), (1, 0))
                   if 0 <= y + dy < layout.height and 0 <= x + dx < layout.width)


def _flat_scene_with_defects(steps: int):
    noise = "hot_fraction=0.004,hot_rate=0.5,dead_fraction=0.004"
    sim = simulate(Scene("flat", np.full((H, W), 0.5, np.float32)), steps, seed=3, noise=noise)
    return sim, SpikeRecording.from_array(sim.spikes)


def test_simulator_draws_a_true_defect_map_and_dead_pixels_never_fire():
    sim, _ = _flat_scene_with_defects(400)
    truth = sim.sensor.defect_map
    assert truth.n_hot == truth.n_dead == round(0.004 * H * W)
    assert not (truth.hot & truth.dead).any()
    assert sim.spikes[:, truth.dead].sum() == 0
    rates = sim.spikes.mean(0)
    assert rates[truth.hot].min() > rates[~truth.mask].max()
    # dead pixels are drawn last: the other maps are those of the sensor without them
    plain = simulate(Scene("flat", np.full((H, W), 0.5, np.float32)), 1, seed=3,
                     noise="hot_fraction=0.004,hot_rate=0.5")
    assert np.array_equal(plain.sensor.threshold_map, sim.sensor.threshold_map)
    assert np.array_equal(plain.sensor.hot_mask, sim.sensor.hot_mask)


def test_offline_correction_finds_the_true_map_and_repairs_the_rates():
    sim, rec = _flat_scene_with_defects(2000)
    fixed = corrected(rec, steps=2000)
    s = score_map(fixed.defect_map, sim.sensor.defect_map)
    assert s["hot_precision"] == s["hot_recall"] == 1.0
    assert s["dead_precision"] == s["dead_recall"] == 1.0
    before = rec.frames(0, 2000).mean(0)
    after = fixed.frames(0, 2000).mean(0)
    bad = sim.sensor.defect_map.mask
    assert np.abs(before[bad] - 0.25).max() > 0.2
    assert np.abs(after[bad] - 0.25).max() < 0.02


def test_streaming_reconstructor_learns_online_and_every_method_reads_corrected_spikes():
    sim, rec = _flat_scene_with_defects(3000)
    params = DefectParams(warmup=1000, refresh=256)
    fix = DefectCorrector(rec.layout, params=params)
    sr = StreamingReconstructor("tfp", rec.layout, params={"window": 160}, slack=1024,
                                defects=fix)
    assert fix.state()["state"] == "learning"
    for a in range(0, 3000, 500):
        sr.push(rec.packed(a, a + 500), a)
    st = fix.state()
    assert st["state"] == "ready" and st["confidence"] == 1.0
    assert (st["hot"], st["dead"]) == (sim.sensor.defect_map.n_hot, sim.sensor.defect_map.n_dead)
    rate = sr.compute(2900).rate
    assert np.abs(rate[sim.sensor.defect_map.mask] - 0.25).max() < 0.03
    off = DefectCorrector(rec.layout, params=params, enabled=False)
    sr_off = StreamingReconstructor("tfp", rec.layout, params={"window": 160}, slack=1024,
                                    defects=off)
    for a in range(0, 3000, 500):
        sr_off.push(rec.packed(a, a + 500), a)
    assert off.state()["state"] == "off" and off.state()["hot"] == st["hot"]
    assert np.abs(sr_off.compute(2900).rate[sim.sensor.dead_mask]).max() == 0.0


def test_map_json_round_trip_and_every_bad_value_refused(tmp_path):
    hot = np.zeros((H, W), bool)
    hot[1, 2] = True
    dead = np.zeros((H, W), bool)
    dead[3, 4] = True
    m = DefectMap(hot, dead, 2000, "stream")
    back = load_map(save_map(m, tmp_path / "cal.json"), (H, W))
    assert np.array_equal(back.hot, hot) and np.array_equal(back.dead, dead)
    assert (back.steps, back.source) == (2000, "stream")
    good = m.to_dict()
    for change, what in [
        ({"hot": [H * W]}, "outside"),
        ({"hot": [5, 5]}, "twice"),
        ({"dead": [good["hot"][0]]}, "both"),
        ({"hot": [1.5]}, "outside"),
        ({"width": W + 1}, "the recording"),
        ({"source": "guess"}, "source"),
        ({"extra": 1}, "unknown"),
        ({"hot": list(range(400))}, "at most"),
    ]:
        with pytest.raises(ValueError, match=what):
            DefectMap.from_dict({**good, **change}, (H, W))


def test_the_live_ring_and_a_corrected_recording_give_the_same_spikes_in_any_read_order():
    sim, rec = _flat_scene_with_defects(1500)
    dmap = sim.sensor.defect_map
    offline = corrected(rec, dmap)
    sr = StreamingReconstructor("tfp", rec.layout, slack=600,
                                defects=DefectCorrector(rec.layout, dmap))
    for a in range(0, 1000, 250):
        sr.push(rec.packed(a, a + 250), a)
    # apart, overlapping on the left, then on the right, steps read before from the other
    # half of the mirrored ring, across its wrap, then all
    for a, b in ((700, 800), (600, 750), (780, 1000), (770, 900), (450, 1000)):
        assert np.array_equal(sr.packed(a, b), offline.packed(a, b)), (a, b)
    sr.push(rec.packed(1000, 1500), 1000)  # the ring turns over: new steps, read once
    assert np.array_equal(sr.packed(sr.first_step, 1500), offline.packed(sr.first_step, 1500))
    sr.reset(0)  # the stream starts again: what was corrected is forgotten
    sr.push(rec.packed(0, 500), 0)
    assert np.array_equal(sr.packed(0, 500), offline.packed(0, 500))


def test_moving_texture_stars_and_lamps_are_never_flagged_and_true_defects_are():
    from cfsr.simulate import star_field

    sky = star_field(H, W, stars=6, lamps=2)
    for content in ("disk", "fan", sky):  # moving texture; a still sky with stars and lamps
        counts = simulate(content, 2000, height=H, width=W).spikes.sum(0, dtype=np.int64)
        assert classify(counts, 2000).mask.sum() == 0, content
    sim = simulate(sky, 2000, noise="hot_fraction=0.005,hot_rate=0.25,dead_fraction=0.002")
    s = score_map(classify(sim.spikes.sum(0, dtype=np.int64), 2000), sim.sensor.defect_map)
    assert s["hot_precision"] == s["dead_precision"] == s["dead_recall"] == 1.0
    assert s["hot_recall"] >= 0.9


def test_steps_read_before_the_map_changed_are_corrected_with_the_new_one():
    sim, rec = _flat_scene_with_defects(1200)
    fix = DefectCorrector(rec.layout, params=DefectParams(warmup=1000, refresh=256))
    sr = StreamingReconstructor("tfp", rec.layout, slack=1024, defects=fix)
    sr.push(rec.packed(0, 200), 0)
    assert np.array_equal(sr.packed(100, 200), rec.packed(100, 200))  # no map yet: as pushed
    sr.push(rec.packed(200, 1200), 200)
    assert fix.map.mask.sum() > 0
    assert np.array_equal(sr.packed(100, 200), correct_packed(rec.packed(100, 200), fix.plan))
