"""The vector kernel of PatchMatch's block search (:mod:`cfsr._simd`) against its numba twin.

* ``box6x8_min`` (LLVM IR) and ``box6x8_min_numba`` give bit-identical lane bests (SSD and
  offset) on random images, positions, offsets and running bests, including NaN lanes and
  ties; they perform the same float32 operations in the same order, so equality is exact.
* PatchMatch's temporal schedule gives the same fields with either (``CFSR_SIMD`` / ``ENABLED``).
"""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from cfsr import _simd
from cfsr._simd import LANES, PATCH, READ_COLS, Lanes, box6x8_min, box6x8_min_numba


@njit
def _both(ref, tgt, rb, tb, stride, cy, cx, a, b, cols):
    box6x8_min(ref, tgt, rb, tb, stride, cy, cx, a)
    box6x8_min_numba(ref, tgt, rb, tb, stride, cy, cx, b, cols)


def _lanes(cost):
    return Lanes(cost.copy(), np.full(LANES, -3, np.int32), np.full(LANES, 5, np.int32))


@pytest.mark.parametrize("seed", range(4))
def test_intrinsic_and_numba_twin_agree_exactly(seed):
    rng = np.random.default_rng(seed)
    h, w = 24, 41
    scale = (1.0, 1e-3, 1e3, 0.5)[seed]
    ref = (rng.random((h, w)) * scale).astype(np.float32)
    tgt = (rng.random((h, w)) * scale).astype(np.float32)
    if seed == 3:  # coarse values: many equal SSDs (ties keep the old best)
        ref = np.round(ref * 4) / 4
        tgt = np.round(tgt * 4) / 4
    cols = np.empty(READ_COLS, np.float32)
    for _ in range(400):
        y, ty = rng.integers(0, h - PATCH + 1, 2)
        x, tx = rng.integers(0, w - READ_COLS + 1, 2)
        cy, cx = (int(v) for v in rng.integers(-40, 40, 2))
        kind = rng.integers(0, 4)
        if kind == 0:
            cost = np.full(LANES, np.inf, np.float32)  # every lane takes the new SSD
        elif kind == 1:
            cost = np.zeros(LANES, np.float32)  # none does
        else:  # some do; a NaN best is never replaced (ordered compare)
            cost = (rng.random(LANES) * 6 * scale * scale).astype(np.float32)
            if kind == 3:
                cost[rng.integers(0, LANES)] = np.nan
        a, b = _lanes(cost), _lanes(cost)
        _both(ref, tgt, y * w + x, ty * w + tx, w, cy, cx, a, b, cols)
        for u, v in zip(a, b, strict=True):
            np.testing.assert_array_equal(u, v)
        # and both are the SSDs (float32 sums: to rounding)
        if kind == 0:
            want = [
                (
                    (
                        ref[y : y + PATCH, x + k : x + k + PATCH]
                        - tgt[ty : ty + PATCH, tx + k : tx + k + PATCH]
                    )
                    ** 2
                ).sum()
                for k in range(LANES)
            ]
            np.testing.assert_allclose(a.cost, want, rtol=1e-5)
            assert np.all(a.dy == cy) and np.all(a.dx == cx)


def test_temporal_schedule_is_the_same_with_the_numba_twin(monkeypatch):
    import cv2

    from cfsr.methods.cfsr.patchmatch import nnf_temporal

    rng = np.random.default_rng(11)
    big = cv2.GaussianBlur(rng.random((110, 140)).astype(np.float32), (0, 0), 1.2)
    ref = big[10:90, 10:120]
    steps = [v for i in range(1, 5) for v in (-3 * i, 3 * i)]
    tg = np.stack([big[10 - s // 3 : 90 - s // 3, 10 + s // 2 : 120 + s // 2] for s in steps])
    tg = tg + 0.01 * rng.standard_normal(tg.shape).astype(np.float32)
    mask = rng.random(ref.shape) < 0.6
    out = []
    for on in (True, False):
        monkeypatch.setattr(_simd, "ENABLED", on)
        out.append(nnf_temporal(ref, tg, mask, steps, seed=4, origin=(2, 3)))
    for u, v in zip(*out, strict=True):
        np.testing.assert_array_equal(u, v)


def test_the_python_stub_is_not_callable():
    with pytest.raises(NotImplementedError):
        _simd.box6x8_update(True, None, None, 0, 0, 0, 0, 0, None, None)
