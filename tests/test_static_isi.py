"""The ``isi`` static estimator (issue 13): exact for steady pixels, TFI below two spikes,
packed == unpacked, finite and in [0, 1] for any spike train, and wired into CSR/CFSR."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from livehelpers import PACKED_LAYOUTS

from cfsr import Layout
from cfsr._bits import pack_frames
from cfsr._words import PackedWindow
from cfsr.methods.cfsr.static_gate import span_isi_rate
from cfsr.methods.registry import get_method, resolve_params
from cfsr.methods.tfi import tfi_rate
from cfsr.methods.tfp import (
    isi_span_rate,
    isi_span_stored,
    static_rate,
    static_rate_packed,
    tfp_rate,
    tfp_span,
)


def steady(rates, n=1200, phase=0.37):
    """Integrate-and-fire pixels at constant ``rates`` (spikes/step): ``(n, 1, len(rates))``."""
    rates = np.asarray(rates, np.float64)
    acc = np.full(rates.size, phase)
    out = np.zeros((n, 1, rates.size), np.uint8)
    for t in range(n):
        acc += rates
        fire = acc >= 1.0
        acc[fire] -= 1.0
        out[t, 0, fire] = 1
    return out


def ref_span(col, a, b):
    t = np.nonzero(col[a:b])[0]
    if len(t) >= 2:
        return (len(t) - 1) / (t[-1] - t[0])
    return len(t) / max(1, b - a)


RATES = [0.005, 0.008, 0.01, 0.013, 0.02, 0.031, 0.037, 0.05, 0.1, 0.37, 0.5, 1.0]


@pytest.mark.parametrize("window", [160, 400, 1000])
def test_steady_pixel_rate_is_exact(window):
    s = steady(RATES)
    c = 1100
    got = static_rate(s, c, window=window, mode="trailing", estimator="isi", max_isi=400)[0]
    tfp = tfp_rate(s, c, window=window)[0]
    a, b = tfp_span(c, s.shape[0], window, "trailing")
    for r, g, p, col in zip(RATES, got, tfp, s[:, 0, :].T, strict=True):
        n = int(col[a:b].sum())
        if n >= 2:  # first-to-last distance is (n - 1) / r within one step
            t = np.nonzero(col[a:b])[0]
            assert abs(g - r) <= r / (t[-1] - t[0]) + 1e-6, (r, g)
            if abs(1 / r - round(1 / r)) < 1e-9:  # whole-step period: exact
                assert g == pytest.approx(r, rel=1e-6), (r, g)
        # within the window count's worst case (one spike over the window) too
        assert abs(g - r) <= 1 / window + 1e-6, (r, g, p)
    # 0.02 spikes/step over 160 steps: TFP is off by up to a spike (3 or 4 of 3.2), isi exact
    i = RATES.index(0.02)
    assert got[i] == pytest.approx(0.02, rel=1e-6)


def test_low_rates_within_one_percent_on_paper_window():
    rates = np.linspace(0.005, 0.05, 46)
    s = steady(rates, n=900)
    got = static_rate(s, 800, window=160, mode="trailing", estimator="isi", max_isi=400)[0]
    # >= 2 spikes: first-to-last spike distance exact to a step; fewer: the TFI interval
    assert np.all(np.abs(got - rates) / rates <= 1 / 30 + 1e-6), np.abs(got - rates) / rates
    tfp = tfp_rate(s, 800, window=160)[0]
    assert np.abs(got - rates).mean() < 0.25 * np.abs(tfp - rates).mean()


def test_fewer_than_two_spikes_take_the_tfi():
    n = 400
    s = np.zeros((n, 1, 4), np.uint8)
    s[[50, 300], 0, 0] = 1  # one spike (300) in the span [249, 349): the TFI at 299 = 1/250
    s[[10, 390], 0, 1] = 1  # none in the span: TFI over 380 steps
    s[[260, 280, 300], 0, 2] = 1  # three spikes: 2 / 40
    # pixel 3 never fires: TFI's open bound 1 / (search range)
    got = static_rate(s, 299, window=100, mode="centred", estimator="isi", max_isi=300)[0]
    tfi = tfi_rate(s, 299, max_isi=300)[0]
    assert tfp_span(299, n, 100, "centred") == (249, 349)
    assert got[0] == pytest.approx(tfi[0]) and got[0] == pytest.approx(1 / 250)
    assert got[1] == pytest.approx(tfi[1]) and got[1] == pytest.approx(1 / 380)
    assert got[2] == pytest.approx(2 / 40)
    assert got[3] == pytest.approx(tfi[3]) and got[3] == pytest.approx(1 / 401)
    # the bare span rule (no TFI): count / span
    bare = isi_span_rate(s, 249, 349)[0]
    np.testing.assert_allclose(bare, [1 / 100, 0.0, 2 / 40, 0.0])
    marked = isi_span_rate(s, 249, 349, mark=True)[0]
    np.testing.assert_allclose(marked, [-1.0, -1.0, 2 / 40, -1.0])


def test_span_matches_reference():
    rng = np.random.default_rng(3)
    s = (rng.random((300, 5, 23)) < rng.random((1, 5, 23)) * 0.4).astype(np.uint8)
    for a, b in [(0, 300), (10, 200), (50, 51), (5, 5), (299, 300)]:
        got = isi_span_rate(s, a, b)
        ref = np.array([[ref_span(s[:, y, x], a, b) for x in range(23)] for y in range(5)])
        np.testing.assert_allclose(got, ref, rtol=1e-6)


@pytest.mark.parametrize(
    "layout", [*PACKED_LAYOUTS, Layout(1000, 3)]  # the last: several 64-byte chunks
)
def test_packed_equals_unpacked(layout):
    rng = np.random.default_rng(5)
    h, w = layout.height, layout.width
    s = (rng.random((300, h, w)) < rng.uniform(0.0, 0.5, (h, w))).astype(np.uint8)
    s[:, 0, 0] = 0  # a pixel that never fires
    s[:, 0, 1] = 1  # one that fires every step
    head = np.ones((300, h, layout.head_cols), np.uint8)
    stored = np.concatenate([head, s] if layout.fliplr else [s, head], axis=2)
    pk = pack_frames(stored, flipud=layout.flipud, fliplr=layout.fliplr)
    for c in (0, 5, 150, 299):
        for win, mode in ((1, "trailing"), (33, "centred"), (160, "trailing")):
            kw = dict(window=win, mode=mode, estimator="isi", max_isi=40)
            np.testing.assert_array_equal(
                static_rate_packed(pk, layout, c, **kw), static_rate(s, c, **kw)
            )
    src = PackedWindow.from_frames(s)
    for a, b in ((0, 300), (40, 200), (7, 8)):
        np.testing.assert_array_equal(span_isi_rate(src, a, b), isi_span_rate(s, a, b))
        np.testing.assert_array_equal(
            span_isi_rate(src, a, b, mark=True), isi_span_rate(s, a, b, mark=True)
        )


@settings(
    max_examples=40, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    n=st.integers(1, 200),
    w=st.integers(1, 20),
    p=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31 - 1),
    data=st.data(),
)
def test_finite_and_bounded(n, w, p, seed, data):
    rng = np.random.default_rng(seed)
    s = (rng.random((n, 2, w)) < p).astype(np.uint8)
    c = data.draw(st.integers(0, n - 1))
    win = data.draw(st.integers(1, 300))
    mode = data.draw(st.sampled_from(["trailing", "centred"]))
    m = data.draw(st.integers(1, 300))
    r = static_rate(s, c, window=win, mode=mode, estimator="isi", max_isi=m)
    assert r.dtype == np.float32 and np.isfinite(r).all()
    assert r.min() >= 0.0 and r.max() <= 1.0
    a, b = tfp_span(c, n, win, mode)
    bare = isi_span_stored(pack_frames(s, flipud=False), a, b)[: 2 * w]
    assert np.isfinite(bare).all() and bare.min() >= 0.0 and bare.max() <= 1.0


def test_defaults_and_presets():
    for name in ("csr", "cfsr"):
        m = get_method(name)
        assert resolve_params(m, {})["static_estimator"] == "steady"
        assert resolve_params(m, {})["distinction"] == "steady"
        for preset in ("paper", "simulated"):
            assert m.presets[preset]["static_estimator"] == "tfp"
            assert m.presets[preset]["distinction"] == "isi_set"
    assert resolve_params(get_method("cfsr"), {})["mog_estimator"] == "tfp"
    with pytest.raises(ValueError):
        resolve_params(get_method("csr"), {"static_estimator": "median"})


@pytest.mark.parametrize("name", ["csr", "cfsr"])
def test_static_scene_is_exact_with_isi(name):
    """A static scene of steady pixels: CSR and CFSR give the rates, TFP does not."""
    rng = np.random.default_rng(1)
    rates = rng.uniform(0.01, 0.3, (12, 20))
    s = steady(rates.ravel(), n=900, phase=0.5).reshape(900, 12, 20)
    m = get_method(name)
    c = 700
    err = {}
    for est in ("isi", "tfp"):
        p = resolve_params(m, {"static_estimator": est})
        err[est] = np.abs(m.compute(s, c, 0, p).rate - rates).max()
    assert err["isi"] < 0.3 * err["tfp"], err
