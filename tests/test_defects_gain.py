"""Threshold spread: why the stream cannot measure it, the flat-field calibration that can,
and its correction of every method's output offline, live and on the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cfsr import StreamingReconstructor
from cfsr.api import reconstruct_outputs
from cfsr.cli import main
from cfsr.datfile import read_dat
from cfsr.defects import DefectCorrector, DefectMap, GainMap, calibrate, corrected, map_of
from cfsr.simulate import Scene, simulate, simulate_to_dat
from cfsr.spikes import SpikeRecording

H, W = 40, 56
SPREAD = "threshold_sd=0.05"


def _texture() -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return (0.45 + 0.3 * np.sin(xx / 3.0) * np.cos(yy / 4.0)).astype(np.float32)


def _true_gain(sim) -> np.ndarray:
    s = sim.sensor
    return (s.gain_map / s.gain) / (s.threshold_map / s.threshold)


def test_on_a_still_scene_a_threshold_spread_is_texture():
    """A sensor whose thresholds spread, looking at texture T, fires like an ideal sensor
    looking at T times every pixel's gain: from the stream alone the two cannot be told
    apart (long-run counts equal up to the one spike of each pixel's starting potential)."""
    steps = 3000
    spread = simulate(Scene("wall", _texture()), steps, seed=3, noise=SPREAD)
    g = _true_gain(spread)
    assert g.std() > 0.03
    ideal = simulate(Scene("wall", _texture() * g.astype(np.float32)), steps, seed=3,
                     noise="none")
    a = spread.spikes.sum(0, dtype=np.int64)
    b = ideal.spikes.sum(0, dtype=np.int64)
    assert np.abs(a - b).max() <= 1


def test_a_flat_field_measures_every_gain_and_the_correction_undoes_the_spread():
    noise = f"{SPREAD},hot_fraction=0.005,hot_rate=0.25,dead_fraction=0.005"
    flat = simulate(Scene("flat", np.full((H, W), 0.5, np.float32)), 4000, seed=2, noise=noise)
    cal = calibrate(SpikeRecording.from_array(flat.spikes))
    truth = flat.sensor.defect_map
    assert np.array_equal(cal.hot, truth.hot) and np.array_equal(cal.dead, truth.dead)
    good = ~cal.mask
    g = _true_gain(flat)
    assert np.sqrt(np.mean((cal.gain.gain - g)[good] ** 2)) < 0.005
    assert np.isfinite(cal.gain.gain).all() and cal.gain.gain.min() > 0.5  # dead ones too
    # the same sensor (same seed) on a still wall: TFP's rates against the ideal sensor's
    wall = Scene("wall", _texture())
    noise = f"{SPREAD},hot_fraction=0.005,hot_rate=0.25,dead_fraction=0.005"
    spread = SpikeRecording.from_array(simulate(wall, 1200, seed=2, noise=noise).spikes)
    ideal = SpikeRecording.from_array(simulate(wall, 1200, seed=2, noise="none").spikes)
    t = [800]

    def err(rec) -> float:
        got = reconstruct_outputs(rec, "tfp", t, params={"window": 600})[0].rate
        want = reconstruct_outputs(ideal, "tfp", t, params={"window": 600})[0].rate
        return float(np.sqrt(np.mean((got - want)[good] ** 2)))

    no_gain = DefectMap(cal.hot, cal.dead, cal.steps, "calibration")
    assert err(corrected(spread, cal)) < 0.25 * err(corrected(spread, no_gain))


def test_the_gain_travels_with_the_map_and_a_bad_one_is_refused(tmp_path):
    rng = np.random.default_rng(0)
    g = GainMap(1 + 0.05 * rng.standard_normal((H, W)), 4000)
    m = DefectMap(np.zeros((H, W), bool), np.zeros((H, W), bool), 4000, "calibration", g)
    back = DefectMap.from_dict(json.loads(json.dumps(m.to_dict())), (H, W))
    assert back.gain is not None and np.abs(back.gain.gain - g.gain).max() < 1e-4
    assert back.gain.steps == 4000
    d = m.to_dict()["gain"]
    for bad in ({**d, "data": "not base64!"}, {**d, "scale": 0}, {**d, "extra": 1},
                {**d, "data": GainMap(np.ones((H, W + 1))).to_dict()["data"]},
                {**d, "data": GainMap(np.ones((H, W - 1))).to_dict()["data"]}):
        with pytest.raises(ValueError, match="gain"):
            DefectMap.from_dict({**m.to_dict(), "gain": bad}, (H, W))


def test_live_and_offline_divide_the_same_gain_out_and_off_leaves_it():
    rec = SpikeRecording.from_array(simulate(Scene("wall", _texture()), 900, seed=1,
                                             noise=SPREAD).spikes)
    g = GainMap(np.linspace(0.9, 1.1, H * W).reshape(H, W))
    cal = DefectMap(np.zeros((H, W), bool), np.zeros((H, W), bool), 0, "calibration", g)
    t = [700]
    offline = reconstruct_outputs(corrected(rec, cal), "tfi", t)[0].rate
    plain = reconstruct_outputs(rec, "tfi", t)[0].rate
    np.testing.assert_allclose(offline, np.minimum(plain / g.gain, 1), rtol=1e-5)
    for enabled, want in ((True, offline), (False, plain)):
        d = DefectCorrector(rec.layout, cal, enabled=enabled)
        sr = StreamingReconstructor("tfi", rec.layout, defects=d)
        sr.push(rec.packed(0, rec.n_frames), 0)
        assert np.array_equal(sr.compute(t[0], final=True).rate, want)
        assert d.state()["gain"] is True and d.current().gain is g


def test_cli_flat_field_calibration_reaches_reconstruct(tmp_path, capsys):
    noise = f"{SPREAD},hot_fraction=0.004,hot_rate=0.5"
    flat, scene = tmp_path / "flat.dat", tmp_path / "scene.dat"
    simulate_to_dat(Scene("flat", np.full((H, W), 0.5, np.float32)), 3000, flat, seed=4,
                    noise=noise)
    simulate_to_dat(Scene("wall", _texture()), 1500, scene, seed=4, noise=noise)
    cal = tmp_path / "cal.json"
    assert main(["info", str(flat), "-q", "--json", "--flat-field",
                 "--export-defects", str(cal)]) == 0
    info = json.loads(capsys.readouterr().out)["defects"]
    assert 0.03 < info["gain"]["sd"] < 0.07 and info["steps"] == 3000
    given = DefectMap.from_dict(json.loads(cal.read_text()), (H, W))
    assert given.gain is not None and given.n_hot > 0

    def rate(name, *opt):
        out = tmp_path / name
        assert main(["reconstruct", str(scene), "-m", "tfp", "-t", "1000", "-o", str(out),
                     "-q", *opt]) == 0
        return np.load(out / "t1000.npy")

    fixed, off = rate("cal", "--defects", str(cal)), rate("off", "--defects", "off")
    want = reconstruct_outputs(corrected(read_dat(scene), given), "tfp", [1000])[0].rate
    assert np.array_equal(fixed, want) and not np.array_equal(fixed, off)
    # kept in the sidecar: a replay (the default --defects sidecar) starts calibrated
    assert main(["info", str(flat), "-q", "--flat-field", "--save-defects"]) == 0
    assert map_of(read_dat(flat)).gain is not None


def test_every_offline_path_reads_the_same_corrected_and_calibrated_frames():
    """Streamed through a reconstructor (corrected in its buffer), on a pool (a corrected
    copy) and window by window: the same outputs, gain included."""
    from cfsr.offline import stream_reconstruct

    noise = f"{SPREAD},hot_fraction=0.01,hot_rate=0.5,dead_fraction=0.005"
    rec = SpikeRecording.from_array(simulate(Scene("wall", _texture()), 1500, seed=6,
                                             noise=noise).spikes)
    cal = calibrate(SpikeRecording.from_array(simulate(
        Scene("flat", np.full((H, W), 0.5, np.float32)), 3000, seed=6, noise=noise).spikes))
    fixed = corrected(rec, cal)
    assert fixed.plan.targets.size > 10
    ts = [300, 700, 1400]
    want = [o.rate for o in reconstruct_outputs(fixed, "tfi", ts)]
    for workers in (1, 2):
        got = [o.rate for _, o in stream_reconstruct(fixed, "tfi", ts, workers=workers)]
        assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True)), workers
    plain = [o.rate for o in reconstruct_outputs(rec, "tfi", ts)]
    assert not np.array_equal(plain[1], want[1])


def test_a_method_that_borrows_spikes_keeps_its_borrowed_pixels_as_they_are():
    """CFSR builds its dynamic pixels (its coarse mask) from spikes along the motion, whose
    gains average out: only its other pixels are divided; a method without such a mask has
    every pixel divided."""
    from cfsr.defects import flatten
    from cfsr.methods.registry import Output, get_method

    rng = np.random.default_rng(1)
    rate = rng.uniform(0.1, 0.5, (H, W)).astype(np.float32)
    moving = np.zeros((H, W), bool)
    moving[10:20, 10:30] = True
    inv = (1 / GainMap(rng.uniform(0.9, 1.1, (H, W))).gain).astype(np.float32)
    out = Output(rate, {"coarse": moving})
    assert get_method("cfsr").borrowed_mask == "coarse" and get_method("csr").borrowed_mask is None
    cfsr = flatten(out, inv, get_method("cfsr")).rate
    csr = flatten(out, inv, get_method("csr")).rate
    np.testing.assert_array_equal(cfsr[moving], rate[moving])
    np.testing.assert_allclose(cfsr[~moving], rate[~moving] * inv[~moving], rtol=1e-6)
    np.testing.assert_allclose(csr, rate * inv, rtol=1e-6)
