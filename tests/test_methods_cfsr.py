"""Units of the CFSR pipeline: ISI-set distinction, ATSR, MOG, DAISI, PatchMatch, CSR, CFSR."""

from __future__ import annotations

import numpy as np
import pytest

import cfsr
from cfsr.methods.cfsr.atsr import atsr_alpha, atsr_fuse, atsr_fuse_isi
from cfsr.methods.cfsr.daisi import daisi_edges, daisi_strength
from cfsr.methods.cfsr.distinction import coarse_masks, distinct_isi_counts
from cfsr.methods.cfsr.fine_mask import fine_mask
from cfsr.methods.cfsr.mog import mog_background, mog_objects, to_u8
from cfsr.methods.cfsr.patchmatch import nnf_multi, patchmatch_fuse


def if_spikes(intensity, steps, *, gain=0.5, v0=None, seed=0):
    """Integrate-and-fire spikes of a static ``(H, W)`` intensity (or ``(T, H, W)`` video)."""
    inten = np.asarray(intensity, np.float64)
    shape = inten.shape[-2:]
    rng = np.random.default_rng(seed)
    v = rng.random(shape) if v0 is None else np.full(shape, float(v0))
    out = np.zeros((steps,) + shape, np.uint8)
    for t in range(steps):
        v += gain * (inten[t] if inten.ndim == 3 else inten)
        s = v >= 1.0
        v -= s
        out[t] = s
    return out


