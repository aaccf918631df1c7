"""Streaming per-pixel state from packed bytes equals a reference computed on unpacked spikes."""

from __future__ import annotations

import numpy as np
import pytest

from cfsr import Layout
from cfsr._bits import pack_frames
from cfsr.pixelstate import PixelState


@pytest.mark.parametrize("block", [1, 37, 255, 256, 600])
@pytest.mark.parametrize("layout", [Layout(64, 10), Layout(64, 10, head_cols=8, fliplr=True)])
def test_state_matches_reference(block, layout):
    rng = np.random.default_rng(block)
    t, h, w = 700, layout.height, layout.width
    rate = rng.uniform(0.0, 0.7, (h, w))
    rate[0, :5] = 0  # never fire
    rate[1, :5] = 1  # fire every step
    fr = (rng.random((t, h, w)) < rate).astype(np.uint8)
    stored = fr
    if layout.head_cols:
        # head columns sit at the right of the stored row; with fliplr the image is mirrored
        # within the first `width` columns, so pad on the side that mirroring moves right
        head = np.ones((t, h, layout.head_cols), np.uint8)
        parts = [head, fr] if layout.fliplr else [fr, head]
        stored = np.concatenate(parts, axis=2)
    pk = pack_frames(stored, flipud=layout.flipud, fliplr=layout.fliplr)
    base = 2**35  # absolute step indices past 2^32
    ps = PixelState(layout)
    for a in range(0, t, block):
        ps.update(pk[a : a + block], base + a)
    assert ps.steps == t and ps.next_step == base + t
    np.testing.assert_array_equal(ps.image(ps.count), fr.sum(0))
    last, isi = ps.image(ps.last), ps.image(ps.isi)
    for y in range(h):
        for x in range(w):
            ts = np.nonzero(fr[:, y, x])[0]
            assert last[y, x] == (base + ts[-1] if len(ts) else -1)
            assert isi[y, x] == (ts[-1] - ts[-2] if len(ts) > 1 else 0)
    r = ps.tfi_rate()
    assert np.all(np.isfinite(r)) and r.dtype == np.float32
    np.testing.assert_allclose(r[1, :5], 1.0)
    np.testing.assert_array_equal(r[0, :5], 0.0)
    np.testing.assert_allclose(ps.mean_rate(), fr.mean(0), rtol=1e-6)
