"""TFI and TFP against plain-Python references, and the streaming path against the whole array."""

from __future__ import annotations

import numpy as np
import pytest
from livehelpers import PACKED_LAYOUTS, streamed_outputs

import cfsr
from cfsr import Layout, StreamingReconstructor
from cfsr.methods.tfi import isi_at
from cfsr.spikes import SpikeRecording


def periodic(period, t=200, h=3, w=8, phase=0):
    s = np.zeros((t, h, w), np.uint8)
    s[phase::period] = 1
    return s


def rand_spikes(t=300, h=6, w=8, seed=0):
    rng = np.random.default_rng(seed)
    rate = rng.uniform(0.02, 0.7, size=(h, w))
    return (rng.random((t, h, w)) < rate).astype(np.uint8)


def ref_isi(col, c, m):
    lo, hi = max(0, c - m), min(len(col), c + m + 1)
    prev = [i for i in range(lo, c + 1) if col[i]]
    nxt = [i for i in range(c + 1, hi) if col[i]]
    if prev and nxt:
        return nxt[0] - prev[-1]
    if prev:
        p = prev[-1]
        return max(hi - p, p - prev[-2]) if len(prev) > 1 else hi - p
    if nxt:
        n = nxt[0]
        return max(n - lo + 1, nxt[1] - n) if len(nxt) > 1 else n - lo + 1
    return hi - lo + 1


def test_tfi_periodic_is_exact():
    for period in (1, 2, 3, 7, 25):
        r = cfsr.reconstruct(periodic(period), "tfi", [100])
        np.testing.assert_allclose(r, 1.0 / period, rtol=1e-6)


def test_tfi_matches_reference():
    s = rand_spikes()
    for c in (0, 1, 57, 150, 298, 299):
        for m in (3, 20, 400):
            got = isi_at(s, c, m)
            want = np.array(
                [[ref_isi(s[:, y, x], c, m) for x in range(s.shape[2])] for y in range(s.shape[1])]
            )
            assert np.array_equal(got, want), (c, m)


def test_tfi_never_fired_and_always_fired():
    z = np.zeros((100, 2, 8), np.uint8)
    r = cfsr.reconstruct(z, "tfi", [0, 50, 99], max_isi=40)
    assert np.all(np.isfinite(r)) and np.all(r > 0) and np.all(r <= 1.0 / 41)
    r = cfsr.reconstruct(np.ones((100, 2, 8), np.uint8), "tfi", [0, 50, 99])
    np.testing.assert_allclose(r, 1.0)


