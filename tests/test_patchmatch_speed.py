"""PatchMatch's temporal schedule (``offsets_steps``): predictions from the nearer targets.

* Under a global linear motion, every target's NNF is the exact displacement.
* The result does not depend on the number of threads, and a crop matches the whole frame.
* ``nnf_multi`` is the two entry points ``nnf_independent`` / ``nnf_temporal``, picked by
  ``offsets_steps``.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from cfsr.methods.cfsr.patchmatch import nnf_independent, nnf_multi, nnf_temporal, patchmatch_fuse


def _texture(h, w, seed=0):
    import cv2

    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.2)


def _moving(steps, v, h=90, w=120, pad=40, seed=0):
    """Frames of a texture translating by ``v`` pixels per step, sampled at ``steps``."""
    big = _texture(h + 2 * pad, w + 2 * pad, seed)
    ref = big[pad : pad + h, pad : pad + w]
    tg = []
    for s in steps:
        dy, dx = round(v[0] * s), round(v[1] * s)
        # content at (y, x) of ref sits at (y + dy, x + dx) of the frame at step s
        tg.append(big[pad - dy : pad - dy + h, pad - dx : pad - dx + w])
    return ref, np.stack(tg)


def _steps(step=3, count=8):
    return [v for i in range(1, count + 1) for v in (-step * i, step * i)]


def test_temporal_schedule_tracks_a_linear_motion_exactly():
    steps = _steps()
    ref, tg = _moving(steps, v=(1 / 3, -2 / 3))  # whole-pixel steps: (i, -2i) at 3i
    mask = np.zeros(ref.shape, bool)
    mask[30:60, 40:80] = True
    ys, xs, off, cost = nnf_multi(
        ref, tg, mask, iters=2, max_radius=8, seed=1, offsets_steps=steps, near_radius=2
    )
    for k, s in enumerate(steps):
        want = (round(s / 3), round(-2 * s / 3))
        hit = (off[k, :, 0] == want[0]) & (off[k, :, 1] == want[1])
        # the largest displacement (16 px) is beyond the near search of 2 px: only the
        # predictions can get there
        assert hit.mean() > 0.99, (s, want, hit.mean())
    assert np.all(cost >= 0)


def test_temporal_schedule_is_thread_independent_and_crop_invariant():
    steps = _steps(count=6)[:-1]  # an unpaired target at the end is allowed
    ref, tg = _moving(steps, v=(0.4, 0.3), seed=4)
    rng = np.random.default_rng(2)
    ref = ref + 0.02 * rng.standard_normal(ref.shape).astype(np.float32)
    mask = np.zeros(ref.shape, bool)
    mask[35:58, 45:80] = rng.random((23, 35)) < 0.8
    kw = dict(iters=2, max_radius=8, seed=2**40 + 3, offsets_steps=steps, band=5)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = patchmatch_fuse(ref, ref, tg, tg, mask, **kw)
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = patchmatch_fuse(ref, ref, tg, tg, mask, **kw)
    finally:
        numba.set_num_threads(before)
    assert np.array_equal(one, two)
    # a crop around the mask, far enough from its borders that no search reaches them
    y0, x0 = 2, 6
    crop = patchmatch_fuse(
        ref[y0:, x0:],
        ref[y0:, x0:],
        tg[:, y0:, x0:],
        tg[:, y0:, x0:],
        mask[y0:, x0:],
        origin=(y0, x0),
        **kw,
    )
    np.testing.assert_array_equal(crop[mask[y0:, x0:]], one[mask])
    # the plain schedule is still there and differs (another search)
    plain = patchmatch_fuse(ref, ref, tg, tg, mask, iters=2, max_radius=8, seed=2**40 + 3)
    assert not np.array_equal(plain, one)


@pytest.fixture(scope="module")
def block_ssd():
    from numba import njit

    from cfsr._simd import Lanes, box6x8_min

    @njit
    def run(ref, tgt, y, x, ty, tx, cy, cx, bc, boy, box):
        w = ref.shape[1]
        box6x8_min(ref, tgt, y * w + x, ty * w + tx, w, cy, cx, Lanes(bc, boy, box))

    rng = np.random.default_rng(5)
    ref = rng.random((30, 40)).astype(np.float32)
    tgt = rng.random((30, 40)).astype(np.float32)
    want = [((ref[4:10, 7 + k : 13 + k] - tgt[9:15, 11 + k : 17 + k]) ** 2).sum() for k in range(8)]
    return run, ref, tgt, np.array(want, np.float32)


def test_block_ssd_matches_numpy(block_ssd):
    run, ref, tgt, want = block_ssd
    bc = np.full(8, np.inf, np.float32)  # every lane takes the new SSD
    run(ref, tgt, 4, 7, 9, 11, 0, 0, bc, np.zeros(8, np.int32), np.zeros(8, np.int32))
    np.testing.assert_allclose(bc, want, rtol=1e-5)


def test_temporal_schedule_other_patch_sizes():
    # patch sizes other than 6 take the generic (scalar) block path
    steps = _steps(count=4)
    ref, tg = _moving(steps, v=(1 / 3, 1 / 3), seed=3)
    mask = np.zeros(ref.shape, bool)
    mask[30:60, 40:80] = True
    for patch in (3, 7):
        ys, xs, off, cost = nnf_multi(
            ref, tg, mask, patch=patch, iters=2, max_radius=8, offsets_steps=steps
        )
        for k, s in enumerate(steps):
            hit = (off[k, :, 0] == round(s / 3)) & (off[k, :, 1] == round(s / 3))
            assert hit.mean() > 0.99, (patch, s, hit.mean())


def test_block_ssd_min_keeps_the_lane_bests(block_ssd):
    run, ref, tgt, want = block_ssd
    bc = np.full(8, np.inf, np.float32)
    bc[::2] = 0.0  # lanes already better than any SSD keep their offsets
    boy = np.full(8, -7, np.int32)
    box = np.full(8, 9, np.int32)
    run(ref, tgt, 4, 7, 9, 11, 5, 4, bc, boy, box)
    np.testing.assert_allclose(bc, np.where(np.arange(8) % 2 == 0, 0.0, want), rtol=1e-5)
    np.testing.assert_array_equal(boy, np.where(np.arange(8) % 2 == 0, -7, 5))
    np.testing.assert_array_equal(box, np.where(np.arange(8) % 2 == 0, 9, 4))


def test_nnf_multi_dispatches_to_the_two_entry_points():
    steps = _steps(count=3)
    ref, tg = _moving(steps, v=(1 / 3, -1 / 3), seed=6)
    mask = np.zeros(ref.shape, bool)
    mask[30:50, 40:70] = True
    kw = dict(iters=2, max_radius=8, seed=9, origin=(3, 5))
    for got, want in (
        (nnf_multi(ref, tg, mask, **kw), nnf_independent(ref, tg, mask, **kw)),
        (
            nnf_multi(ref, tg, mask, offsets_steps=steps, band=7, **kw),
            nnf_temporal(ref, tg, mask, steps, band=7, **kw),
        ),
    ):
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="offsets_steps"):
        nnf_temporal(ref, tg, mask, steps[:-1])


def test_the_temporal_search_reads_padded_guides_as_it_reads_its_own_copy():
    # CFSR writes its guides straight into the buffer the search reads (padded_guides,
    # finish_padding): the matches must be the ones of the search's own padded copy
    from cfsr.methods.cfsr.patchmatch import finish_padding, padded_guides

    rng = np.random.default_rng(11)
    n, h, w = 5, 37, 53
    frames = rng.random((n + 1, h, w), dtype=np.float32)
    mask = rng.random((h, w)) < 0.3
    steps = [-3, 3, -6, 6, -9]
    for patch in (3, 6):
        want = nnf_temporal(frames[0], frames[1:], mask, steps, patch=patch, seed=4)
        buf, view = padded_guides(n + 1, h, w, patch)
        view[...] = frames
        finish_padding(buf, patch)
        got = nnf_temporal(view[0], view[1:], mask, steps, patch=patch, seed=4, padded=buf)
        for a, b in zip(want, got, strict=True):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="padded guides"):
        nnf_temporal(frames[0], frames[1:], mask, steps, patch=6, padded=buf[:, :-1])


@pytest.mark.parametrize(("patch", "temporal"), [(6, True), (3, True), (6, False)])
def test_a_patch_that_reads_nan_is_never_a_match(patch, temporal):
    # CFSR computes guides only on the tiles near the fine mask and leaves NaN elsewhere
    # (pm_frames): a NaN SSD must lose to every finite one, so no match reads the NaN area
    steps = _steps(count=6)
    ref, tg = _moving(steps, v=(0.0, 1 / 3))  # content at x sits at x + s/3 at step s
    tg = tg.copy()
    tg[:, :, 86:] = np.nan
    mask = np.zeros(ref.shape, bool)
    mask[30:60, 40:80] = True
    kw = {"offsets_steps": steps} if temporal else {}
    ys, xs, off, cost = nnf_multi(ref, tg, mask, patch=patch, iters=2, max_radius=8, seed=3, **kw)
    assert not np.isnan(cost).any()  # a match has a finite cost, no match an infinite one
    found = np.isfinite(cost)
    assert found.mean() > 0.95
    lo = (patch - 1) // 2
    h, w = ref.shape
    for k, s in enumerate(steps):
        ty = np.clip(ys + off[k, :, 0], 0, h - 1)
        tx = np.clip(xs + off[k, :, 1], 0, w - 1)
        for j in np.flatnonzero(found[k])[::7]:  # the matched patch holds no NaN
            win = tg[
                k, max(0, ty[j] - lo) : ty[j] - lo + patch, max(0, tx[j] - lo) : tx[j] - lo + patch
            ]
            assert np.isfinite(win).all(), (s, ys[j], xs[j])
        if temporal and patch == 6:  # where the true match is clear of the NaN, it is found
            clear = xs + round(s / 3) + patch - lo <= 86
            want = (off[k, :, 0] == 0) & (off[k, :, 1] == round(s / 3))
            assert want[clear].mean() > 0.99, (s, want[clear].mean())
    fused = patchmatch_fuse(
        ref, ref, tg, tg, mask, patch=patch, iters=2, max_radius=8, seed=3, **kw
    )
    # the average of the reference and the targets that have a match
    ty = np.clip(ys + off[..., 0], 0, h - 1)
    tx = np.clip(xs + off[..., 1], 0, w - 1)
    vals = np.where(found, tg[np.arange(len(steps))[:, None], ty, tx], 0.0)
    want = (ref[ys, xs] + vals.sum(axis=0)) / (1 + found.sum(axis=0))
    np.testing.assert_allclose(fused[ys, xs], want, rtol=1e-5)


def test_fusion_of_the_wanted_pixels_only_gives_their_full_fusion_values():
    # CFSR matches the still pixels it leaves out (they carry the propagation) but uses
    # only the other pixels' averages: those must be the averages of the full fusion
    from cfsr.methods.cfsr.patchmatch import fuse_matches

    steps = _steps(count=4)
    ref, tg = _moving(steps, v=(0.3, -0.2), seed=2)
    mask = np.zeros(ref.shape, bool)
    mask[20:70, 30:90] = True
    matches = nnf_multi(ref, tg, mask, iters=2, max_radius=8, seed=5, offsets_steps=steps)
    ys, xs = matches[:2]
    wanted = np.random.default_rng(1).random(ys.size) < 0.5
    for h in (0.0, 0.05):
        full = fuse_matches(ref, tg, matches, h=h)
        part = fuse_matches(ref, tg, matches, h=h, wanted=wanted)
        np.testing.assert_array_equal(part[wanted], full[wanted])
        np.testing.assert_array_equal(part[~wanted], ref[ys[~wanted], xs[~wanted]])
    with pytest.raises(ValueError, match="wanted"):
        fuse_matches(ref, tg, matches, wanted=wanted[:-1])
    # patchmatch_fuse takes the same choice as an image
    img = np.zeros(ref.shape, bool)
    img[ys[wanted], xs[wanted]] = True
    kw = {"iters": 2, "max_radius": 8, "seed": 5, "offsets_steps": steps}
    got = patchmatch_fuse(ref, ref, tg, tg, mask, wanted=img, **kw)
    want = patchmatch_fuse(ref, ref, tg, tg, mask, **kw)
    np.testing.assert_array_equal(got[img], want[img])
    np.testing.assert_array_equal(got[mask & ~img], ref[mask & ~img])
