"""Windows as long as the motion allows (cfsr.methods.cfsr.slow_motion_windows) and CFSR's use
of them."""

from __future__ import annotations

import numpy as np
import pytest

import cfsr
from cfsr._words import PackedWindow
from cfsr.methods.cfsr.slow_motion_windows import (
    HALVES,
    SLOW_PARAMS,
    SlowSettings,
    slow_class,
    slow_fuse,
    slow_rates,
)
from cfsr.simulate import make_scene, simulate

H, W = 48, 64


def _if_pixel(rates: np.ndarray, phase: float = 0.3) -> np.ndarray:
    """Spikes of an ideal integrate-and-fire pixel driven by ``rates`` (spikes/step)."""
    pot = phase
    out = np.zeros(rates.size, np.uint8)
    for t, r in enumerate(rates):
        pot += r
        if pot >= 1.0:
            pot -= 1.0
            out[t] = 1
    return out


def _window(columns: list[np.ndarray]) -> PackedWindow:
    return PackedWindow.from_frames(np.stack(columns, axis=1)[:, None, :].copy())


@pytest.mark.parametrize("rate", [0.02, 0.13, 0.25, 0.37, 0.5, 0.93])
def test_a_still_pixel_reaches_the_longest_window_with_its_rate(rate):
    n = 801
    src = _window([_if_pixel(np.full(n, rate), phase) for phase in (0.0, 0.4, 0.9)])
    r, half, count = slow_rates(src, 400, np.ones((1, 3), bool), reach=192)
    assert (half == 192).all()
    # first-to-last rule over 385 steps: within one step of the whole intervals' span
    np.testing.assert_allclose(r, rate, rtol=1.0 / (385 * rate - 2))
    assert (np.abs(count - 385 * rate) < 1.0 + 1e-9).all()


def test_a_change_shortens_the_window_on_either_side():
    n = 801
    step_before = np.where(np.arange(n) < 380, 0.2, 0.3)  # a change 20 steps before t
    step_after = np.where(np.arange(n) < 430, 0.2, 0.3)  # 30 steps after t
    symmetric = np.where(np.arange(n) < 400, 0.25, 0.5)  # at t: the centred mean hides it
    src = _window([_if_pixel(x) for x in (step_before, step_after, symmetric)])
    r, half, _ = slow_rates(src, 400, np.ones((1, 3), bool), reach=192)
    assert 12 <= half[0, 0] <= 24 and 16 <= half[0, 1] <= 32, half
    assert half[0, 2] < 8
    np.testing.assert_allclose(r[0, :2], [0.3, 0.2], rtol=0.1)  # the rate on t's side


def test_a_rung_between_doublings_keeps_the_window_a_change_leaves():
    # constant within 60 steps of t, then a change: the doubling ladder stops at 32 steps, the
    # one with rungs at 1.5x at 48, and its rate is the constant one's over more spikes
    n = 801
    rates = np.where(np.abs(np.arange(n) - 400) <= 60, 0.25, 0.45)
    src = _window([_if_pixel(rates, phase) for phase in (0.1, 0.6)])
    cand = np.ones((1, 2), bool)
    r1, half1, _ = slow_rates(src, 400, cand, reach=128)
    r2, half2, count2 = slow_rates(src, 400, cand, reach=128, rungs=2)
    assert (half1 == 32).all() and (half2 == 48).all(), (half1, half2)
    np.testing.assert_allclose(r2, 0.25, rtol=1.0 / (97 * 0.25 - 2))
    assert (count2 > 97 * 0.25 - 1).all()


def test_slow_drift_gets_a_longer_window_than_fast():
    n = 801
    t = np.arange(n)
    slow = 0.3 + 0.05 * np.sin(2 * np.pi * t / 4000)  # a slow change: a long window
    fast = 0.3 + 0.05 * np.sin(2 * np.pi * t / 80)
    src = _window([_if_pixel(slow), _if_pixel(fast)])
    _, half, _ = slow_rates(src, 400, np.ones((1, 2), bool), reach=192)
    assert half[0, 0] >= 48 and half[0, 1] <= 24 and half[0, 0] > 2 * half[0, 1]


def test_halves_stay_inside_the_window():
    src = _window([_if_pixel(np.full(300, 0.25))])
    _, half, _ = slow_rates(src, 100, np.ones((1, 1), bool), reach=192)
    assert half[0, 0] == 100  # clipped to the window's start
    with pytest.raises(ValueError, match="outside the window"):
        slow_rates(src, 100, np.ones((1, 1), bool), reach=192, halves=[8, 150])
    assert HALVES == tuple(sorted(HALVES))


