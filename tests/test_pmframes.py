"""The PatchMatch stage's frames (:mod:`cfsr.methods.cfsr.patchmatch_frames`) against the
stand-alone rules.

* ``pm_frames`` gives exactly the TFI rates of :func:`cfsr.methods.tfi.tfi_rates` and the TFA
  rates of :func:`cfsr.methods.tfa.adaptive_rates` (guide before smoothing), on random windows
  mixing bright, dark, silent, single-spike, edge-only and bursting pixels, with the
  PatchMatch centers (``t`` and ``t +- 3 i``) or random ones, clipped and unclipped ranges.
* Its per-pixel fast path (every center's interval and TFA span inside its range) and the
  rule-as-written path agree: a pixel gives the same rates alone or among any neighbours.
* :func:`cfsr.methods.tfa.grow_span` (branchless merge where spikes lie on both sides) picks
  the same span as growing one interval at a time.
"""

from __future__ import annotations

import numpy as np
import pytest

from cfsr._words import PackedWindow
from cfsr.methods.cfsr.patchmatch_frames import pm_frames
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.registry import get_method, resolve_params
from cfsr.methods.tfa import adaptive_rates, grow_span
from cfsr.methods.tfi import tfi_rates


def _params(**kw):
    return resolve_params(get_method("cfsr"), {"pm_sigma": 0.0, **kw})


