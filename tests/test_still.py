"""Still pixels (cfsr.methods.cfsr.still_pixels): the proof that a pixel is background at t, and
how the
fine mask uses it."""

from __future__ import annotations

import numpy as np
import pytest

import cfsr  # noqa: F401  (registers the methods)
from cfsr.methods.cfsr.fine_mask import fine_mask
from cfsr.methods.cfsr.still_pixels import still_pixel


def _fire(rates: np.ndarray, phase: float) -> np.ndarray:
    """Spike steps of an integrate-and-fire pixel with per-step rates (spikes per step)."""
    acc = phase + np.cumsum(np.asarray(rates, np.float64))
    fired = np.floor(acc) > np.floor(np.concatenate([[phase], acc[:-1]]))
    return np.nonzero(fired)[0].astype(np.int64)


def _still(times: np.ndarray, c: int, min_run: int = 64, jump: float = 0.2):
    tm = np.zeros(max(1, times.size), np.int64)
    tm[: times.size] = times
    return still_pixel(tm, times.size, c, min_run, jump)


@pytest.mark.parametrize("rate", [0.011, 0.07, 0.25, 0.33, 0.41, 0.5, 0.93])
@pytest.mark.parametrize("phase", [0.0, 0.37, 0.99])
def test_a_constant_pixel_is_still_at_its_rate(rate, phase):
    times = _fire(np.full(761, rate), phase)
    ok, r = _still(times, 380)
    assert ok
    assert abs(r - rate) <= 2.0 / (times[-1] - times[0])


def _fan_pixel(n: int, background: float, period: int, covered: int, seed: int) -> np.ndarray:
    """A pixel over which a textured blade passes every ``period`` steps for ``covered``
    steps (texture: a smooth wave of +-20 %, a new one each pass)."""
    rng = np.random.default_rng(seed)
    rates = np.full(n, background)
    u = np.arange(covered)
    for start in range(10, n, period):
        mean, cycles, phase = rng.uniform(0.25, 0.4), rng.uniform(1, 3), rng.uniform(0, 6.3)
        m = min(covered, n - start)
        wave = mean * (1 + 0.2 * np.sin(2 * np.pi * cycles * u / covered + phase))
        rates[start : start + m] = wave[:m]
    return rates


@pytest.mark.parametrize("seed", range(6))
def test_background_between_passes_is_still_and_the_blade_is_not(seed):
    rates = _fan_pixel(761, 0.12, 231, 92, seed)
    times = _fire(rates, 0.5)
    covered = np.zeros(761, bool)
    for start in range(10, 761, 231):
        covered[start : start + 92] = True
    # the middle of a gap, far from both edges: still, at the background's rate
    for c in (10 + 231 + 92 + 60, 10 + 2 * 231 + 92 + 40):
        ok, r = _still(times, c)
        assert not covered[c] and ok, c
        assert abs(r - 0.12) < 0.01
    # under the blade: never still
    for c in np.nonzero(covered)[0][5::7]:
        if 200 <= c <= 560:
            assert not _still(times, int(c))[0], c


def test_a_slow_ramp_is_not_still():
    # light that changes by 10 % over the range: no exact rate for long, no return
    times = _fire(np.linspace(0.30, 0.33, 761), 0.2)
    assert not _still(times, 380)[0]


def test_a_change_at_t_is_not_still():
    rates = np.full(761, 0.2)
    rates[381:] = 0.45
    times = _fire(rates, 0.0)
    assert not _still(times, 381)[0]
    assert not _still(times, 380)[0]


def test_too_few_spikes_prove_nothing():
    assert not _still(np.array([100, 500], np.int64), 300)[0]
    assert not _still(np.array([], np.int64), 300)[0]


def test_fine_mask_leaves_still_pixels_out_and_does_not_grow_into_them():
    h, w = 60, 80
    blade = np.zeros((h, w), bool)
    blade[20:40, 10:30] = True
    smear = np.zeros((h, w), bool)  # a coarse mask smeared 8 px to the right
    smear[20:40, 10:38] = True
    still = np.zeros((h, w), bool)
    still[:, 30:] = True  # proven background right of the blade
    still[28:31, 18:21] = True  # a false proof inside the blade
    none = np.zeros((h, w), bool)
    old = fine_mask(smear, none, none, close_size=9, min_area=16, dilate=2)
    new = fine_mask(smear, none, none, close_size=9, min_area=16, dilate=2, still=still)
    assert old[20:40, 30:40].all()  # the smear and the margin
    assert not new[:, 30:].any()  # nothing right of the blade: neither smear nor margin
    assert new[28:31, 18:21].all()  # the enclosed false proof is filled back
    assert new[18:42, 10:30].all() and new[20:40, 8:30].all()  # the margin, where not still
    # no still pixel: the mask of the union, as before
    assert np.array_equal(
        fine_mask(smear, none, none, close_size=9, min_area=16, dilate=2, still=none), old
    )


def test_still_pixels_on_a_window_match_the_pixel_rule():
    from cfsr._words import PackedWindow
    from cfsr.methods.cfsr.still_pixels import still_pixels

    rng = np.random.default_rng(3)
    n, h, w = 761, 6, 70
    frames = np.zeros((n, h, w), np.uint8)
    want = np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            if (x + y) % 3 == 0:
                rates = _fan_pixel(n, rng.uniform(0.05, 0.3), 231, 92, int(rng.integers(99)))
            elif x % 2:  # moving texture: a new rate every 3-20 steps (rejected near t)
                lengths = rng.integers(3, 21, n)
                rates = np.repeat(rng.uniform(0.05, 0.6, n), lengths)[:n]
            else:
                rates = np.full(n, rng.uniform(0.02, 0.6))
            times = _fire(rates, rng.uniform())
            frames[times, y, x] = 1
            want[y, x] = _still(times, 380)[0]
    cand = rng.uniform(size=(h, w)) < 0.8
    still, rate = still_pixels(
        PackedWindow.from_frames(frames), 380, cand, reach=380, min_run=64, jump=0.2
    )
    assert np.array_equal(still, want & cand)
    assert (rate[still] > 0).all() and (rate[~still] == 0).all()


def test_the_paper_presets_have_no_still_pixels():
    from cfsr.methods.cfsr.params import FINE_PARAMS, FINE_PRESETS
    from cfsr.methods.registry import get_method, resolve_params

    assert FINE_PRESETS["paper"]["still_reach"] == 0
    assert FINE_PRESETS["simulated"]["still_reach"] == 0
    assert FINE_PARAMS["still_reach"].default > 0
    p = resolve_params(get_method("cfsr"), {"mog_sides": "past"}, None)
    before, after = get_method("cfsr").window(p)
    assert before >= p["still_reach"] and after >= p["still_reach"]
    q = resolve_params(get_method("cfsr"), {"mog_sides": "past", "still_reach": 0}, None)
    assert get_method("cfsr").window(q)[1] < after
