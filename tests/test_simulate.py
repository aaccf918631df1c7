"""The simulator: determinism, ground truth consistent with the spikes, motion masks, files."""

from __future__ import annotations

import json

import numpy as np
import pytest

import cfsr
from cfsr.cli import main
from cfsr.simulate import (
    NOISE_PRESETS,
    SCENES,
    Noise,
    Sensor,
    gt_path,
    load_ground_truth,
    make_scene,
    simulate,
    simulate_to_dat,
)

H, W = 48, 64
MOVING = ("disk", "fan", "car", "lowlight", "dim", "noisy", "blades")
# moving mounts: the motion mask is where the motion is visible, not every pixel that changes
# (tests/test_simulate_scenes.py)
MOUNTS = ("vibrate", "vibrate_mover", "drift", "pan")


def test_scene_names_match_cli_list():
    from cfsr.cli.simulate import SCENE_NAMES

    assert tuple(SCENES) == SCENE_NAMES


@pytest.mark.parametrize("name", list(SCENES))
def test_scene_intensity_and_mask(name):
    s = make_scene(name, height=H, width=W)
    img, mask = s.intensity_and_mask(123)
    assert img.dtype == np.float32 and img.shape == (H, W)
    assert 0.0 <= img.min() and img.max() <= 1.0
    assert mask.dtype == np.bool_ and mask.shape == (H, W)
    assert s.describe()["name"] == name
    json.dumps(s.describe())  # JSON-ready (goes to the sidecar)
    if name in MOVING + MOUNTS:
        assert mask.any() and s.moving
    else:
        assert not mask.any() and not s.moving


@pytest.mark.parametrize("name", MOVING)
def test_changes_happen_inside_the_motion_mask(name):
    s = make_scene(name, height=H, width=W)
    a, ma = s.intensity_and_mask(500)
    b, mb = s.intensity_and_mask(560)
    changed = np.abs(a - b) > 1e-6
    assert changed.any()
    # the mask holds every pixel a moving object touches, so nothing changes outside it
    assert not (changed & ~(ma | mb)).any()


def test_static_scene_never_changes():
    s = make_scene("static", height=H, width=W)
    np.testing.assert_array_equal(s.intensity(0), s.intensity(10_000_000_000))


def test_disk_period_is_1200_steps_at_2000_rpm():
    # 2000 rpm at 40 kHz: one turn every 40000 * 60 / 2000 = 1200 steps
    s = make_scene("disk", height=H, width=W)
    np.testing.assert_allclose(s.intensity(300), s.intensity(1500), atol=1e-4)
    assert np.abs(s.intensity(300) - s.intensity(600)).max() > 0.05


def test_car_speed_100kmh_at_100px_per_m():
    s = make_scene("car", height=H, width=W * 4)
    v = 100 / 3.6 * 100 / 40_000  # px/step
    (car,) = s.layers
    assert car.velocity == pytest.approx(v)
    xs = [np.flatnonzero(s.motion_mask(t).any(0)).min() for t in (0, 400)]
    assert xs[1] - xs[0] == pytest.approx(400 * v, abs=1.0)


def test_unknown_scene_lists_choices():
    with pytest.raises(ValueError, match="choices: disk, fan, car, static, lowlight"):
        make_scene("nope")
    with pytest.raises(ValueError, match="bad option"):
        make_scene("disk", height=H, width=W, colour="red")


def test_deterministic_by_seed():
    a = simulate("disk", 200, seed=7, height=H, width=W).spikes
    b = simulate("disk", 200, seed=7, height=H, width=W).spikes
    c = simulate("disk", 200, seed=8, height=H, width=W).spikes
    assert a.dtype == np.uint8 and a.shape == (200, H, W) and set(np.unique(a)) <= {0, 1}
    np.testing.assert_array_equal(a, b)
    assert (a != c).mean() > 0.05