def moving_bars(steps=700, h=24, w=48, speed=0.25, seed=0, video=False):
    """A textured band sliding right across a static textured background; returns spikes and
    the true moving-pixel mask at every step (and the intensity video if asked)."""
    import cv2

    rng = np.random.default_rng(seed)
    bg = 0.2 + 0.6 * rng.random((h, w))
    tex = cv2.GaussianBlur(rng.random((h // 2, 2 * w)), (0, 0), 1.5)  # natural-ish texture
    tex = 0.1 + 0.9 * (tex - tex.min()) / (tex.max() - tex.min())
    frames = np.empty((steps, h, w))
    mask = np.zeros((steps, h, w), bool)
    for t in range(steps):
        frames[t] = bg
        off = int(speed * t)
        frames[t, h // 4 : h // 4 + h // 2] = np.roll(tex, off, axis=1)[:, :w]
        mask[t, h // 4 : h // 4 + h // 2] = True
    spikes = if_spikes(frames, steps, seed=seed)
    return (spikes, mask, frames) if video else (spikes, mask)


def brute_distinct(col, e, span):
    times = [t for t in range(max(0, e - span + 1), e + 1) if col[t]]
    return len({b - a for a, b in zip(times, times[1:], strict=False)})


# --------------------------------------------------------------------------- distinction


def test_distinct_counts_match_brute_force():
    rng = np.random.default_rng(1)
    s = (rng.random((260, 3, 5)) < rng.uniform(0.05, 0.8, (3, 5))).astype(np.uint8)
    ends = [259, 0, 5, 100, 101, 180]
    for span in (1, 7, 50, 300):
        got = distinct_isi_counts(s, ends, span)
        for k, e in enumerate(ends):
            want = [[brute_distinct(s[:, y, x], e, span) for x in range(5)] for y in range(3)]
            assert np.array_equal(got[k], want), (span, e)


def test_bright_static_pixel_is_static_and_moving_texture_dynamic():
    # Eq. 5-6 read literally: a static pixel of ANY brightness alternates between <= 2 ISIs.
    levels = np.linspace(0.02, 1.0, 40).reshape(4, 10)
    s = if_spikes(levels, 400)
    counts = distinct_isi_counts(s, [399], 300)[0]
    assert counts.max() <= 2
    assert not coarse_masks(s, [399], 300, 3).any()
    spikes, mask = moving_bars(steps=400)
    m = coarse_masks(spikes, [399], 300, 3)[0]
    assert not m[~mask[399]].any()
    assert m[mask[399]].mean() > 0.5


def test_distinct_counts_argument_checks():
    s = np.zeros((10, 2, 2), np.uint8)
    with pytest.raises(ValueError, match="span T must be >= 1"):
        distinct_isi_counts(s, [3], 0)
    with pytest.raises(ValueError, match="outside the window"):
        distinct_isi_counts(s, [10], 5)
    assert distinct_isi_counts(s, [], 5).shape == (0, 2, 2)


# --------------------------------------------------------------------------- ATSR


def test_atsr_scale_and_guards():
    tfi = np.full((4, 4), 0.3, np.float32)
    tfp = np.full((4, 4), 0.2, np.float32)
    mask = np.zeros((4, 4), bool)
    mask[0] = True
    out, alpha = atsr_fuse(tfi, tfp, mask)
    assert alpha == pytest.approx(1.5)
    np.testing.assert_allclose(out, 0.3, rtol=1e-6)
    # empty static region -> alpha 1, the dynamic values everywhere
    out, alpha = atsr_fuse(tfi, tfp, np.ones((4, 4), bool))
    assert alpha == 1.0 and np.allclose(out, 0.3)
    # empty dynamic region -> plain scaled TFP
    out, alpha = atsr_fuse(tfi, tfp, np.zeros((4, 4), bool))
    assert np.allclose(out, 0.3)
    # zero TFP, NaN inputs, huge ratios: finite, bounded
    assert atsr_alpha(tfi, np.zeros((4, 4)), ~mask) == 1.0
    assert atsr_alpha(np.zeros((4, 4)), tfp, ~mask) == 1.0
    assert atsr_alpha(tfi * 100, tfp, ~mask) == 4.0
    bad = tfi.copy()
    bad[1, 1] = np.nan
    out, alpha = atsr_fuse(bad, tfp, mask)
    assert alpha == 1.0 and np.isfinite(out).all() and out.max() <= 1.0


def test_atsr_of_a_stack_from_intervals_equals_atsr_fuse_frame_by_frame():
    rng = np.random.default_rng(7)
    k, h, w = 6, 9, 11
    isi = rng.integers(1, 300, (k, h, w)).astype(np.int32)
    isi[1] = 1  # every TFI 1: the clip at 1 spike/step
    tfp = rng.random((k, h, w)).astype(np.float32) * 0.8
    tfp[2] = 0.0  # dark static region: scale 1
    mask = rng.random((k, h, w)) < 0.3
    mask[3] = False  # no dynamic pixel: the TFP itself
    mask[4] = True  # no static pixel: scale 1
    got = atsr_fuse_isi(isi, tfp, mask)
    for j in range(k):
        if mask[j].any():
            want = atsr_fuse((1.0 / isi[j]).astype(np.float32), tfp[j], mask[j])[0]
        else:
            want = np.clip(tfp[j], 0.0, 1.0)
        np.testing.assert_array_equal(got[j], want)


# --------------------------------------------------------------------------- MOG


def test_mog_background_and_objects():
    rng = np.random.default_rng(0)
    bg = rng.integers(40, 200, (40, 60)).astype(np.uint8)
    frames = np.repeat(bg[None], 12, axis=0)
    frames[-1, 10:20, 30:45] = 250  # an object appears in the current frame
    fg, background = mog_background(frames, history=12)
    assert background.dtype == np.float32 and background.shape == bg.shape
    np.testing.assert_allclose(background, bg, atol=1)
    obj = mog_objects(frames[-1], background, 20)
    assert obj[10:20, 30:45].all() and obj.sum() == 150
    assert fg[10:20, 30:45].mean() > 0.9
    with pytest.raises(ValueError, match=r"\(K, H, W\)"):
        mog_background(np.zeros((0, 4, 4), np.uint8))


def test_to_u8_guards():
    r = np.array([[0.0, 0.25, 0.5, np.nan, np.inf]], np.float32)
    np.testing.assert_array_equal(to_u8(r, 0.5), [[0, 128, 255, 0, 255]])
    assert to_u8(r, 0.0).dtype == np.uint8  # non-positive gain falls back to 1


# --------------------------------------------------------------------------- DAISI


def test_daisi_spike_and_three_isi_forms():
    col = np.zeros((60, 1, 1), np.uint8)
    for t in (0, 10, 20, 23, 26, 29):  # ISIs 10, 10, 3, 3, 3
        col[t] = 1
    # spike at t = 23: |log 3 - log 10| (Eq. 10-11)
    assert daisi_strength(col, 23)[0, 0] == pytest.approx(np.log(10 / 3), rel=1e-5)
    # spike at t = 20 closes the second 10-step interval: no change
    assert daisi_strength(col, 20)[0, 0] == pytest.approx(0.0, abs=1e-6)
    # no spike at t = 21: three-ISI form, interval (20, 23] against both neighbours
    assert daisi_strength(col, 21)[0, 0] == pytest.approx(np.log(10 / 3), rel=1e-5)
    # no spike at t = 15: interval (10, 20] against (0, 10] and (20, 23]
    assert daisi_strength(col, 15)[0, 0] == pytest.approx(np.log(10 / 3), rel=1e-5)
    # t = 5 sees (0, 10] and (10, 20] only
    assert daisi_strength(col, 5)[0, 0] == pytest.approx(0.0, abs=1e-6)
    # the span reaches the change from t = 5
    assert daisi_strength(col, 5, span=10)[0, 0] == pytest.approx(np.log(10 / 3), rel=1e-5)


def test_daisi_never_marks_a_static_pixel_above_log2():
    levels = np.linspace(0.01, 1.0, 60).reshape(6, 10)
    s = if_spikes(levels, 500, gain=1.0)  # rates up to 1: ISIs 1 and 2 are the worst case
    d = daisi_strength(s, 300, span=50)
    assert d.max() <= np.log(2) + 1e-6
    assert not daisi_edges(s, 300, 0.75, span=50).any()
    assert np.isfinite(daisi_strength(np.zeros((50, 2, 2), np.uint8), 25)).all()


# --------------------------------------------------------------------------- PatchMatch


def _textured(h=40, w=56, seed=0):
    rng = np.random.default_rng(seed)
    img = rng.random((h + 8, w + 8)).astype(np.float32)
    import cv2

    return cv2.GaussianBlur(img, (0, 0), 1.2)


def test_patchmatch_recovers_a_shift():
    big = _textured()
    ref = big[4:-4, 4:-4]
    tgt = np.stack(
        [
            big[4 + dy : big.shape[0] - 4 + dy, 4 + dx : big.shape[1] - 4 + dx]
            for dy, dx in ((2, -3), (-1, 4))
        ]
    )
    mask = np.zeros(ref.shape, bool)
    mask[8:-8, 8:-8] = True
    ys, xs, off, cost = nnf_multi(ref, tgt, mask, iters=4, max_radius=8, seed=3)
    # content at (y, x) of ref sits at (y - dy, x - dx) of a target shifted by (dy, dx)
    assert np.mean((off[0, :, 0] == -2) & (off[0, :, 1] == 3)) > 0.95
    assert np.mean((off[1, :, 0] == 1) & (off[1, :, 1] == -4)) > 0.95
    assert np.all(cost >= 0)


def test_patchmatch_is_deterministic_and_averages():
    big = _textured(seed=5)
    ref = big[4:-4, 4:-4]
    tgts = np.stack([np.roll(ref, k, axis=1) for k in (1, 2, -1)])
    mask = np.zeros(ref.shape, bool)
    mask[10:30, 10:40] = True
    a = patchmatch_fuse(ref, ref, tgts, tgts, mask, seed=2**40 + 7)
    b = patchmatch_fuse(ref, ref, tgts, tgts, mask, seed=2**40 + 7)
    assert np.array_equal(a, b)
    # every target holds the same content (shifted): the average is the reference itself
    np.testing.assert_allclose(a[mask], ref[mask], atol=1e-6)
    assert np.array_equal(a[~mask], ref[~mask])
    # nothing to do: empty mask or no targets
    assert np.array_equal(patchmatch_fuse(ref, ref, tgts, tgts, np.zeros_like(mask)), ref)
    assert np.array_equal(patchmatch_fuse(ref, ref, tgts[:0], tgts[:0], mask), ref)


# --------------------------------------------------------------------------- fine mask


def test_fine_mask_closes_fills_and_drops_specks():
    coarse = np.zeros((40, 40), bool)
    coarse[10:30, 10] = coarse[10:30, 29] = coarse[10, 10:30] = coarse[29, 10:30] = True
    coarse[12:28:4, 10] = False  # a broken outline
    speck = np.zeros_like(coarse)
    speck[2, 2] = True
    m = fine_mask(coarse, speck, np.zeros_like(coarse), close_size=5, min_area=16)
    assert m[10:30, 10:30].all() and not m[2, 2]
    assert not fine_mask(
        np.zeros((5, 5), bool), np.zeros((5, 5), bool), np.zeros((5, 5), bool)
    ).any()
    grown = fine_mask(coarse, speck, speck, close_size=5, min_area=16, dilate=2)
    assert grown.sum() > m.sum() and grown[8, 15]


# --------------------------------------------------------------------------- CSR / CFSR


def test_registry_names_presets_and_masks():
    ms = cfsr.methods()
    assert {"tfi", "tfp", "tfa", "tfstp", "snm", "csr", "cfsr"} <= set(ms)
    assert ms["csr"]["masks"] == ["coarse"]
    assert ms["cfsr"]["masks"] == ["coarse", "fine"]
    paper = ms["cfsr"]["presets"]["paper"]
    assert (paper["T"], paper["theta"], paper["phi0"], paper["phi"], paper["tfp_window"]) == (
        400,
        6,
        50.0,
        4.0,
        160,
    )
    sim = ms["csr"]["presets"]["simulated"]
    assert (sim["T"], sim["theta"], sim["tfp_window"]) == (300, 10, 30)
    assert ms["tfa"]["presets"]["paper"]["threshold"] == 12
    for name in ("csr", "cfsr", "tfa", "tfstp", "snm"):
        for k, p in ms[name]["params"].items():
            assert p["unit"] is not None and p["help"], (name, k)


@pytest.mark.parametrize("est", ["tfp", "isi"])
def test_csr_uses_tfi_on_dynamic_and_tfp_on_static(est):
    from cfsr.methods.tfp import static_rate

    spikes, truth = moving_bars(steps=500)
    t = 450
    # the paper's reading of CSR (Eq. 5-7): distinct-ISI distinction, TFI on the dynamic region
    rate, masks = cfsr.reconstruct(
        spikes,
        "csr",
        [t],
        theta=3,
        return_masks=True,
        static_estimator=est,
        distinction="isi_set",
        dynamic_estimator="tfi",
        static_span=0,
    )
    m = masks["coarse"][0]
    assert m.any() and (~m).any()
    tfi = cfsr.reconstruct(spikes, "tfi", [t], max_isi=200)[0]
    np.testing.assert_array_equal(rate[0][m], tfi[m])
    tfp = cfsr.reconstruct(spikes, "tfp", [t], window=32, mode="centred")[0]
    if est == "isi":
        tfp = static_rate(spikes, t, window=32, mode="centred", estimator="isi", max_isi=200)
    ratio = rate[0][~m] / np.maximum(tfp[~m], 1e-9)
    assert np.allclose(ratio, ratio[0], rtol=1e-4)  # one ATSR scale for the static region
    assert 0.8 < ratio[0] < 1.25


def test_cfsr_masks_and_static_skip():
    spikes, truth = moving_bars(steps=800)
    t = 700
    rate, masks = cfsr.reconstruct(spikes, "cfsr", [t], return_masks=True)
    fine = masks["fine"][0]
    inter = (fine & truth[t]).sum() / (fine | truth[t]).sum()
    assert inter > 0.7
    assert rate.dtype == np.float32 and np.isfinite(rate).all()
    # a static scene: no dynamic pixel, the output is the plain static estimate (isi by
    # default, the paper's TFP with static_estimator=tfp), over 160 steps centred on t
    from cfsr.methods.tfp import static_rate

    static = if_spikes(np.linspace(0.1, 0.9, 24 * 48).reshape(24, 48), 800)
    r, m = cfsr.reconstruct(static, "cfsr", [700], return_masks=True)
    assert not m["coarse"].any() and not m["fine"].any()
    want = static_rate(static, 700, window=160, mode="centred", estimator="isi", max_isi=200)
    np.testing.assert_array_equal(r[0], want)
    r = cfsr.reconstruct(static, "cfsr", [700], static_estimator="tfp")
    tfp = cfsr.reconstruct(static, "tfp", [700], window=160, mode="centred")
    np.testing.assert_array_equal(r[0], tfp[0])


def test_cfsr_refines_the_moving_region():
    spikes, truth, frames = moving_bars(steps=800, h=32, w=64, speed=0.2, video=True)
    for t in (650, 700):
        gt = 0.5 * frames[t]  # rate = gain * intensity
        m = truth[t]
        err = {
            name: np.sqrt(np.mean((cfsr.reconstruct(spikes, name, [t], **kw)[0] - gt)[m] ** 2))
            for name, kw in (("tfi", {}), ("cfsr", {}), ("tfp", {"window": 32, "mode": "centred"}))
        }
        assert err["cfsr"] < 0.6 * err["tfi"], err
        assert err["cfsr"] < err["tfp"], err


def test_multi_center_kernels_equal_single_center():
    from cfsr.methods.tfa import adaptive_rate, adaptive_rates
    from cfsr.methods.tfi import tfi_rate, tfi_rates

    rng = np.random.default_rng(7)
    for trial in range(20):
        n = int(rng.integers(1, 250))
        h, w = (int(v) for v in rng.integers(1, 5, 2))
        s = (rng.random((n, h, w)) < rng.uniform(0, 1, (h, w)) ** 3).astype(np.uint8)
        cs = [int(c) for c in rng.integers(0, n, 6)]
        m = int(rng.integers(1, 90))
        a = tfi_rates(s, cs, max_isi=m)
        b = adaptive_rates(s, cs, threshold=3, max_window=m)
        for k, c in enumerate(cs):
            assert np.array_equal(a[k], tfi_rate(s, c, max_isi=m)), trial
            assert np.array_equal(b[k], adaptive_rate(s, c, threshold=3, max_window=m)), trial


# --------------------------------------------------------------------------- two-sided objects


def test_future_background_splits_ghosts_from_objects():
    """Eq. 9 against the background after t (``mog_sides = both``): a pixel a mover left
    before t matches it (a ghost), a pixel the mover covers at t does not."""
    from cfsr._words import PackedWindow
    from cfsr.methods.cfsr.mog_two_sided import SharpRate, future_objects
    from cfsr.methods.cfsr.settings import CfsrSettings
    from cfsr.methods.registry import get_method, resolve_params

    n, c = 1000, 600
    inten = np.full((n, 1, 2), 0.2)
    inten[: c - 50, 0, 0] = 0.8  # uncovered 50 steps before t: background from then on
    inten[c - 20 : c + 20, 0, 1] = 0.8  # covered at t, background again 20 steps later
    src = PackedWindow.from_frames(if_spikes(inten, n, v0=0.5))
    rate = np.array([[0.1, 0.4]], np.float32)  # rate at t: 51 and 204 levels at gain 0.5
    sharp = SharpRate(rate, np.ones((1, 2), np.int32), rate, 16)
    p = CfsrSettings.of(resolve_params(get_method("cfsr")))
    for adaptive in (True, False):
        keep = future_objects(src, c, np.ones((1, 2), bool), sharp, 0.5, 10.0, adaptive, p, 12)
        assert keep.tolist() == [[False, True]]
        # a pixel that is no candidate stays out
        keep = future_objects(src, c, np.array([[False, True]]), sharp, 0.5, 10.0, adaptive, p, 12)
        assert keep.tolist() == [[False, True]]


def test_two_sided_objects_drop_the_ghost_behind_a_mover():
    """A block sliding right leaves a trail the history before t still holds as the block:
    Eq. 9 on the past alone (the paper, ``mog_sides = past``) marks it, both sides do not."""
    h, w, n, t = 32, 96, 1200, 700
    rng = np.random.default_rng(3)
    bg = 0.15 + 0.1 * rng.random((h, w))
    frames = np.repeat(bg[None], n, axis=0)
    truth = np.zeros((n, h, w), bool)
    block = 0.7 + 0.2 * rng.random((16, 24))
    for s in range(n):
        x = int(10 + 0.05 * s)
        frames[s, 8:24, x : x + 24] = block
        truth[s, 8:24, x : x + 24] = True
    spikes = if_spikes(frames, n)
    fine = {}
    for sides in ("past", "both"):  # the objects alone: no still pixels (they drop it too)
        _, m = cfsr.reconstruct(
            spikes, "cfsr", [t], return_masks=True, mog_sides=sides, still_reach=0
        )
        fine[sides] = m["fine"][0]
    _, m = cfsr.reconstruct(spikes, "cfsr", [t], return_masks=True, mog_sides="past")
    fine["past, still"] = m["fine"][0]
    tr = truth[t]
    iou = {k: (f & tr).sum() / (f | tr).sum() for k, f in fine.items()}
    assert iou["both"] > iou["past"] + 0.05, iou
    assert (fine["both"] & tr).sum() >= 0.95 * tr.sum()  # the block itself stays
    x = int(10 + 0.05 * t)
    trail = np.zeros((h, w), bool)
    trail[8:24, x - 14 : x - 3] = True  # left 3-14 px (60-280 steps) before t: beyond dilate
    assert fine["past"][trail].mean() > 0.5
    assert fine["both"][trail].mean() < 0.2
    # the trail is background that holds one exact rate from the block's passing to the end
    # of the window: still pixels, out of the fine mask whatever Eq. 9 says
    assert fine["past, still"][trail].mean() < 0.2
    assert (fine["past, still"] & tr).sum() >= 0.95 * tr.sum()


def test_paper_presets_keep_eq9_on_the_past():
    ms = cfsr.methods()["cfsr"]
    assert ms["params"]["mog_sides"]["default"] == "both"
    assert ms["presets"]["paper"]["mog_sides"] == "past"
    assert ms["presets"]["simulated"]["mog_sides"] == "past"
    assert ms["params"]["mog_match"]["range"] and ms["params"]["mog_span"]["range"]


def test_every_method_reads_typed_settings_holding_exactly_its_parameters():
    """One source of names: each method's settings type has one field per Param of its
    table, typed as the default (a choice by the StrEnum of its choices); built from resolved
    values, it holds them as they are, and the registry builds it once per parameter set."""
    import dataclasses
    import typing
    from enum import StrEnum

    from cfsr.methods.registry import (
        Method,
        MethodSettings,
        get_method,
        methods,
        register,
        resolve_params,
    )

    for name in methods():
        m = get_method(name)
        assert m.settings is not None, name
        hints = typing.get_type_hints(m.settings)
        assert {f.name for f in dataclasses.fields(m.settings)} == set(m.params), name
        for k, prm in m.params.items():
            if prm.choices is None:
                assert hints[k] is type(prm.default), (name, k)
            else:
                assert issubclass(hints[k], StrEnum), (name, k)
                assert tuple(c.value for c in hints[k]) == prm.choices, (name, k)
        p = resolve_params(m)
        s = m.settings.of(p)
        assert m.settings.of(s) is s
        assert m.settings_of(dict(p)) is m.settings_of(p) == m.settings_of(s)
        with pytest.raises(TypeError):  # a value of another type is resolved first
            m.settings.of({**p, next(k for k in p if type(p[k]) is int): 1.5})
        if name != "cfsr":  # cfsr's settings take its quality tier (test_cfsr_tiers)
            assert dataclasses.asdict(s) == p
        with pytest.raises(dataclasses.FrozenInstanceError):
            s.__setattr__(next(iter(m.params)), 0)
        with pytest.raises(KeyError):
            m.settings.of({})  # a partial set is resolved first, never guessed

    @dataclasses.dataclass(frozen=True)
    class Short(MethodSettings):
        max_isi: int

    tfi = get_method("tfi")
    with pytest.raises(ValueError, match="settings fields differ"):
        register(Method("tfi-copy", "", {**tfi.params, "extra": tfi.params["max_isi"]},
                        tfi.window, tfi.compute, settings=Short))


def test_cfsr_settings_take_the_quality_tier():
    from cfsr.methods.cfsr.settings import CfsrSettings
    from cfsr.methods.cfsr.tiers import QUALITY_TIERS, effective_params
    from cfsr.methods.registry import get_method, resolve_params

    p = resolve_params(get_method("cfsr"), {"quality": "fast", "pm_radius": 12})
    s = CfsrSettings.of(p)
    assert s.mog_frames == QUALITY_TIERS["fast"]["mog_frames"]
    assert s.pm_radius == 12  # set by hand: kept
    assert s == CfsrSettings.of(effective_params(p))
    assert s.coarse.dynamic_estimator == "tfi" and s.coarse.T == s.T


def test_pm_offsets_near_then_far_and_the_window_reaches_the_last():
    from cfsr.methods.cfsr.settings import CfsrSettings, pm_offsets
    from cfsr.methods.registry import get_method, resolve_params

    m = get_method("cfsr")
    p = resolve_params(m, {"pm_step": 2, "pm_count": 15, "pm_far_count": 2, "pm_far_step": 9})
    assert pm_offsets(CfsrSettings.of(p)) == (*range(2, 31, 2), 39, 48)
    assert pm_offsets(CfsrSettings.of({**p, "pm_count": 0})) == (9, 18)
    base = resolve_params(m, {"pm_step": 2, "pm_count": 24, "still_reach": 0, "slow_reach": 0,
                              "mog_sides": "past"})
    far = {**base, "pm_count": 15, "pm_far_count": 2, "pm_far_step": 9}
    # the frame's window reads the last target's TFI: 48 + max_isi steps on each side
    assert m.window(far)[1] == m.window(base)[1] == 48 + base["max_isi"]


def test_the_methods_package_is_callable_and_its_modules_import_by_path():
    """``cfsr.methods()`` describes the methods and ``cfsr.methods`` stays the package: a
    function bound over it made ``import cfsr.methods.<module> as m`` fail."""
    import cfsr
    import cfsr.methods.cfsr.params as params

    assert list(cfsr.methods()) == list(cfsr.methods.methods())
    assert "phi0" in params.FINE_PARAMS and "phi0" in cfsr.methods()["cfsr"]["params"]