def test_only_candidates_are_estimated():
    sim = simulate("static", 400, seed=1, height=H, width=W)
    src = PackedWindow.from_frames(sim.spikes)
    cand = np.zeros((H, W), bool)
    cand[10:20, 5:30] = True
    r, half, _ = slow_rates(src, 200, cand, reach=128)
    assert (half[~cand] == 0).all() and (r[~cand] == 0).all()
    assert (half[cand] == 128).all()
    # the still scene's rates from their longest windows: within a 257-step window's error
    gt = sim.gt_rate(200)
    assert np.abs(r[cand] - gt[cand]).max() < 1.0 / 200


#: the stage's window rules as the fusion tests set them (reach, slack, the two thresholds
#: outside and inside the fine mask, the fine weight; no noise), the others at their defaults
_WINDOW_RULES = {
    **{k: prm.default for k, prm in SLOW_PARAMS.items()},
    "slow_reach": 128,
    "slow_rungs": 1,  # the doubling ladder, as slow_rates by default
    "slow_slack": 1.0,
    "slow_min": 8,
    "slow_intervals": 4,
    "slow_fine_min": 32,
    "slow_fine_intervals": 12,
    "slow_fine_weight": 0.5,
    "slow_fine_full": 0,
    "slow_noise": 0.0,
}