@pytest.mark.parametrize("noise", [None, "spcs,electrons_per_spike=100"])
def test_chunking_does_not_change_the_spikes(noise):
    scene = make_scene("fan", height=H, width=W)
    one = Sensor(scene, seed=3, noise=noise).read(400)
    s = Sensor(scene, seed=3, noise=noise)
    parts = np.concatenate([s.read(1), s.read(130), s.read(269)])
    np.testing.assert_array_equal(one, parts)


@pytest.mark.parametrize("noise", [None, "spcs"])
def test_static_counts_match_gt_rate_within_one_spike(noise):
    # With subtractive reset the count over N steps is (p0 + N c - p_end) / theta with p0 and
    # p_end in [0, theta): it lies strictly within 1 spike of N * rate, whatever the seed.
    n = 4000
    sim = simulate("static", n, seed=11, height=H, width=W, noise=noise)
    counts = sim.spikes.sum(0, dtype=np.int64)
    expected = n * sim.gt_rate(0).astype(np.float64)
    assert np.abs(counts - expected).max() < 1.0 + 1e-3
    # and so the TFP rate over the run is the GT rate within 1 / n
    rate = cfsr.reconstruct(sim.spikes, "tfp", [n - 1], window=n)[0]
    np.testing.assert_allclose(rate, sim.gt_rate(0), atol=1.0 / n + 1e-5)


@pytest.mark.parametrize("name", ["disk", "car", "noisy", "blades"])
def test_moving_counts_match_integrated_gt_rate(name):
    # The same bound holds for a moving scene with the GT rate summed step by step: checks
    # that gt_rate(t) is exactly what the sensor integrated at every step.
    n = 240
    sim = simulate(name, n, seed=2, height=H, width=W, start=1000)
    # all n GT frames in one render call, checked against gt_rate(t) at a few steps
    y0, y1, x0, x1 = sim.scene.roi
    frames = np.repeat(sim.scene.background[None], n, axis=0)
    frames[:, y0:y1, x0:x1] = sim.scene.render_roi(1000, n)[0]
    rates = np.stack([sim.sensor.rate_from_intensity(f) for f in frames])
    for t in (0, 77, n - 1):
        np.testing.assert_array_equal(rates[t], sim.gt_rate(t))
    counts = sim.spikes.sum(0, dtype=np.int64)
    assert np.abs(counts - rates.sum(0, dtype=np.float64)).max() < 1.0 + 1e-3
    assert sim.motion_mask(0).any()


def test_shot_noise_keeps_mean_rate():
    n = 3000
    sim = simulate("static", n, seed=1, height=H, width=W, noise="shot")
    counts = sim.spikes.sum(0, dtype=np.int64)
    expected = n * sim.gt_rate(0).astype(np.float64)
    d = counts - expected
    # Poisson electrons: count variance ~ count / electrons_per_spike (~7.5 here)
    assert abs(d.mean()) < 0.3
    assert 1.5 < d.std() < 4.5


def test_rate_scale_and_lowlight():
    sim = simulate("disk", 10, height=H, width=W)
    assert sim.rate_scale == pytest.approx(0.5)
    low = simulate("lowlight", 10, height=H, width=W)
    assert low.rate_scale == pytest.approx(0.05)
    assert low.gt_image(5).max() > 0.5  # intensity stays normalised; rates drop
    assert low.gt_rate(5).max() <= 0.05 + 1e-6


def test_noise_parsing():
    assert Noise.parse(None).is_zero
    assert Noise.parse("spcs") == NOISE_PRESETS["spcs"]
    n = Noise.parse("spcs,dark_rate=0.01")
    assert n.dark_rate == 0.01 and n.gain_sd == NOISE_PRESETS["spcs"].gain_sd
    with pytest.raises(ValueError, match="unknown noise preset"):
        Noise.parse("loud")
    with pytest.raises(ValueError, match="gain_sd"):
        Noise.parse("gain_sd=-1")
    with pytest.raises(ValueError, match="unknown noise parameter"):
        Noise.parse({"colour": 1})


