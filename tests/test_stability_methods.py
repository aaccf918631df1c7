"""Numerical stability of every reconstruction method (property tests with hypothesis).

No NaN or Inf ever; rates bounded in [0, 1] spikes/step; a uniform static scene gives a uniform
image; a brighter scene never gives a darker image; edge cases: no spikes at all, a spike every
step, a 1 x 1 image, step indices beyond 2**32, empty static or dynamic regions.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import cfsr
from cfsr.methods.registry import get_method, resolve_params

METHODS = ("tfi", "tfp", "tfa", "tfstp", "snm", "csr", "cfsr")

# Small windows so that hypothesis can run many examples; defaults are used in the edge cases.
SMALL = {
    "tfi": {"max_isi": 30},
    "tfp": {"window": 12},
    "tfa": {"threshold": 5, "max_window": 30},
    "tfstp": {"warmup": 40},
    "snm": {"long_window": 24, "max_isi": 20},
    "csr": {"T": 40, "theta": 3, "tfp_window": 12, "max_isi": 20},
    "cfsr": {
        "T": 40,
        "theta": 3,
        "tfp_window": 20,
        "max_isi": 20,
        "mog_frames": 3,
        "mog_stride": 6,
        "mog_window": 8,
        "pm_step": 2,
        "pm_count": 3,
        "pm_guide": 4,
        "min_area": 1,
    },
}

FAST = settings(
    max_examples=25, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)


def run(method, window, center, start=0, params=None):
    m = get_method(method)
    p = resolve_params(m, SMALL[method] if params is None else params)
    return m.compute(np.ascontiguousarray(window, dtype=np.uint8), center, start, p)


def check_output(out, shape, method):
    r = out.rate
    assert r.shape == shape and r.dtype == np.float32, method
    assert np.isfinite(r).all(), method
    assert r.min() >= 0.0 and r.max() <= 1.0, (method, float(r.min()), float(r.max()))
    for name, m in out.masks.items():
        assert m.shape == shape and m.dtype == np.bool_, (method, name)


@st.composite
def spike_windows(draw):
    n = draw(st.integers(1, 90))
    h = draw(st.integers(1, 5))
    w = draw(st.integers(1, 6))
    kind = draw(st.sampled_from(["random", "none", "all", "periodic", "sparse"]))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    if kind == "none":
        s = np.zeros((n, h, w), np.uint8)
    elif kind == "all":
        s = np.ones((n, h, w), np.uint8)
    elif kind == "periodic":
        p = rng.integers(1, 40, (h, w))
        ph = rng.integers(0, 40, (h, w))
        t = np.arange(n)[:, None, None]
        s = ((t + ph) % p == 0).astype(np.uint8)
    else:
        dens = rng.uniform(0, 0.05 if kind == "sparse" else 1.0, (h, w))
        s = (rng.random((n, h, w)) < dens).astype(np.uint8)
    center = draw(st.integers(0, n - 1))
    start = draw(st.sampled_from([0, 7, 2**32 - 1, 2**32 + 5, 2**40, 2**62]))
    return s, center, start


@pytest.mark.parametrize("method", METHODS)
@FAST
@given(case=spike_windows())
def test_finite_and_bounded_on_any_window(method, case):
    s, center, start = case
    check_output(run(method, s, center, start), s.shape[1:], method)


@pytest.mark.parametrize("method", METHODS)
@FAST
@given(
    period=st.integers(1, 40),
    phase=st.integers(0, 39),
    n=st.integers(1, 120),
    h=st.integers(1, 6),
    w=st.integers(1, 7),
    frac=st.floats(0, 1),
)
def test_uniform_static_scene_gives_uniform_image(method, period, phase, n, h, w, frac):
    t = np.arange(n)[:, None, None]
    s = np.broadcast_to(((t + phase) % period == 0).astype(np.uint8), (n, h, w))
    out = run(method, s, int(frac * (n - 1)))
    check_output(out, (h, w), method)
    assert np.ptp(out.rate) <= 1e-6, (method, out.rate)
    for name, m in out.masks.items():
        assert m.all() or not m.any(), (method, name)


def if_uniform(intensity, steps, v0):
    """Integrate-and-fire pixels under one uniform intensity, initial potentials ``v0``."""
    v = v0.copy()
    out = np.zeros((steps,) + v0.shape, np.uint8)
    for t in range(steps):
        v += 0.5 * intensity
        s = v >= 1.0
        v -= s
        out[t] = s
    return out


@pytest.mark.parametrize("method", METHODS)
@FAST
@given(
    lo=st.integers(0, 8),
    gap=st.integers(1, 9),
    seed=st.integers(0, 2**31 - 1),
    frac=st.floats(0.3, 0.7),
)
def test_brighter_scene_never_gives_darker_image(method, lo, gap, seed, frac):
    # intensities on a 0.1 grid: rate gap >= 0.05 spikes/step, resolvable by every window
    i1 = 0.05 + 0.1 * lo
    i2 = min(1.0, i1 + 0.1 * gap)
    v0 = np.random.default_rng(seed).random((8, 8))
    n = 160
    c = int(frac * (n - 1))
    a = run(method, if_uniform(i1, n, v0), c).rate
    b = run(method, if_uniform(i2, n, v0), c).rate
    assert b.mean() >= a.mean(), (method, i1, i2, float(a.mean()), float(b.mean()))


@pytest.mark.parametrize("method", ["tfi", "tfp"])
@FAST
@given(case=spike_windows(), extra=st.integers(0, 2**31 - 1))
def test_more_spikes_never_darker_pointwise(method, case, extra):
    """Adding spikes never darkens TFP, nor TFI where t lies inside a closed interval.

    (Where t is before the first or after the last spike in range, TFI falls back to a bound
    that uses the neighbouring interval, so a far extra spike can lengthen that guess. TFA is
    not monotone in the spike set either: with fewer than ``threshold`` intervals in range, an
    extra distant spike adds a long interval to the average. The scene-level property above
    holds for every method.)
    """
    s, center, _ = case
    more = s | (np.random.default_rng(extra).random(s.shape) < 0.2).astype(np.uint8)
    a = run(method, s, center).rate
    b = run(method, more, center).rate
    if method == "tfp":
        closed = np.ones(a.shape, bool)
    else:
        m = SMALL[method]["max_isi"]
        closed = s[max(0, center - m) : center + 1].any(0) & s[center + 1 : center + m + 1].any(0)
    assert (b[closed] >= a[closed] - 1e-7).all(), method


# --------------------------------------------------------------------------- edge cases, defaults


@pytest.mark.parametrize("method", METHODS)
def test_edge_cases_with_default_parameters(method):
    for s in (
        np.zeros((700, 6, 8), np.uint8),  # no spikes at all
        np.ones((700, 6, 8), np.uint8),  # a spike every step
        np.zeros((3, 1, 1), np.uint8),  # tiny window
        np.ones((1, 1, 1), np.uint8),
    ):
        n = s.shape[0]
        for t in sorted({0, n // 2, n - 1}):
            r, masks = cfsr.reconstruct(s, method, [t], return_masks=True)
            assert np.isfinite(r).all() and r.min() >= 0 and r.max() <= 1, (method, s.shape, t)
            assert np.ptp(r) <= 1e-6, (method, s.shape, t)
            if s.any() and n > 1:
                np.testing.assert_allclose(r, 1.0, rtol=1e-5)


@pytest.mark.parametrize("method", METHODS)
def test_one_by_one_image(method):
    rng = np.random.default_rng(4)
    s = (rng.random((800, 1, 1)) < 0.3).astype(np.uint8)
    r, masks = cfsr.reconstruct(s, method, [0, 399, 799], return_masks=True)
    assert r.shape == (3, 1, 1) and np.isfinite(r).all() and (r >= 0).all() and (r <= 1).all()
    for m in masks.values():
        assert m.shape == (3, 1, 1)


def test_all_dynamic_and_all_static_regions():
    """CSR/CFSR with every pixel dynamic (empty static region) and every pixel static."""
    rng = np.random.default_rng(0)
    n, h, w = 500, 12, 16
    # every pixel's rate jumps around: many distinct ISIs -> all dynamic
    rate = rng.uniform(0.05, 0.6, (n // 10, h, w)).repeat(10, axis=0)
    s = (rng.random((n, h, w)) < rate).astype(np.uint8)
    for method in ("csr", "cfsr"):
        # Eq. 5-6: Bernoulli spikes are all noise to the steady distinction (docs/methods.md)
        r, m = cfsr.reconstruct(
            s, method, [400], return_masks=True, theta=3, distinction="isi_set"
        )
        assert m["coarse"].all()
        assert np.isfinite(r).all() and (r >= 0).all() and (r <= 1).all()
    static = np.zeros((n, h, w), np.uint8)
    static[::3] = 1
    for method in ("csr", "cfsr"):
        r, m = cfsr.reconstruct(static, method, [400], return_masks=True)
        assert not any(v.any() for v in m.values())
        np.testing.assert_allclose(r, 1 / 3, atol=0.02)
