"""The steady-interval distinction and static check (cfsr.methods.cfsr.steady_distinction, issue
13)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage as ndi

import cfsr
from cfsr._words import PackedWindow
from cfsr.methods.cfsr.fine_mask import _fill_holes, regularise
from cfsr.methods.cfsr.steady_distinction import (
    check_static,
    clipped_median,
    noise_level,
    steadiness,
    steady_mask,
)
from cfsr.methods.tfi import isi_at
from cfsr.methods.tfp import static_rate, tfp_span


def if_train(rates, phase, n):
    """Integrate-and-fire spikes ``(n, len(rates))`` of per-step rates ``rates[t, p]``."""
    level = np.cumsum(np.asarray(rates, np.float64), axis=0) + phase
    prev = np.vstack([np.full((1, level.shape[1]), 0.0) + phase, level[:-1]])
    return (np.floor(level) > np.floor(prev)).astype(np.uint8)


def brute_spread(times, c, radius, a, b):
    """(max - min - 1) / mean over the distinct whole intervals (both spikes in [a, b))
    containing a step of c +- radius; 0 with fewer than two."""
    ts = [s for s in times if a <= s < b]
    seen = set()
    for t in range(max(a, c - radius), min(b - 1, c + radius) + 1):
        prev = max((s for s in ts if s <= t), default=None)
        nxt = min((s for s in ts if s > t), default=None)
        if prev is not None and nxt is not None:
            seen.add((prev, nxt))
    if len(seen) < 2:
        return 0.0
    v = np.array([q - p for p, q in seen], np.float64)
    return (v.max() - v.min() - 1) / v.mean()


def exact_train(num, den, phase, n):
    """Spikes of a steady integrate-and-fire pixel at rate num / den spikes per step, in exact
    integer arithmetic (a float accumulation can move a crossing by one step)."""
    t = np.arange(n + 1, dtype=np.int64)
    level = (t * num + phase) // den
    return np.diff(level).astype(np.uint8)


@settings(max_examples=60, deadline=None)
@given(
    den=st.integers(1, 250),
    num=st.integers(1, 250),
    phase=st.integers(0, 249),
    c=st.integers(0, 599),
    radius=st.integers(1, 64),
)
def test_a_steady_pixel_has_no_spread_at_any_rate(den, num, phase, c, radius):
    """Intervals of a steady integrate-and-fire pixel (rates 0.004-1 spikes/step) differ by
    at most one step, so its spread is <= 0 (never dynamic), open intervals at the ends of the
    search range included, and the static check keeps its span rate."""
    num = min(num, den)
    s = exact_train(num, den, phase % den, 600).reshape(600, 1, 1)
    spread, isi, rates = steadiness(
        PackedWindow.from_frames(s), c, radius=radius, max_isi=200,
        spans=(tfp_span(c, 600, 160, "centred"),),
    )
    assert spread[0, 0] <= 1e-6
    assert not steady_mask(spread, tol=0.0, noise=0.0, noise_factor=3.5, close_size=0).any()
    kept = check_static(rates[0], isi, match=0.0)
    if np.count_nonzero(s) >= 3:
        np.testing.assert_array_equal(kept, rates[0])


def test_a_pixel_whose_light_changes_is_dynamic_and_gets_its_tfi():
    n, c = 600, 300
    r = np.full((n, 2), 0.1)
    r[c + 5 :, 1] = 0.35  # pixel 1 brightens 5 steps after t
    s = if_train(r, 0.3, n).reshape(n, 1, 2)
    src = PackedWindow.from_frames(s)
    spread, isi, rates = steadiness(src, c, radius=24, max_isi=200, spans=((c - 80, c + 80),))
    assert spread[0, 0] <= 0 < 0.2 < spread[0, 1]
    out = check_static(rates[0], isi, match=0.05)
    assert out[0, 0] == rates[0][0, 0]  # steady: the span rate
    assert out[0, 1] == np.float32(1.0 / isi[0, 1])  # changed: the TFI at t
    assert out[0, 1] != rates[0][0, 1]


@pytest.mark.parametrize("seed", range(4))
def test_steadiness_equals_the_plain_rules(seed):
    """TFI interval, spread and span rates against the plain definitions (spikes read from
    the words vs written-out Python), open intervals at the search range's ends included."""
    rng = np.random.default_rng(seed)
    n, h, w = 300, 3, 70  # 70 columns cross a 64-pixel word block
    s = (rng.random((n, h, w)) < rng.uniform(0.005, 0.6, (1, h, w))).astype(np.uint8)
    c, radius, m = int(rng.integers(0, n)), int(rng.integers(1, 40)), int(rng.integers(5, 120))
    spans = (tfp_span(c, n, 60, "centred"), tfp_span(c, n, 16, "trailing"))
    spread, isi, rates = steadiness(
        PackedWindow.from_frames(s), c, radius=radius, max_isi=m, spans=spans
    )
    np.testing.assert_array_equal(isi, isi_at(s, c, m))
    a, b = max(0, c - m), min(n, c + m + 1)
    for y in range(h):
        for x in range(w):
            times = list(np.nonzero(s[:, y, x])[0])
            assert spread[y, x] == pytest.approx(brute_spread(times, c, radius, a, b), rel=1e-5)
    for (win, mode), got in zip(((60, "centred"), (16, "trailing")), rates, strict=True):
        want = static_rate(s, c, window=win, mode=mode, estimator="isi", max_isi=m)
        np.testing.assert_array_equal(got, want)