def _mixed_window(rng, n, h, w):
    """Random rates per pixel, plus pixels that are silent, always firing, with one or two
    spikes, spikes only at the window's ends, or bursts in silence."""
    rate = rng.uniform(0.0, 1.0, (1, h, w)) ** 2
    s = (rng.random((n, h, w)) < rate).astype(np.uint8)
    for _ in range(h * w // 3):
        y, x = int(rng.integers(0, h)), int(rng.integers(0, w))
        kind = int(rng.integers(0, 6))
        s[:, y, x] = 0
        if kind == 1:
            s[:, y, x] = 1
        elif kind == 2:
            s[rng.integers(0, n, int(rng.integers(1, 3))), y, x] = 1
        elif kind == 3:
            s[: int(rng.integers(1, 4)), y, x] = 1
            s[n - int(rng.integers(1, 4)) :, y, x] = 1
        elif kind == 4:
            a = int(rng.integers(0, n))
            s[a : a + int(rng.integers(1, 12)), y, x] = 1
        elif kind == 5:
            s[rng.integers(0, n, int(rng.integers(3, 9))), y, x] = 1
    return s


def _centers(rng, n):
    if rng.random() < 0.6:  # the PatchMatch centers: t first, then t -+ 3 i inside the window
        t = int(rng.integers(0, n))
        cs = [t] + [c for i in range(1, 17) for c in (t - 3 * i, t + 3 * i) if 0 <= c < n]
    else:
        cs = [int(c) for c in rng.integers(0, n, int(rng.integers(1, 12)))]
    return cs


def _check(s, cs, box, p, tiles=None):
    raw, guide = pm_frames(PackedWindow.from_frames(s), cs, box, CfsrSettings.of(p), tiles)
    crop = np.ascontiguousarray(s[:, box[0] : box[1], box[2] : box[3]])
    want = tfi_rates(crop, cs, max_isi=p["max_isi"])
    np.testing.assert_array_equal(raw, want)
    if p["pm_guide"] > 0:
        g = adaptive_rates(crop, cs, threshold=p["pm_guide"], max_window=p["max_isi"])
    else:
        g = want.copy()
    if p["pm_sigma"] > 0:
        import cv2

        for k in range(g.shape[0]):
            g[k] = cv2.GaussianBlur(g[k], (0, 0), float(p["pm_sigma"]))
    np.testing.assert_array_equal(guide, g)
    return raw, guide


@pytest.mark.parametrize("trial", range(6))
def test_pm_frames_equal_tfi_and_tfa_then_the_gaussian_guide(trial):
    """With the default Gaussian (sigma 1) on the guides, centers in any order, a narrow box
    or one across numba's row chunks."""
    rng = np.random.default_rng(100 + trial)
    n = int(rng.integers(40, 500))
    rate = rng.uniform(0.01, 0.95, (1, 14, 170))
    s = (rng.random((n, 14, 170)) < rate).astype(np.uint8)
    p = _params(max_isi=int(rng.integers(1, 150)), pm_guide=(0, 1, 3, 8)[trial % 4], pm_sigma=1.0)
    cs = sorted({int(x) for x in rng.integers(0, n, int(rng.integers(1, 12)))})
    rng.shuffle(cs)
    box = (2, 11, 3, 15) if trial % 2 else (1, 13, 5, 160)
    _check(s, cs, box, p)


@pytest.mark.parametrize("trial", range(12))
def test_pm_frames_equal_tfi_and_tfa_on_mixed_pixels(trial):
    rng = np.random.default_rng(700 + trial)
    n = int(rng.integers(20, 700))
    h, w = 12, (20, 90)[trial % 2]
    s = _mixed_window(rng, n, h, w)
    p = _params(
        max_isi=int(rng.integers(1, 260)),
        pm_guide=(0, 1, 2, 3, 3, 8)[trial % 6],
    )
    box = (int(rng.integers(0, 3)), h - int(rng.integers(0, 3)), int(rng.integers(0, 5)), w)
    _check(s, _centers(rng, n), box, p)


@pytest.mark.parametrize("guide", [1, 3, 5])
def test_pm_frames_same_rates_alone_or_among_neighbours(guide):
    """A bright pixel (fast path) next to dark ones (rules as written) in one row, and each
    of them alone: the same numbers."""
    rng = np.random.default_rng(guide)
    n = 500
    s = np.zeros((n, 1, 5), np.uint8)
    s[:, 0, 0] = rng.random(n) < 0.4  # bright: every center's span inside its range
    s[::97, 0, 1] = 1  # dark: few spikes per range
    s[250, 0, 2] = 1  # one spike
    s[240:262, 0, 3] = 1  # a burst at the centers, silence around
    s[:, 0, 4] = rng.random(n) < 0.05
    p = _params(max_isi=60, pm_guide=guide)
    cs = [250] + [c for i in range(1, 17) for c in (250 - 3 * i, 250 + 3 * i)]
    raw, g = _check(s, cs, (0, 1, 0, 5), p)
    for x in range(5):
        one = np.ascontiguousarray(s[:, :, x : x + 1])
        r1, g1 = _check(one, cs, (0, 1, 0, 1), p)
        np.testing.assert_array_equal(r1[:, 0, 0], raw[:, 0, x])
        np.testing.assert_array_equal(g1[:, 0, 0], g[:, 0, x])


def _grow_one_by_one(times, f0, f1, ip, c, n_int):
    """The rule as stated: from the interval containing c, add the closer neighbour."""
    if ip < f0:
        a, b = f0, f0 + 1
    elif ip >= f1 - 1:
        a, b = f1 - 2, f1 - 1
    else:
        a, b = ip, ip + 1
    while b - a < n_int:
        can_l, can_r = a > f0, b < f1 - 1
        if can_l and (not can_r or c - times[a - 1] <= times[b + 1] - c):
            a -= 1
        elif can_r:
            b += 1
        else:
            break
    return a, b


def test_grow_span_equals_growing_one_interval_at_a_time():
    rng = np.random.default_rng(9)
    for _ in range(3000):
        ns = int(rng.integers(2, 30))
        # ties are common: small steps, repeated gaps
        times = np.sort(rng.choice(int(rng.integers(ns, 4 * ns)), ns, replace=False)).astype(
            np.int64
        )
        f0 = int(rng.integers(0, ns - 1))
        f1 = int(rng.integers(f0 + 2, ns + 1))
        c = int(rng.integers(times[f0] - 3, times[f1 - 1] + 4))  # also outside the spikes
        ip = int(np.searchsorted(times, c, side="right")) - 1
        n_int = int(rng.integers(1, 12))
        assert tuple(grow_span(times, f0, f1, ip, c, n_int)) == _grow_one_by_one(
            times, f0, f1, ip, c, n_int
        )


def _blur_in_child(q) -> None:
    from cfsr.methods.cfsr.patchmatch_frames import _blur_pool

    q.put(_blur_pool().submit(lambda: 41 + 1).result(timeout=20))


@pytest.mark.skipif(
    "fork" not in __import__("multiprocessing").get_all_start_methods(),
    reason="needs the fork start method (POSIX)",
)
def test_blur_threads_work_in_a_forked_child():
    """A child forked after the guides were blurred gets a fresh pool (the parent's threads
    do not survive the fork, and jobs on the inherited pool would never run)."""
    import multiprocessing as mp

    from cfsr.methods.cfsr.patchmatch_frames import _blur_pool

    assert _blur_pool().submit(lambda: 1).result(timeout=20) == 1  # the parent's threads exist
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    proc = ctx.Process(target=_blur_in_child, args=(q,))
    proc.start()
    try:
        assert q.get(timeout=30) == 42
    finally:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.kill()
