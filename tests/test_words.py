"""Pixel-major spike words (cfsr._words) against the unpacked frames."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from cfsr._bits import pack_frames
from cfsr._words import geometry, popcount, row_words, transpose64, word_times
from cfsr.layout import Layout


@njit(cache=True)
def _all_times(packed, geo, lo, hi, h, w, x0, x1):
    nw = (hi - lo + 63) // 64
    words = np.zeros(((x1 - x0 + 80), nw), np.uint64)
    out = np.full((h, x1 - x0, hi - lo + 1), -1, np.int64)
    counts = np.zeros((h, x1 - x0), np.int64)
    times = np.empty(hi - lo + 1, np.int64)
    for y in range(h):
        base, step = row_words(packed, geo, lo, hi, y, x0, x1, words)
        for x in range(x0, x1):
            k = base + step * (x - x0)
            ns = word_times(words, k, nw, lo, times)
            out[y, x - x0, :ns] = times[:ns]
            c = 0
            for q in range(nw):
                c += popcount(words[k, q])
            counts[y, x - x0] = c
    return out, counts


def _reference(frames, lo, hi, x0, x1):
    n, h, w = frames.shape
    out = np.full((h, x1 - x0, hi - lo + 1), -1, np.int64)
    for y in range(h):
        for x in range(x0, x1):
            t = np.nonzero(frames[lo:hi, y, x])[0] + lo
            out[y, x - x0, : t.size] = t
    return out


@njit(cache=True)
def _transposed(a):
    b = a.copy()
    transpose64(b)
    return b


def test_transpose64_moves_bit_j_of_word_r_to_bit_r_of_word_j():
    rng = np.random.default_rng(0)
    bits = rng.random((64, 64)) < 0.5
    a = np.array([sum(int(bits[r, j]) << j for j in range(64)) for r in range(64)], np.uint64)
    b = _transposed(a)
    got = np.array([[(int(b[j]) >> r) & 1 for r in range(64)] for j in range(64)], bool)
    np.testing.assert_array_equal(got, bits.T)


@pytest.mark.parametrize(
    "layout",
    [
        Layout(40, 6),
        Layout(37, 8, flipud=False),  # rows start mid-byte
        Layout(36, 6, head_cols=4, fliplr=True),
    ],
)
@pytest.mark.parametrize("lo,hi,x0,x1", [(0, 200, 0, None), (13, 141, 3, 21), (70, 71, 5, 6)])
def test_row_words_give_each_pixels_spike_times(layout, lo, hi, x0, x1):
    rng = np.random.default_rng(1)
    n = 200
    frames = (rng.random((n, layout.height, layout.width)) < 0.3).astype(np.uint8)
    x1 = layout.width if x1 is None else x1
    stored = np.zeros((n, layout.height, layout.stored_width), np.uint8)
    img = frames[:, ::-1] if layout.flipud else frames
    img = img[:, :, ::-1] if layout.fliplr else img
    stored[:, :, : layout.width] = img
    packed = pack_frames(stored.reshape(n, 1, -1), flipud=False).reshape(n, -1)
    got, counts = _all_times(packed, geometry(layout), lo, hi, layout.height, layout.width, x0, x1)
    want = _reference(frames, lo, hi, x0, x1)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(counts, frames[lo:hi, :, x0:x1].sum(axis=0))


@pytest.mark.parametrize("trial", range(6))
def test_distinct_counts_from_packed_words_equal_the_unpacked_kernel(trial):
    from cfsr.methods.cfsr.distinction import distinct_isi_counts, distinct_isi_counts_packed

    rng = np.random.default_rng(50 + trial)
    layout = Layout(72, 5, flipud=bool(trial % 2), fliplr=trial == 3, head_cols=8 * (trial == 4))
    n = int(rng.integers(50, 900))
    # bright, mid and very dark pixels: ISIs below and above 64 steps, dense and sparse words
    rate = rng.choice([0.9, 0.4, 0.1, 0.02, 0.004], (1, layout.height, layout.width))
    frames = (rng.random((n, layout.height, layout.width)) < rate).astype(np.uint8)
    stored = np.zeros((n, layout.height, layout.stored_width), np.uint8)
    img = frames[:, ::-1] if layout.flipud else frames
    stored[:, :, : layout.width] = img[:, :, ::-1] if layout.fliplr else img
    packed = pack_frames(stored.reshape(n, 1, -1), flipud=False).reshape(n, -1)
    for _ in range(4):
        end = int(rng.integers(0, n))
        span = int(rng.integers(1, 400))
        got = distinct_isi_counts_packed(packed, layout, end, span)
        np.testing.assert_array_equal(got, distinct_isi_counts(frames, [end], span)[0])