def test_noise_level_is_zero_without_noise_and_rises_with_shot_noise():
    from cfsr.simulate import simulate

    clean = simulate("disk", steps=700, height=60, width=90, seed=0)
    noisy = simulate("disk", steps=700, height=60, width=90, seed=0, noise="shot")
    levels = []
    for sim in (clean, noisy):
        spread, _, _ = steadiness(PackedWindow.from_frames(sim.spikes), 500, radius=24, max_isi=200)
        levels.append(noise_level(spread))
    assert levels[0] == 0.0
    assert 0.05 < levels[1] < 0.5  # ~0.2 at 100 electrons per threshold


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.sampled_from([-1.0, -0.25, 0.0, 0.1, 0.2, 0.5, 3.0, float("nan"), float("inf")]),
        min_size=0,
        max_size=40,
    )
)
def test_noise_level_is_the_clipped_median_of_its_rule(values):
    """The count shortcut (more than half the values <= 0: level 0, no median) gives the
    rule's value on any mix, odd and even counts, ties at the middle included: the rounds
    started from the plain median of the finite values."""
    s = np.asarray(values, np.float32)
    f = s[np.isfinite(s)]
    first = float(np.median(f)) if f.size else 0.0
    assert noise_level(s) == clipped_median(f, first, clip=3.0, rounds=3)


def test_noise_level_ignores_a_minority_of_strong_movers():
    rng = np.random.default_rng(0)
    spread = rng.normal(0.2, 0.05, (100, 100)).astype(np.float32)
    base = noise_level(spread)
    spread[:40] += 3.0  # 40 % of the frame moves strongly
    assert noise_level(spread) < base * 1.6  # the plain median would be ~0.3


def test_check_static_is_finite_for_dark_and_open_pixels():
    static = np.array([[0.0, 0.02, 1.0]], np.float32)
    isi = np.array([[401, 50, 1]], np.int32)
    out = check_static(static, isi, match=0.05)
    assert np.isfinite(out).all() and (out > 0).all() and (out <= 1).all()
    assert out[0, 0] == np.float32(1 / 401) and out[0, 1] == np.float32(0.02)


@pytest.mark.parametrize("seed", range(30))
def test_regularise_equals_the_scipy_reference(seed):
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(1, 50, 2))
    m = rng.random((h, w)) < rng.uniform(0.05, 0.9)
    np.testing.assert_array_equal(_fill_holes(m), ndi.binary_fill_holes(m))
    area = int(rng.integers(1, 20))
    got = regularise(m, close_size=0, min_area=area)
    filled = ndi.binary_fill_holes(m)
    lab, k = ndi.label(filled)
    keep = np.bincount(lab.ravel(), minlength=k + 1) >= area
    keep[0] = False
    np.testing.assert_array_equal(got, keep[lab] if area > 1 else filled)


def test_closing_does_not_glue_a_mask_to_the_frame_border():
    m = np.zeros((24, 48), bool)
    m[6:18:2, 3:45:3] = True  # a dotted band 6 px from the top and bottom edges
    out = regularise(m, close_size=15, min_area=16)
    assert out[6:17, 3:43].all()  # the dots and the gaps between them
    assert not out[:5].any() and not out[19:].any()


def test_csr_and_cfsr_defaults_take_the_steady_rules():
    ms = cfsr.methods()
    for name in ("csr", "cfsr"):
        p = {k: v["default"] for k, v in ms[name]["params"].items()}
        assert p["distinction"] == "steady" and p["static_estimator"] == "steady"
        assert ms[name]["presets"]["paper"]["distinction"] == "isi_set"
    assert ms["csr"]["params"]["dynamic_estimator"]["default"] == "steady"
    assert ms["csr"]["presets"]["paper"]["dynamic_estimator"] == "tfi"
