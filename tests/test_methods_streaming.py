"""Every method through the streaming reconstructor (block by block) equals the whole-array path.

Each method is a pure function of its spike window, so the live worker can use it unchanged;
these tests hold that promise for the stateful-looking stages too (MOG history rebuilt per
output, the synapse state of TFSTP, PatchMatch's random search seeded by the absolute step).
"""

from __future__ import annotations

import numpy as np
import pytest
from livehelpers import streamed_outputs

import cfsr
from cfsr import StreamingReconstructor
from cfsr.methods.tfstp import state_grid
from cfsr.spikes import SpikeRecording

# small windows keep the test quick; defaults are exercised by the accuracy tests
SMALL = {
    "tfa": {"threshold": 6, "max_window": 60},
    "tfstp": {"warmup": 80},
    "snm": {"long_window": 40, "max_isi": 40},
    "csr": {"T": 60, "theta": 3, "tfp_window": 20, "max_isi": 40},
    "cfsr": {
        "T": 60,
        "theta": 3,
        "tfp_window": 40,
        "max_isi": 40,
        "mog_frames": 4,
        "mog_stride": 10,
        "mog_window": 16,
        "pm_step": 3,
        "pm_count": 4,
        "pm_guide": 8,
    },
}


def moving_scene(steps=420, h=16, w=24, seed=3):
    """A bright square drifting over a random static background (integrate-and-fire)."""
    rng = np.random.default_rng(seed)
    bg = rng.uniform(0.05, 0.6, (h, w))
    v = rng.random((h, w))
    out = np.zeros((steps, h, w), np.uint8)
    for t in range(steps):
        img = bg.copy()
        x0 = 2 + (t // 12) % (w - 8)
        img[4:10, x0 : x0 + 6] = np.linspace(0.5, 1.0, 6)
        v += 0.6 * img
        s = v >= 1
        v -= s
        out[t] = s
    return out


@pytest.mark.parametrize("method", ["tfa", "tfstp", "snm", "csr", "cfsr"])
@pytest.mark.parametrize("block", [1, 37, 1000])
def test_streaming_equals_whole_array(method, block):
    if block == 1 and method == "cfsr":
        block = 5  # one-frame blocks are covered by the cheaper methods
    s = moving_scene()
    params = SMALL[method]
    times = [0, 1, 90, 200, 333, 419]
    whole, wm = cfsr.reconstruct(s, method, times, return_masks=True, **params)
    got, off = streamed_outputs(s, method, times, params, block)
    for i, t in enumerate(times):
        np.testing.assert_array_equal(got[t].rate, whole[i])
        for k, m in wm.items():
            np.testing.assert_array_equal(got[t].masks[k], m[i])
        np.testing.assert_array_equal(off[t].rate, whole[i])


@pytest.mark.parametrize("method", ["tfa", "tfstp", "snm", "csr", "cfsr"])
def test_large_absolute_step_indices(method):
    """The same window at step 2**40 gives the same frame (seeds use 64-bit arithmetic)."""
    s = moving_scene(steps=300)
    rec = SpikeRecording.from_array(s)
    params = SMALL[method]
    base = 2**40 + 12345
    if method == "tfstp":  # its state starts on a grid of absolute steps: shift by whole cells
        base -= base % state_grid(params["warmup"])
    sr0 = StreamingReconstructor(method, rec.layout, params=params)
    sr1 = StreamingReconstructor(method, rec.layout, params=params)
    sr0.push(rec.packed(0, 300), 0)
    sr1.push(rec.packed(0, 300), base)
    a = sr0.compute(250, final=True)
    b = sr1.compute(base + 250, final=True)
    assert np.isfinite(b.rate).all()
    if method != "cfsr":
        np.testing.assert_array_equal(a.rate, b.rate)
    else:  # PatchMatch's random search is seeded by the absolute step: equal up to matching
        np.testing.assert_allclose(a.rate, b.rate, atol=0.25)
        np.testing.assert_array_equal(a.masks["fine"], b.masks["fine"])


@pytest.mark.parametrize(
    "params",
    [
        {},  # steady distinction, steady static check, steady dynamic region
        {"distinction": "isi_set"},
        {"distinction": "isi_set", "static_estimator": "isi", "dynamic_estimator": "tfi"},
        {"static_estimator": "tfp", "dynamic_estimator": "tfi"},
    ],
)
def test_csr_packed_path_equals_unpacked(params):
    """The packed CSR path (used by the library and the live worker) equals csr_frames."""
    from cfsr._bits import pack_frames
    from cfsr.layout import Layout
    from cfsr.methods.cfsr.coarse import CsrSettings, csr_frame_packed, csr_frames
    from cfsr.methods.registry import get_method, resolve_params

    rng = np.random.default_rng(7)
    t, h, w = 700, 12, 24
    base = rng.uniform(0.02, 0.6, (h, w))
    wobble = 0.3 * np.sin(np.arange(t)[:, None, None] / 9.0 + np.arange(w)[None, None, :])
    rate = np.clip(base[None] * (1 + wobble * (np.arange(w) > 12)), 0, 1)
    # integrate-and-fire pixels (random phase), so the left half is steady and the right moves
    level = np.cumsum(rate, axis=0) + rng.random((h, w))
    s = np.diff(np.floor(level), axis=0, prepend=np.floor(level[:1] - rate[:1])).astype(np.uint8)
    lay = Layout(w, h)
    pk = pack_frames(s)
    p = resolve_params(get_method("csr"), params)
    for c in (0, 150, 350, 699):
        rates, masks, _ = csr_frames(s, [c], CsrSettings.of(p))
        r, m = csr_frame_packed(pk, lay, c, CsrSettings.of(p))
        np.testing.assert_array_equal(m, masks[0])
        np.testing.assert_array_equal(r, rates[0])
    assert masks[0].any() and not masks[0].all()


# -- run-time reconfiguration: all or nothing, memory follows the window (issue 12) ---------
def _random_packed(n, layout, seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (n, layout.frame_bytes), dtype=np.uint8)


def _same_output(a, b):
    return np.array_equal(a.rate, b.rate) and a.masks.keys() == b.masks.keys()


def test_rejected_window_leaves_the_reconstructor_running():
    """``window=1e9`` once stopped every frame for good: the method state was changed before
    the allocation that failed, and the next pushes broke on the stale capacity."""
    from cfsr.layout import DEFAULT_LAYOUT as lay

    data = _random_packed(2000, lay)
    rec = StreamingReconstructor("tfp", lay, slack=64)
    ref = StreamingReconstructor("tfp", lay, slack=64)
    rec.push(data[:1000], 0)
    ref.push(data[:1000], 0)
    with pytest.raises((ValueError, MemoryError)):
        rec.set_method("tfp", params={"window": 1_000_000_000})
    kept = (rec.method.name, rec.params, rec.before, rec.after)
    rec.push(data[1000:1200], 1000)  # still running on the old configuration
    ref.push(data[1000:1200], 1000)
    assert _same_output(rec.compute(1199), ref.compute(1199))
    rec.set_method("tfp", params={"window": 160})  # what a user does next
    rec.set_method("tfi", params={})  # or switches method
    ref.set_method("tfi", params={})
    for start in (1200, 1500):
        rec.push(data[start : start + 300], start)
        ref.push(data[start : start + 300], start)
        t = rec.latest_step()
        assert t == ref.latest_step() and _same_output(rec.compute(t), ref.compute(t))
    assert kept == ("tfp", {"window": 160, "mode": "trailing"}, 159, 0)


def test_allocation_failure_changes_nothing(monkeypatch):
    """A valid window whose buffer cannot be allocated (MemoryError) keeps the old method,
    parameters and history."""
    from cfsr.layout import Layout

    lay = Layout(width=32, height=24)
    data = _random_packed(1500, lay, seed=1)
    rec = StreamingReconstructor("tfp", lay, params={"window": 40}, slack=64)
    ref = StreamingReconstructor("tfp", lay, params={"window": 40}, slack=64)
    rec.push(data[:700], 0)
    ref.push(data[:700], 0)
    real_zeros = np.zeros

    def zeros(shape, *a, **k):  # the allocator refuses anything above 1 MB
        if int(np.prod(shape)) > 1 << 20:
            raise MemoryError("test: cannot allocate")
        return real_zeros(shape, *a, **k)

    monkeypatch.setattr(np, "zeros", zeros)
    with pytest.raises(MemoryError):
        rec.set_method("tfi", params={"max_isi": 20_000})
    monkeypatch.setattr(np, "zeros", real_zeros)
    assert rec.method.name == "tfp" and rec.params["window"] == 40
    assert (rec.first_step, rec.next_step) == (ref.first_step, ref.next_step)
    rec.push(data[700:], 700)
    ref.push(data[700:], 700)
    for t in (rec.latest_step() - 50, rec.latest_step()):
        assert _same_output(rec.compute(t), ref.compute(t))


def test_buffer_shrinks_back_after_a_large_window():
    """``window=100000`` took the worker from 362 MB to 2.8 GB, and it stayed there after
    reverting: the history buffer only ever grew. It now follows the window both ways."""
    import tracemalloc

    from cfsr.layout import DEFAULT_LAYOUT as lay

    data = _random_packed(600, lay, seed=2)
    tracemalloc.start()  # numpy reports its buffers to tracemalloc
    try:
        rec = StreamingReconstructor("tfp", lay, slack=256)
        rec.push(data, 0)
        base_traced = tracemalloc.get_traced_memory()[0]
        rec.set_method("tfp", params={"window": 40_000})  # valid, large: about 1 GB
        big_traced = tracemalloc.get_traced_memory()[0]
        rec.set_method("tfp", params={"window": 160})
        back_traced = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert big_traced - base_traced > 900e6
    assert back_traced - base_traced < 20e6  # given back (was: kept for good)
    assert rec.buffer_nbytes == 2 * (160 + 256) * lay.frame_bytes  # the baseline
    # the history that still fits was kept: the newest window needs no new data
    ref = StreamingReconstructor("tfp", lay, slack=256)
    ref.push(data, 0)
    t = rec.latest_step()
    assert t == ref.latest_step() == 599
    assert _same_output(rec.compute(t), ref.compute(t))


@pytest.mark.parametrize("block", [1, 64])
def test_recurrent_state_across_dense_outputs_equals_isolated_frames(block):
    """TFSTP's outputs one step apart continue one synapse state in the stream's memo; each
    equals the frame computed alone, and a gap in the stream forgets the state."""
    s = moving_scene()
    rec = SpikeRecording.from_array(s)
    params = SMALL["tfstp"]
    times = list(range(150, 420, 1))
    sr = StreamingReconstructor("tfstp", rec.layout, params=params, slack=block)
    blocks = ((a, rec.packed(a, a + block)) for a in range(0, len(rec), block))
    got = dict(sr.run(blocks, times))
    assert sr.memo  # the state was kept
    for t in times[::7] + [times[-1]]:
        alone = cfsr.reconstruct(s, "tfstp", [t], **params)[0]
        np.testing.assert_array_equal(got[t].rate, alone)
    sr.push(rec.packed(0, 10), 0)  # a jump back: the stream restarts
    assert sr.gaps == 1 and not sr.memo
