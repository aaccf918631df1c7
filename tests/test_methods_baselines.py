"""The paper's baselines: TFA (adaptive threshold), TFSTP (short-term plasticity), SNM."""

from __future__ import annotations

import math

import numpy as np
import pytest

import cfsr
from cfsr.methods.snm import graph_cut_labels, motion_confidence
from cfsr.methods.tfa import adaptive_rate
from cfsr.methods.tfstp import state_grid, state_start, stp_rate


def periodic(period, t=600, h=2, w=3, phase=0):
    s = np.zeros((t, h, w), np.uint8)
    s[phase::period] = 1
    return s


# --------------------------------------------------------------------------- TFA


@pytest.mark.parametrize("period", [1, 2, 3, 5, 17])
@pytest.mark.parametrize("threshold", [1, 4, 12])
def test_tfa_exact_on_regular_trains(period, threshold):
    r = cfsr.reconstruct(periodic(period), "tfa", [300], threshold=threshold)
    np.testing.assert_allclose(r, 1.0 / period, rtol=1e-6)


def test_tfa_one_interval_is_tfi_and_adapts_its_window():
    rng = np.random.default_rng(0)
    s = (rng.random((400, 4, 6)) < rng.uniform(0.05, 0.6, (4, 6))).astype(np.uint8)
    for t in (150, 201, 250):
        np.testing.assert_allclose(
            adaptive_rate(s, t, threshold=1, max_window=150),
            cfsr.reconstruct(s, "tfi", [t], max_isi=150)[0],
            rtol=1e-6,
        )
    # a rate step: a short threshold follows it, a long one averages across it
    step = np.zeros((400, 1, 1), np.uint8)
    step[:200:8] = 1
    step[200::2] = 1
    assert adaptive_rate(step, 260, threshold=4)[0, 0] == pytest.approx(0.5)
    assert adaptive_rate(step, 205, threshold=40)[0, 0] < 0.4


def test_tfa_refractory_merges_too_short_intervals():
    s = periodic(6, t=300, h=1, w=1)
    s[151, 0, 0] = 1  # a noise spike one step after a regular one (150)
    plain = adaptive_rate(s, 160, threshold=6)[0, 0]
    refined = adaptive_rate(s, 160, threshold=6, refractory=0.5)[0, 0]
    assert plain > 1 / 6 + 0.01
    assert refined == pytest.approx(1 / 6, rel=0.25)


# --------------------------------------------------------------------------- TFSTP


@pytest.mark.parametrize("period", [1, 2, 3, 4, 7, 12])
def test_tfstp_steady_state_inversion_is_exact(period):
    r = stp_rate(periodic(period, t=500), 499)
    np.testing.assert_allclose(r, 1.0 / period, rtol=1e-4)


def test_tfstp_follows_a_rate_change_and_is_causal():
    s = np.zeros((600, 1, 1), np.uint8)
    s[:300:10] = 1
    s[300::3] = 1
    assert stp_rate(s, 290)[0, 0] == pytest.approx(0.1, rel=1e-3)
    assert stp_rate(s, 599)[0, 0] == pytest.approx(1 / 3, rel=1e-3)
    # causal: spikes after t change nothing
    cut = s.copy()
    cut[400:] = 0
    assert stp_rate(cut, 399)[0, 0] == stp_rate(s, 399)[0, 0]


def test_tfstp_parameter_checks_and_sparse_pixels():
    with pytest.raises(ValueError, match="bad STP parameters"):
        stp_rate(periodic(3), 100, u0=1.5)
    z = np.zeros((50, 2, 2), np.uint8)
    z[10, 0, 0] = 1
    # warm-up 40: the state starts on a 10-step grid at least 40 steps before t, here step 0
    r = stp_rate(z, 49, warmup=40)
    assert np.isfinite(r).all() and r[0, 0] == pytest.approx(1 / 50)  # 1 spike in 50 steps
    assert (r[1:, :] == 0).all()
    # the same window cut from a recording at an absolute step: the grid is absolute
    assert stp_rate(z[9:], 40, warmup=40, start=9)[0, 0] == pytest.approx(1 / 41)  # from 9
    assert stp_rate(z[5:], 44, warmup=40, start=5)[0, 0] == pytest.approx(1 / 45)  # from 5


@pytest.mark.parametrize("warmup", [1, 7, 40, 400])
def test_tfstp_state_starts_on_an_absolute_grid(warmup):
    g = state_grid(warmup)
    assert g == -(-warmup // 4)
    for t in range(0, 3 * warmup + 5):
        s0 = state_start(t, warmup)
        assert s0 % g == 0 or s0 == 0
        assert t - warmup - g < s0 <= max(0, t - warmup)


def test_tfstp_dense_outputs_share_one_state_with_identical_results():
    """Outputs one step apart continue the state (memo) and equal isolated outputs."""
    rng = np.random.default_rng(5)
    s = (rng.random((700, 6, 9)) < rng.uniform(0.02, 0.6, (6, 9))).astype(np.uint8)
    memo: dict = {}
    for t in [399, 400, 401, 450, 450, 499, 500, 650, 420, 699]:  # forward, repeats, back
        dense = stp_rate(s, t, memo=memo)
        np.testing.assert_array_equal(dense, stp_rate(s, t))
    # through the library: one reconstruct call over dense times keeps a memo
    times = list(range(600, 700))
    whole = cfsr.reconstruct(s, "tfstp", times)
    for i in (0, 37, 99):
        np.testing.assert_array_equal(whole[i], cfsr.reconstruct(s, "tfstp", [times[i]])[0])


# --------------------------------------------------------------------------- SNM


def test_snm_confidence_graph_cut_and_reconstruction():
    rng = np.random.default_rng(0)
    h, w, steps = 24, 32, 500
    # left half static at rate 1/4; right half switches between rate 1/2 and 1/8 every 20 steps
    s = np.zeros((steps, h, w), np.uint8)
    s[::4, :, : w // 2] = 1
    for a in range(0, steps, 40):
        s[a : a + 20 : 2, :, w // 2 :] = 1
        s[a + 20 : a + 40 : 8, :, w // 2 :] = 1
    conf = motion_confidence(s, 250, long_window=160, max_isi=100, motion_sigma=0.35)
    assert conf[:, : w // 2 - 2].max() < 0.2 and conf[:, w // 2 + 2 :].min() > 0.5
    noisy = np.clip(conf + rng.normal(0, 0.3, conf.shape), 0, 1)
    labels = graph_cut_labels(noisy, 2.0)
    assert labels[:, w // 2 + 2 :].mean() > 0.95 and labels[:, : w // 2 - 2].mean() < 0.05
    assert graph_cut_labels(noisy, 0.0).sum() != labels.sum()  # smoothing does something
    rate, masks = cfsr.reconstruct(s, "snm", [250], return_masks=True)
    motion = masks["motion"][0]
    assert motion[:, w // 2 + 2 :].all() and not motion[:, : w // 2 - 2].any()
    np.testing.assert_allclose(rate[0][:, : w // 2 - 2], 0.25, rtol=0.05)


def test_snm_static_scene_has_no_motion():
    s = periodic(5, t=400, h=6, w=7)
    rate, masks = cfsr.reconstruct(s, "snm", [200], return_masks=True)
    assert not masks["motion"].any()
    np.testing.assert_allclose(rate, 0.2, rtol=1e-6)
    assert math.isclose(float(rate.mean()), 0.2, rel_tol=1e-6)
