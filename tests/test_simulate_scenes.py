"""The scenes users meet: ``dim``, ``noisy`` (sensor noise, hot pixels), ``blades``; and the
scenes whose motion is small, slow or everywhere: a vibrating mount (with and without a fast
mover in front), a drift, a slow pan (a :class:`~cfsr.simulate.Mount` layer: the still scene
seen shifted by ``offsets(t)``; its motion mask is where a one-pixel shift changes the
intensity by at least ``edge``)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cfsr.cli import main
from cfsr.simulate import (
    NOISE_PRESETS,
    SCENES,
    Mount,
    Noise,
    Scene,
    Sensor,
    make_scene,
    simulate,
)
from cfsr.simulate.scenes import drift, vibration

H, W = 48, 64
NEW = ("dim", "noisy", "blades")


@pytest.mark.parametrize("name", NEW)
def test_new_scenes_render_with_motion(name):
    sim = simulate(name, 64, seed=0, height=H, width=W)
    assert sim.spikes.shape == (64, H, W) and sim.spikes.any()
    for t in (0, 63):
        img, mask = sim.gt_image(t), sim.motion_mask(t)
        assert img.dtype == np.float32 and 0.0 <= img.min() and img.max() <= 1.0
        assert mask.any() and not mask.all()
    assert sim.scene.moving
    json.dumps(sim.describe())


@pytest.mark.parametrize("size", [(H, W), (250, 400)])
def test_dim_true_rates_are_5e_3_to_5e_2(size):
    s = make_scene("dim", height=size[0], width=size[1])
    sensor = Sensor(s, seed=0)
    assert sensor.rate_scale == pytest.approx(0.05) and sensor.noise.is_zero
    for t in (0, 300, 1000):
        r = sensor.rate_from_intensity(s.intensity(t))
        assert r.min() >= 0.005 - 1e-6 and r.max() <= 0.05 + 1e-6
        assert r.max() > 0.04 and r.min() < 0.007  # the range is used, not a sliver of it
    # the disk moves as in the ``disk`` scene: same geometry, same mask
    np.testing.assert_array_equal(
        s.motion_mask(500), make_scene("disk", height=size[0], width=size[1]).motion_mask(500)
    )


def test_dim_spike_counts_match_the_stated_rates():
    n = 2000
    sim = simulate("dim", n, seed=1, height=H, width=W)
    mean_rate = sim.spikes.mean(0)
    assert 0.005 - 1e-3 < mean_rate.min() and mean_rate.max() < 0.05 + 1e-3


def test_noisy_scene_uses_the_sensor_preset_unless_told_otherwise():
    s = make_scene("noisy", height=H, width=W)
    assert s.noise == "sensor" and s.describe()["noise"] == "sensor"
    assert Sensor(s).noise == NOISE_PRESETS["sensor"]
    assert Sensor(s, noise="none").noise.is_zero
    assert Sensor(s, noise="shot").noise == NOISE_PRESETS["shot"]  # explicit noise replaces it
    assert Sensor(make_scene("disk", height=H, width=W)).noise.is_zero
    # with the noise off it is the disk scene, spike for spike
    a = simulate("noisy", 150, seed=4, height=H, width=W, noise="none").spikes
    b = simulate("disk", 150, seed=4, height=H, width=W).spikes
    np.testing.assert_array_equal(a, b)
    c = simulate("noisy", 150, seed=4, height=H, width=W).spikes
    assert (a != c).any()


def test_noisy_is_deterministic_for_a_seed():
    a = simulate("noisy", 200, seed=7, height=H, width=W)
    b = simulate("noisy", 200, seed=7, height=H, width=W)
    c = simulate("noisy", 200, seed=8, height=H, width=W)
    np.testing.assert_array_equal(a.spikes, b.spikes)
    np.testing.assert_array_equal(a.sensor.hot_mask, b.sensor.hot_mask)
    np.testing.assert_array_equal(a.sensor.dark_map, b.sensor.dark_map)
    assert (a.spikes != c.spikes).mean() > 0.05
    assert not np.array_equal(a.sensor.threshold_map, c.sensor.threshold_map)


def _flat(value: float, h: int = 40, w: int = 50) -> Scene:
    return Scene("flat", np.full((h, w), value, np.float32))


def test_hot_pixels_fire_far_above_their_intensity():
    n = 2000
    sim = simulate(_flat(0.1), n, seed=3, noise="hot_fraction=0.01,hot_rate=0.6")
    hot = sim.sensor.hot_mask
    assert hot.sum() == 20  # 1 % of 2000 pixels
    rate = sim.spikes.mean(0)
    ideal = sim.ideal_rate(0)  # 0.05 spikes/step everywhere
    assert rate[hot].min() > 0.3 + ideal.max()  # 0.6 x U(0.5, 1) on top of the light
    assert np.abs(rate[~hot] - ideal[~hot]).max() < 2.0 / n
    np.testing.assert_allclose(rate, sim.gt_rate(0), atol=1.0 / n + 1e-5)  # gt_rate knows them
    # the ``sensor`` preset: 0.1 % hot pixels at 0.25-0.5 spikes/step
    s = Sensor(_flat(0.0, 100, 100), seed=0, noise="sensor")
    assert s.hot_mask.sum() == 10
    dark = s.rate_from_intensity(np.zeros((100, 100)))
    assert dark[s.hot_mask].min() >= 0.25 - 0.02 and dark[~s.hot_mask].max() < 0.05


def test_dark_current_adds_spikes_where_intensity_is_zero():
    n = 4000
    assert not simulate(_flat(0.0), n, seed=0).spikes.any()  # an ideal sensor: nothing
    sim = simulate(_flat(0.0), n, seed=0, noise="dark_rate=0.01,dark_sd=0.5")
    rate = sim.spikes.mean(0)
    assert rate.mean() == pytest.approx(0.01, abs=0.001)
    assert rate.std() > 0.002  # per-pixel dark current spread (50 %)
    assert not sim.ideal_rate(0).any()  # the evaluation's ground truth stays black


def test_threshold_mismatch_spreads_rates():
    n = 4000
    ideal = simulate(_flat(0.5), n, seed=2).spikes.mean(0)
    spread = simulate(_flat(0.5), n, seed=2, noise="threshold_sd=0.05").spikes.mean(0)
    assert ideal.std() < 0.5 / n  # 0.25 spikes/step in every pixel
    assert spread.mean() == pytest.approx(0.25, rel=0.02)
    assert 0.25 * 0.035 < spread.std() < 0.25 * 0.07  # ~ rate x threshold_sd


def test_hot_pixel_parameters_are_checked():
    assert Noise.parse("sensor") == NOISE_PRESETS["sensor"]
    assert Noise.parse("hot_fraction=0.01,hot_rate=0.5").hot_fraction == 0.01
    with pytest.raises(ValueError, match="hot_rate"):
        Noise.parse("hot_fraction=0.01")
    with pytest.raises(ValueError, match="hot_fraction"):
        Noise.parse("hot_fraction=2,hot_rate=0.5")
    with pytest.raises(ValueError, match="hot_rate"):
        Noise.parse("hot_fraction=0.1,hot_rate=1.5")
    # no hot pixels, no change to the other maps (hot pixels are drawn last)
    s0 = Sensor(_flat(0.3), seed=5, noise="spcs")
    s1 = Sensor(_flat(0.3), seed=5, noise="spcs,hot_fraction=0.01,hot_rate=0.5")
    np.testing.assert_array_equal(s0.threshold_map, s1.threshold_map)
    np.testing.assert_array_equal(s0.gain_map, s1.gain_map)
    np.testing.assert_array_equal(s0.dark_map[~s1.hot_mask], s1.dark_map[~s1.hot_mask])


def test_blades_are_thin_and_fast():
    fan = make_scene("fan")
    thin = make_scene("blades")
    wide = make_scene("blades", blade_width=6.0)
    rotor = thin.layers[0]
    assert rotor.rpm == 2600 and rotor.blades == 4 and rotor.blade_width == 3.0
    assert thin.describe()["layers"][0]["blade_width_px"] == 3.0
    assert rotor.omega * rotor.radius > 0.5  # tips move > 0.5 px per step
    hub = np.hypot(*np.mgrid[:250, :400] - np.array([124.5, 199.5])[:, None, None])
    outside_hub = hub > rotor.hub + 2
    scenes = {"f": fan, "t": thin, "w": wide}
    area = {k: (s.motion_mask(0) & outside_hub).sum() for k, s in scenes.items()}
    # constant-width bars: 4 blades x ~(radius - hub) px long x width
    expect = 4 * (rotor.radius - rotor.hub - 2) * 3.0
    assert 0.8 * expect < area["t"] < 1.5 * expect
    assert 1.7 < area["w"] / area["t"] < 2.3
    assert area["t"] < 0.2 * area["f"]
    # every radius is covered by a bar of the same width: ~3-4 px where a circle crosses a blade
    ring = (np.abs(hub - 80) < 0.5) & thin.motion_mask(0)
    assert 4 * 3 <= ring.sum() <= 4 * 6
    with pytest.raises(ValueError, match="blade_width"):
        make_scene("blades", blade_width=0)


def test_blades_move_only_inside_the_mask():
    s = make_scene("blades", height=H, width=W)
    a, ma = s.intensity_and_mask(500)
    b, mb = s.intensity_and_mask(503)
    changed = np.abs(a - b) > 1e-6
    assert changed.any() and not (changed & ~(ma | mb)).any()


def test_evaluate_scores_the_new_scenes_against_the_clean_scene():
    from cfsr.evaluation import evaluate

    rows = evaluate(["tfi"], ["dim", "noisy", "blades"], steps=300, times=[200], height=H, width=W)
    assert [r["scene"] for r in rows] == ["dim", "noisy", "blades"]
    for r in rows:
        assert r["psnr_all"] is not None and r["psnr_motion"] is not None
        assert r["motion_fraction"] > 0
    assert rows[0]["rate_scale"] == pytest.approx(0.05)
    # the ground truth of the noisy scene is the ideal rate, not the sensor's fixed pattern
    sim = simulate("noisy", 10, seed=0, height=H, width=W)
    assert sim.sensor.hot_mask.any()
    assert not np.array_equal(sim.ideal_rate(5), sim.gt_rate(5))
    clean = simulate("disk", 10, seed=0, height=H, width=W)
    np.testing.assert_array_equal(clean.ideal_rate(5), clean.gt_rate(5))
    np.testing.assert_array_equal(sim.ideal_rate(5), clean.ideal_rate(5))


def test_cli_simulate_noisy_defaults_to_its_noise(tmp_path, capsys):
    out = tmp_path / "n.dat"
    assert (
        main(
            [
                "simulate",
                "noisy",
                "-o",
                str(out),
                "-n",
                "64",
                "--height",
                "32",
                "--width",
                "40",
                "-q",
            ]
        )
        == 0
    )
    side = json.loads((tmp_path / "n.dat.json").read_text())
    assert side["simulator"]["noise"] == NOISE_PRESETS["sensor"].to_dict()
    assert side["scene"]["noise"] == "sensor"
    out2 = tmp_path / "m.dat"
    assert (
        main(
            [
                "simulate",
                "noisy",
                "-o",
                str(out2),
                "-n",
                "64",
                "--height",
                "32",
                "--width",
                "40",
                "--noise",
                "none",
                "-q",
            ]
        )
        == 0
    )
    side2 = json.loads((tmp_path / "m.dat.json").read_text())
    assert not any(side2["simulator"]["noise"].values())


# --------------------------------------------------------------------------- moving mounts

MOUNT_SCENES = ("vibrate", "vibrate_mover", "drift", "pan")


@pytest.mark.parametrize("name", MOUNT_SCENES)
def test_mount_scenes_are_listed_and_move(name):
    assert name in SCENES
    s = make_scene(name, height=H, width=W)
    assert s.moving and isinstance(s.layers[0], Mount)
    img, mask = s.intensity_and_mask(700)
    assert img.shape == (H, W) and 0.0 <= img.min() and img.max() <= 1.0
    # textured, not everywhere: the visible motion lies on the edges of the still scene
    assert 0.05 < mask.mean() < 0.95, mask.mean()


@pytest.mark.parametrize(("amplitude", "hz"), [(0.5, 20.0), (1.0, 50.0), (3.0, 200.0)])
def test_vibration_path(amplitude, hz):
    s = make_scene("vibrate", height=H, width=W, amplitude=amplitude, hz=hz)
    mount = s.layers[0]
    period = 40_000 / hz  # steps
    t = np.arange(0, int(4 * period))
    dy, dx = mount.offsets(0, t.size)
    assert np.abs(dx).max() == pytest.approx(amplitude, rel=1e-3)
    assert np.abs(dy).max() == pytest.approx(amplitude / 2, rel=1e-3)
    # periodic at hz, and its peak speed is A w px/step
    k = int(round(period))
    if abs(k - period) < 1e-9:
        np.testing.assert_allclose(dx[k:], dx[:-k], atol=1e-9)
    w = 2 * math.pi * hz / 40_000
    assert np.abs(np.diff(dx)).max() == pytest.approx(amplitude * w, rel=0.01)
    assert s.describe()["layers"][0]["peak_px_per_step"] == pytest.approx(amplitude * w)


def test_a_whole_pixel_shift_moves_the_picture_by_one_pixel():
    plane = make_scene("static", height=H, width=W).background
    m = Mount(plane, drift(1.0, 0.0))  # one pixel right per step
    out = np.empty((3, H, W), np.float32)
    m.render(0, 3, out, np.zeros((0, 0, 0), np.float32), 0, 0)
    np.testing.assert_allclose(out[0], plane, atol=1e-6)
    # pixel x at step 2 shows plane point x + 2
    np.testing.assert_allclose(out[2][:, :-2], plane[:, 2:], atol=1e-6)


@pytest.mark.parametrize("speed", [0.001, 0.005, 0.02])
def test_drift_speed(speed):
    s = make_scene("drift", height=H, width=W, speed=speed, angle=30.0)
    dy, dx = s.layers[0].offsets(1000, 2)
    assert math.hypot(dy[1] - dy[0], dx[1] - dx[0]) == pytest.approx(speed)
    assert dy[0] == pytest.approx(1000 * speed * 0.5)


@pytest.mark.parametrize("name", MOUNT_SCENES)
def test_changes_outside_the_mask_are_below_the_edge(name):
    # a shift of less than a pixel moves a pixel outside the visible-motion mask by less than
    # the edge step (bilinear: at most the largest neighbour difference)
    s = make_scene(name, height=H, width=W)
    a, ma = s.intensity_and_mask(500)
    b, mb = s.intensity_and_mask(530)
    shift = np.hypot(
        *(
            np.subtract(
                *[
                    np.asarray(o)[:, 0]
                    for o in (s.layers[0].offsets(530, 1), s.layers[0].offsets(500, 1))
                ]
            )
        )
    )
    assert shift < 1.0
    out = ~(ma | mb)
    assert np.abs(a - b)[out].max() < s.layers[0].edge
    assert (np.abs(a - b)[ma | mb] > 1e-6).any()


def test_vibrating_mover_in_front():
    s = make_scene("vibrate_mover", height=H, width=W)
    assert [ly.describe()["kind"] for ly in s.layers] == ["mount", "disk"]
    mask_fast = make_scene("vibrate_mover", height=H, width=W).motion_mask(300)
    mask_still = make_scene("vibrate", height=H, width=W).motion_mask(300)
    assert (mask_fast & ~mask_still).sum() > 20  # the disk's pixels


@pytest.mark.parametrize(
    ("opts", "match"),
    [({"amplitude": 0.0}, "amplitude"), ({"hz": -1.0}, "hz"), ({"speed": 2.0}, "speed")],
)
def test_bad_options(opts, match):
    name = "drift" if "speed" in opts else "vibrate"
    with pytest.raises(ValueError, match=match):
        make_scene(name, height=H, width=W, **opts)


def test_counts_follow_the_moving_ground_truth():
    # the sensor integrates exactly the rendered frames: counts over the run match the summed
    # ground-truth rates within one spike at every pixel (the simulator's own invariant)
    n = 300
    sim = simulate("vibrate", n, seed=4, height=H, width=W, start=200)
    frames = sim.scene.render_roi(200, n)[0]
    rates = np.stack([sim.sensor.rate_from_intensity(f) for f in frames])
    counts = sim.spikes.sum(0, dtype=np.int64)
    assert np.abs(counts - rates.sum(0, dtype=np.float64)).max() < 1.0 + 1e-3


def test_vibration_helper_is_elliptic():
    dy, dx = vibration(2.0, 100.0)(np.arange(400, dtype=np.float64))
    assert np.abs(dx).max() == pytest.approx(2.0, rel=1e-3)
    assert np.abs(dy).max() == pytest.approx(1.0, rel=1e-3)


def test_cli_scene_options(tmp_path, capsys):
    out = tmp_path / "shake.dat"
    assert (
        main(
            [
                "simulate",
                "vibrate",
                "--steps",
                "50",
                "--height",
                str(H),
                "--width",
                str(W),
                "--option",
                "amplitude=3",
                "--option",
                "hz=200",
                "-o",
                str(out),
                "-q",
            ]
        )
        == 0
    )
    scene = json.loads(out.with_name(out.name + ".json").read_text())["scene"]
    assert scene["layers"][0]["amplitude_px"] == 3.0 and scene["layers"][0]["hz"] == 200.0
    assert main(["simulate", "vibrate", "--option", "amplitude", "-o", str(out), "-q"]) != 0
    assert "use KEY=VALUE" in capsys.readouterr().err