def test_fuse_rules():
    sim = simulate("vibrate", 600, seed=0, height=H, width=W)
    src = PackedWindow.from_frames(sim.spikes)
    rate = np.full((H, W), 0.123, np.float32)
    p = {**_WINDOW_RULES, "slow_region_weight": 0.0,  # the slow class: test_slow_class
         "slow_region_noise": 0.0}
    assert slow_fuse(src, 300, rate, None, SlowSettings.of({**p, "slow_reach": 0})) is rate
    # temporal noise breaks the exact bounds: the stage stands aside
    assert slow_fuse(src, 300, rate, None, SlowSettings.of(p), noise=0.2) is rate
    slow, half, count = slow_rates(src, 300, np.ones((H, W), bool), reach=128)
    out = slow_fuse(src, 300, rate, None, SlowSettings.of(p))
    took = (half >= 8) & (count - 1 >= 4)
    assert took.any() and (~took).any()
    np.testing.assert_array_equal(out[took], slow[took])
    np.testing.assert_array_equal(out[~took], rate[~took])
    fine = np.zeros((H, W), bool)
    fine[:, : W // 2] = True
    out = slow_fuse(src, 300, rate, fine, SlowSettings.of(p))
    inner = fine & (half >= 32) & (count - 1 >= 12)
    np.testing.assert_allclose(out[inner], 0.5 * (slow[inner] + 0.123), rtol=1e-6)
    np.testing.assert_array_equal(out[fine & ~inner], rate[fine & ~inner])
    np.testing.assert_array_equal(out[~fine & took], slow[~fine & took])
    # from slow_fine_full on, the window's rate replaces PatchMatch's
    out = slow_fuse(src, 300, rate, fine, SlowSettings.of({**p, "slow_fine_full": 64}))
    full = inner & (half >= 64)
    assert full.any()
    np.testing.assert_array_equal(out[full], slow[full])


def test_slow_class():
    sim = simulate("vibrate", 600, seed=0, height=H, width=W)
    src = PackedWindow.from_frames(sim.spikes)
    p = {**_WINDOW_RULES, "slow_region": 9, "slow_region_half": 16, "slow_region_share": 0.9,
         "slow_region_intervals": 6, "slow_region_weight": 0.5, "slow_rough": 1.3,
         "slow_region_noise": 0.0}
    everywhere = np.ones((H, W), bool)
    slow, half, count = slow_rates(src, 300, everywhere, reach=128)
    fine = np.zeros((H, W), bool)
    fine[:, : W // 2] = True
    cls = slow_class(half, count - 1, fine, everywhere, SlowSettings.of(p))
    # the class: long windows in a square of nearly all long windows, inside the fine region
    assert cls.any() and not cls[~fine].any()
    assert (half[cls] >= 16).all() and (count[cls] - 1 >= 6).all()
    no_region = SlowSettings.of({**p, "slow_region": 0})
    assert not slow_class(half, count - 1, fine, everywhere, no_region).any()
    # a lone long window among short ones is not slow: every other pixel's window cut short
    short = np.where(np.arange(W)[None, :] % 2 == 0, half, 2)
    assert not slow_class(short, count - 1, fine, everywhere, SlowSettings.of(p)).any()
    # PatchMatch's rate as rough as the windows': the class moves halfway to the window's rate
    rate = (slow + np.float32(0.01)).astype(np.float32)
    inner = fine & (half >= 32) & (count - 1 >= 12)
    base = np.where(inner, np.float32(0.5), np.float32(0.0))
    wgt = np.where(cls, base + (1 - base) * 0.5, base)
    out = slow_fuse(src, 300, rate, fine, SlowSettings.of(p))
    np.testing.assert_allclose(out[fine], (wgt * slow + (1 - wgt) * rate)[fine], atol=1e-6)
    off = slow_fuse(src, 300, rate, fine, SlowSettings.of({**p, "slow_region_weight": 0.0}))
    assert np.abs(out - off)[cls & ~inner].max() > 0.004
    np.testing.assert_array_equal(out[~cls], off[~cls])
    # temporal noise above slow_noise: only the slow class is left, up to slow_region_noise
    region_noise = SlowSettings.of({**p, "slow_region_noise": 0.5})
    noisy = slow_fuse(src, 300, rate, fine, region_noise, noise=0.2)
    np.testing.assert_allclose(noisy[cls], (0.5 * slow + 0.5 * rate)[cls], atol=1e-6)
    np.testing.assert_array_equal(noisy[~cls], rate[~cls])
    low_noise = SlowSettings.of({**p, "slow_region_noise": 0.1})
    assert slow_fuse(src, 300, rate, fine, low_noise, noise=0.2) is rate
    assert slow_fuse(src, 300, rate, None, region_noise, noise=0.2) is rate
    # a smooth PatchMatch rate (the windows keep a fixed-pattern spread): the class is off
    flat = np.full((H, W), 0.123, np.float32)
    np.testing.assert_array_equal(
        slow_fuse(src, 300, flat, fine, SlowSettings.of(p)),
        slow_fuse(src, 300, flat, fine, SlowSettings.of({**p, "slow_region_weight": 0.0})),
    )


def _psnr(sim, rate, t, mask=None):
    from cfsr.display import to_display
    from cfsr.metrics import psnr

    gt = to_display(sim.ideal_rate(t), gain=sim.rate_scale)
    return psnr(gt, to_display(rate, gain=sim.rate_scale), mask=mask)


def test_cfsr_under_shot_noise_is_left_alone():
    sim = simulate("disk", 900, seed=0, height=96, width=128, noise="shot")
    off = cfsr.reconstruct(sim.spikes, "cfsr", [450], slow_reach=0)[0]
    # the windows outside the slow class stand aside
    gated = cfsr.reconstruct(sim.spikes, "cfsr", [450], slow_region_noise=0.0)[0]
    np.testing.assert_array_equal(gated, off)
    # the slow class (up to slow_region_noise) changes fine-region pixels only
    on, masks = cfsr.reconstruct(sim.spikes, "cfsr", [450], return_masks=True)
    out = ~masks["fine"][0]
    np.testing.assert_array_equal(on[0][out], off[out])


def _with_and_without(sim, t: int = 450, **off: float):
    """PSNR (whole frame, motion region) of CFSR at ``t`` as it is and with ``off`` set."""
    m = sim.motion_mask(t)
    out = []
    for params in ({}, off):
        rate = cfsr.reconstruct(sim.spikes, "cfsr", [t], **params)[0]
        out.append((_psnr(sim, rate, t), _psnr(sim, rate, t, m)))
    return out


@pytest.mark.parametrize("scene", ["vibrate", "drift"])
def test_cfsr_with_slow_windows_beats_without_on_slow_motion(scene):
    on, off = _with_and_without(simulate(scene, 900, seed=0, height=96, width=128),
                                slow_reach=0)
    assert on[0] > off[0] + 1.0 and on[1] > off[1] + 1.0


@pytest.mark.parametrize(
    "scene, opts", [("drift", {"speed": 0.02}), ("vibrate", {"amplitude": 0.5, "hz": 200})]
)
def test_slow_class_pays_where_the_fine_region_moves_slowly(scene, opts):
    # the fine region under sub-pixel motion: PatchMatch's average blurs it (+2.5 and +1.2 dB
    # measured in the motion region at this size)
    on, off = _with_and_without(
        simulate(make_scene(scene, height=96, width=128, **opts), 900, seed=0),
        slow_region_weight=0.0)
    assert on[0] > off[0] + 0.5 and on[1] > off[1] + 0.5


def test_paper_presets_run_without_the_stage():
    from cfsr.methods.cfsr.params import FINE_PRESETS

    assert all(pr["slow_reach"] == 0 for pr in FINE_PRESETS.values())
    scene = make_scene("vibrate", height=H, width=W)
    assert scene.moving
