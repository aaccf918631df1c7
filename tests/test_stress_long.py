"""Stress: a recording of more than 10^6 steps whose indices run past 2^32, streamed block by
block through every method and the per-pixel state. No NaN/Inf, no overflow, no drift, and the
float32 outputs agree with float64 references.

The scene is exactly periodic (every pixel's period divides 840 steps; some pixels are dark, some
fire every step), so any window method must return identical images at steps 840 apart, however
far along the stream. That is the drift check, and it holds for every registered method.
"""

from __future__ import annotations

import numpy as np
import pytest

import cfsr
from cfsr import Layout, StreamingReconstructor
from cfsr._bits import pack_frames
from cfsr.pixelstate import PixelState

H, W = 8, 16
PERIOD = 840
START = 2**32 - 600_000  # indices cross 2^32 mid-stream
STEPS = 1_100_000
BLOCK = 8192
LAYOUT = Layout(W, H)


def _periods() -> np.ndarray:
    divisors = [d for d in range(1, PERIOD + 1) if PERIOD % d == 0]
    rng = np.random.default_rng(0)
    per = rng.choice(divisors, size=(H, W)).astype(np.int64)
    per[0, :4] = 0  # dark: never fires
    per[1, :4] = 1  # saturated: fires every step
    return per


PER = _periods()
PHASE = np.random.default_rng(1).integers(0, PERIOD, size=(H, W))


def frames(a: int, n: int) -> np.ndarray:
    t = np.arange(a, a + n, dtype=np.int64)[:, None, None]
    safe = np.where(PER > 0, PER, 1)
    f = ((t + PHASE) % safe == 0) & (PER > 0)
    return f.astype(np.uint8)


def blocks():
    for a in range(START, START + STEPS, BLOCK):
        yield a, pack_frames(frames(a, min(BLOCK, START + STEPS - a)))


def _stream(method: str, params: dict, times: list[int]) -> dict[int, cfsr.Output]:
    sr = StreamingReconstructor(method, LAYOUT, params=params, slack=BLOCK)
    return dict(sr.run(blocks(), times))


@pytest.mark.slow
def test_tfi_tfp_exact_over_a_long_stream_past_2_32():
    times = [START + 1000, 2**32 + 5 * PERIOD, START + STEPS - 2000]
    for t in times:
        assert t < START + STEPS
    outs_tfp = _stream("tfp", {"window": PERIOD}, times)
    outs_tfi = _stream("tfi", {"max_isi": PERIOD}, times)
    # float64 references: TFP over a whole period counts exactly PERIOD/P spikes; TFI = 1/P
    safe = np.where(PER > 0, PER, 1).astype(np.float64)
    ref = np.where(PER > 0, 1.0 / safe, 0.0)
    for t in times:
        np.testing.assert_allclose(outs_tfp[t].rate, ref, rtol=1e-6, atol=0)
        tfi = outs_tfi[t].rate
        np.testing.assert_allclose(tfi[PER > 0], ref[PER > 0], rtol=1e-6)
        assert np.all(tfi[PER == 0] > 0) and np.all(tfi[PER == 0] <= 1.0 / PERIOD)


@pytest.mark.slow
def test_pixel_state_long_stream():
    ps = PixelState(LAYOUT)
    for a, blk in blocks():
        ps.update(blk, a)
    end = START + STEPS
    counts = ps.image(ps.count)
    safe = np.where(PER > 0, PER, 1)
    # exact count of t in [START, end) with (t + phase) % P == 0
    first = START + (-(START + PHASE)) % safe
    expect = np.where(PER > 0, (end - 1 - first) // safe + 1, 0)
    np.testing.assert_array_equal(counts, expect)
    last = ps.image(ps.last)
    expect_last = np.where(PER > 0, end - 1 - ((end - 1 + PHASE) % safe), -1)
    np.testing.assert_array_equal(last, expect_last)
    assert last.max() > 2**32
    np.testing.assert_array_equal(ps.image(ps.isi)[PER > 0], PER[PER > 0])


@pytest.mark.slow
@pytest.mark.parametrize("method", sorted(cfsr.methods()))
def test_every_method_is_finite_bounded_and_drift_free(method):
    m = cfsr.get_method(method)
    params = {k: p.default for k, p in m.params.items()}
    before, after = m.window(params)
    t0 = START + max(before, 2000)
    times = [t0, t0 + PERIOD * 600, t0 + PERIOD * 1200]  # ~0.5M and ~1M steps later
    assert times[-1] + after < START + STEPS
    outs = _stream(method, {}, times)
    for t in times:
        r = outs[t].rate
        assert r.dtype == np.float32
        assert np.all(np.isfinite(r)), (method, t)
        assert r.min() >= 0 and r.max() <= 1.0 + 1e-6, (method, t, r.min(), r.max())
    np.testing.assert_array_equal(outs[times[0]].rate, outs[times[1]].rate)
    np.testing.assert_array_equal(outs[times[0]].rate, outs[times[2]].rate)


def _extreme_values(p: cfsr.methods.Param) -> list:
    if p.choices is not None:
        return list(p.choices)
    if isinstance(p.default, bool):
        return [True, False]
    if not isinstance(p.default, (int, float)):
        return [p.default]
    lo = p.minimum if p.minimum is not None else 0
    hi = p.default * 4 if p.default else 8
    if p.maximum is not None:
        hi = min(hi, p.maximum)
    kind = type(p.default)
    return [kind(lo), kind(hi)]


@pytest.mark.slow
@pytest.mark.parametrize("method", sorted(cfsr.methods()))
def test_extreme_parameters_stay_finite_and_bounded(method):
    """Each parameter at its smallest allowed value and at 4x its default (or its maximum),
    one at a time, on a scene with dark, saturated and ordinary pixels."""
    m = cfsr.get_method(method)
    rng = np.random.default_rng(3)
    rate = rng.uniform(0.0, 0.8, (H, W))
    rate[0, :4], rate[1, :4] = 0.0, 1.0
    spikes = (rng.random((900, H, W)) < rate).astype(np.uint8)
    checked = 0
    for name, p in m.params.items():
        for v in _extreme_values(p):
            r = cfsr.reconstruct(spikes, method, [450], **{name: v})
            assert np.all(np.isfinite(r)), (method, name, v)
            assert r.min() >= 0 and r.max() <= 1.0 + 1e-6, (method, name, v, r.min(), r.max())
            checked += 1
    assert checked >= len(m.params)