def test_dark_current_fires_in_the_dark():
    n = 4000
    sim = simulate("static", n, height=H, width=W, noise="dark_rate=0.01", gain=1e-9)
    assert sim.spikes.mean() == pytest.approx(0.01, abs=0.001)


def test_bad_arguments():
    with pytest.raises(ValueError, match="steps"):
        simulate("disk", 0, height=H, width=W)
    with pytest.raises(ValueError, match="gain"):
        simulate("disk", 5, height=H, width=W, gain=-1)
    with pytest.raises(ValueError, match="outside the simulation"):
        simulate("disk", 5, height=H, width=W).gt_rate(5)


def test_simulate_to_dat_round_trip(tmp_path):
    path = tmp_path / "car.dat"
    out = simulate_to_dat(
        "car", 300, path, seed=4, gt_every=100, height=H, width=W, chunk=128, noise="spcs"
    )
    assert out == path
    sim = simulate("car", 300, seed=4, height=H, width=W, noise="spcs")
    rec = cfsr.read_dat(path)
    assert rec.shape == (300, H, W)
    np.testing.assert_array_equal(rec[:], sim.spikes)
    assert rec.gain == pytest.approx(0.5)
    side = cfsr.read_sidecar(path)
    assert side["seed"] == 4 and side["scene"]["name"] == "car"
    assert side["simulator"]["noise"]["gain_sd"] > 0
    assert side["ground_truth"] == "car.gt.npz"
    gt = load_ground_truth(path)
    assert gt_path(path).exists()
    assert list(gt.steps) == [0, 100, 200]
    assert gt.images.shape == (3, H, W) and gt.masks.shape == (3, H, W)
    for i, t in enumerate(gt.steps):
        np.testing.assert_allclose(gt.images[i], sim.gt_image(int(t)))
        np.testing.assert_array_equal(gt.masks[i], sim.motion_mask(int(t)))
        np.testing.assert_allclose(gt.rate(int(t)), sim.gt_rate(int(t)), atol=1e-6)


def test_simulate_to_dat_odd_geometry(tmp_path):
    # 37 x 21 pixels is not a whole number of bytes: rows get zero head columns
    path = simulate_to_dat("disk", 50, tmp_path / "odd.dat", height=21, width=37, gt_every=0)
    rec = cfsr.read_dat(path)
    assert rec.shape == (50, 21, 37) and rec.layout.head_cols > 0
    np.testing.assert_array_equal(rec[:], simulate("disk", 50, height=21, width=37).spikes)
    assert not gt_path(path).exists()


def test_cli_simulate_writes_files(tmp_path, capsys):
    out = tmp_path / "sub" / "fan.dat"
    rc = main(
        [
            "simulate",
            "fan",
            "--steps",
            "250",
            "-o",
            str(out),
            "--height",
            str(H),
            "--width",
            str(W),
            "--gt-every",
            "50",
            "--seed",
            "3",
            "-q",
        ]
    )
    assert rc == 0
    assert out.exists() and out.with_name("fan.dat.json").exists()
    assert (tmp_path / "sub" / "fan.gt.npz").exists()
    rec = cfsr.read_dat(out)
    assert rec.shape == (250, H, W) and rec.gain == pytest.approx(0.5)
    assert "250 steps of fan" in capsys.readouterr().out
    np.testing.assert_array_equal(rec[:], simulate("fan", 250, seed=3, height=H, width=W).spikes)


def test_cli_simulate_unknown_scene(tmp_path, capsys):
    rc = main(["simulate", "rocket", "-o", str(tmp_path / "x.dat"), "-q"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "unknown scene 'rocket'" in err and "disk, fan, car, static, lowlight" in err
    assert not (tmp_path / "x.dat").exists()


def test_cli_simulate_bad_noise(tmp_path, capsys):
    rc = main(["simulate", "disk", "-o", str(tmp_path / "x.dat"), "--noise", "loud", "-q"])
    assert rc == 2
    assert "unknown noise preset" in capsys.readouterr().err