def test_tfp_trailing_and_centred_reference():
    s = rand_spikes()
    for t in (0, 10, 150, 299):
        for w in (1, 16, 32, 160):
            tr = cfsr.reconstruct(s, "tfp", [t], window=w, mode="trailing")[0]
            a = max(0, t - w + 1)
            np.testing.assert_allclose(tr, s[a : t + 1].sum(0) / (t + 1 - a), rtol=1e-6)
            ce = cfsr.reconstruct(s, "tfp", [t], window=w, mode="centred")[0]
            a, b = max(0, t - w // 2), min(300, t - w // 2 + w)
            np.testing.assert_allclose(ce, s[a:b].sum(0) / (b - a), rtol=1e-6)


def test_tfp_periodic_rate():
    r = cfsr.reconstruct(periodic(4, t=400), "tfp", [200], window=160)
    np.testing.assert_allclose(r, 0.25)


def test_outputs_are_float32_upright():
    s = np.zeros((50, 4, 8), np.uint8)
    s[:, 0, :] = 1  # top row always fires
    for m in ("tfi", "tfp"):
        r = cfsr.reconstruct(s, m, [25])
        assert r.dtype == np.float32 and r.shape == (1, 4, 8)
        assert r[0, 0].min() > r[0, 3].max()


def test_bad_arguments():
    s = rand_spikes(t=20)
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        cfsr.reconstruct(s, "nope", [1])
    with pytest.raises(ValueError, match="no parameter 'windw'"):
        cfsr.reconstruct(s, "tfp", [1], windw=3)
    with pytest.raises(ValueError, match="must be >= 1"):
        cfsr.reconstruct(s, "tfp", [1], window=0)
    with pytest.raises(ValueError, match=r"outside the recording \(0..19"):
        cfsr.reconstruct(s, "tfp", [20])
    with pytest.raises(ValueError, match="must be one of"):
        cfsr.reconstruct(s, "tfp", [1], mode="sideways")


def test_methods_listing():
    ms = cfsr.methods()
    assert {"tfi", "tfp"} <= set(ms)
    assert ms["tfp"]["params"]["window"]["default"] == 160
    assert ms["tfp"]["presets"]["paper"] == {"window": 160}


@pytest.mark.parametrize(
    "method,params",
    [("tfi", {"max_isi": 30}), ("tfp", {"window": 40}), ("tfp", {"window": 33, "mode": "centred"})],
)
@pytest.mark.parametrize("block", [1, 7, 64, 1000])
def test_streaming_equals_whole_array(method, params, block):
    s = rand_spikes(t=260, h=5, w=16, seed=2)
    times = [0, 3, 40, 128, 200, 259]
    whole = cfsr.reconstruct(s, method, times, **params)
    # the live path and the offline file path (sparse spans) give the same numbers
    got, off = streamed_outputs(s, method, times, params, block)
    for i, t in enumerate(times):
        np.testing.assert_array_equal(got[t].rate, whole[i])
        np.testing.assert_array_equal(off[t].rate, whole[i])


def test_streaming_detects_gaps_and_large_step_indices():
    s = rand_spikes(t=100, h=2, w=8)
    rec = SpikeRecording.from_array(s)
    base = 2**40  # 64-bit step indices far past 2^32
    sr = StreamingReconstructor("tfp", rec.layout, params={"window": 10})
    sr.push(rec.packed(0, 50), base)
    sr.push(rec.packed(60, 100), base + 60)  # 10 steps lost
    assert sr.gaps == 1 and sr.first_step == base + 60
    t, out = sr.latest()
    assert t == base + 99
    np.testing.assert_allclose(out.rate, s[90:100].sum(0) / 10)


def test_streaming_switch_method_keeps_history():
    s = rand_spikes(t=200, h=2, w=8)
    rec = SpikeRecording.from_array(s)
    sr = StreamingReconstructor("tfp", rec.layout, params={"window": 20})
    sr.push(rec.packed(0, 200), 0)
    sr.set_method("tfi", params={"max_isi": 50})
    np.testing.assert_array_equal(
        sr.compute(120).rate, cfsr.reconstruct(s, "tfi", [120], max_isi=50)[0]
    )


def test_layout_of_pushed_blocks_is_checked():
    sr = StreamingReconstructor("tfp", Layout(16, 4))
    with pytest.raises(ValueError, match=r"\(n, 8\)"):
        sr.push(np.zeros((3, 9), np.uint8), 0)


@pytest.mark.parametrize("layout", PACKED_LAYOUTS)
def test_packed_paths_equal_unpacked_kernels(layout):
    from cfsr._bits import pack_frames
    from cfsr.methods.tfi import tfi_rate, tfi_rate_packed
    from cfsr.methods.tfp import tfp_rate, tfp_rate_packed

    s = rand_spikes(t=300, h=layout.height, w=layout.width, seed=5)
    head = np.ones((300, layout.height, layout.head_cols), np.uint8)
    stored = np.concatenate([head, s] if layout.fliplr else [s, head], axis=2)
    pk = pack_frames(stored, flipud=layout.flipud, fliplr=layout.fliplr)
    for c in (0, 5, 150, 299):
        for m in (3, 40, 400):
            np.testing.assert_array_equal(
                tfi_rate_packed(pk, layout, c, max_isi=m), tfi_rate(s, c, max_isi=m)
            )
        for w, mode in ((1, "trailing"), (33, "centred"), (160, "trailing")):
            np.testing.assert_array_equal(
                tfp_rate_packed(pk, layout, c, window=w, mode=mode),
                tfp_rate(s, c, window=w, mode=mode),
            )
