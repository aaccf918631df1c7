"""CFSR's "skip what the scene does not need" (``adaptive``) and its fused per-pixel scans.

* The fused history scan of :mod:`cfsr.methods.cfsr.pipeline` gives exactly the numbers of the
  stand-alone kernels it replaces (coarse distinction, TFI, TFP, DAISI), on random windows with
  clipped ranges (the PatchMatch frames' TFI and TFA: tests/test_pmframes.py).
* MOG run only where the history varies by phi0 or more finds the same objects.
* A window without a fine-dynamic pixel gives the TFP path's rate, adaptive or not.
* The adaptive pipeline stays within 0.1 dB of the always-full one on a moving scene; without
  the gate per tile its masks are the full pipeline's.
* Outside the tiles the gate per tile passes, the history scan gives static pixels.
"""

from __future__ import annotations

import numpy as np
import pytest

import cfsr
from cfsr._words import PackedWindow
from cfsr.methods.cfsr import history
from cfsr.methods.cfsr.coarse import CsrSettings, csr_frames, span_estimator, static_length
from cfsr.methods.cfsr.daisi import daisi_strength
from cfsr.methods.cfsr.fine_mask import fine_mask
from cfsr.methods.cfsr.history import history_scan, tfi_at
from cfsr.methods.cfsr.mog import history_objects
from cfsr.methods.cfsr.mog_two_sided import SharpRate
from cfsr.methods.cfsr.patchmatch_frames import TILE, pm_frames, pm_tiles
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.registry import get_method, resolve_params
from cfsr.methods.tfi import tfi_rate
from cfsr.methods.tfp import static_rate, tfp_rate


def _params(**kw):
    return resolve_params(get_method("cfsr"), kw)


def _tfi_at_t(hist, src, c, p):
    """The TFI at t of a history scan: its own when its second pass ran, else computed."""
    return tfi_at(src, c, p["max_isi"]) if hist.tfi is None else hist.tfi


def _random_window(rng, n, h=9, w=13):
    rate = rng.uniform(0.01, 0.95, (1, h, w))
    return (rng.random((n, h, w)) < rate).astype(np.uint8)


@pytest.mark.parametrize("trial", range(8))
def test_history_scan_equals_stand_alone_kernels(trial):
    rng = np.random.default_rng(trial)
    n = int(rng.integers(60, 700))
    # wide windows cross the scans' 64-pixel column chunks
    s = _random_window(rng, n, 5, 150) if trial % 3 == 2 else _random_window(rng, n)
    p = _params(
        T=int(rng.integers(2, 300)),
        theta=int(rng.integers(1, 6)),
        max_isi=int(rng.integers(1, 200)),
        mog_frames=int(rng.integers(1, 13)),
        mog_stride=int(rng.integers(1, 40)),
        mog_window=int(rng.integers(1, 80)),
        tfp_window=int(rng.integers(1, 200)),
        tfp_mode=("trailing", "centred")[trial % 2],
        daisi_span=int(rng.integers(0, 7)),
        static_estimator=("isi", "tfp")[(trial // 2) % 2],
        static_span=int(rng.integers(0, 200)) * (trial % 3 == 0),
        mog_estimator=("tfp", "isi")[trial % 4 == 3],
    )
    c = int(rng.integers(0, n))
    src = PackedWindow.from_frames(s)
    got = history_scan(src, c, CfsrSettings.of(p))
    cs = [c - k * p["mog_stride"] for k in range(p["mog_frames"] - 1, -1, -1)]
    cs = [x for x in cs if x >= 0]
    # the history frames are the paper's CSR frames (Eq. 5-7) on mog_window-step spans
    hp = {**p, "tfp_window": p["mog_window"], "static_span": 0, "distinction": "isi_set"}
    hs = CsrSettings.of({**hp, "static_estimator": p["mog_estimator"]})
    rates, masks, _ = csr_frames(s, cs, hs)
    np.testing.assert_array_equal(got.rates, rates)
    np.testing.assert_array_equal(got.coarse, masks[-1])
    np.testing.assert_array_equal(_tfi_at_t(got, src, c, p), tfi_rate(s, c, max_isi=p["max_isi"]))
    want_tfp = static_rate(
        s,
        c,
        window=static_length(CfsrSettings.of(p)),
        mode=p["tfp_mode"],
        estimator=p["static_estimator"],
        max_isi=p["max_isi"],
    )
    np.testing.assert_array_equal(got.tfp, want_tfp)
    want_d = daisi_strength(s, c, span=p["daisi_span"], max_isi=p["max_isi"])
    np.testing.assert_array_equal(got.daisi, want_d)


def test_mog_only_where_the_history_varies_finds_the_same_objects():
    rng = np.random.default_rng(3)
    u8 = np.repeat(rng.integers(30, 220, (1, 40, 60)), 12, axis=0).astype(np.uint8)
    u8 += rng.integers(0, 6, u8.shape).astype(np.uint8)  # small flicker: never an object
    u8[-1, 10:18, 30:41] = 250  # an object appears
    u8[4:8, 30:35, 2:9] = 5  # a passing shadow in the history
    p = _params()
    full = history_objects(u8, 20.0, False, CfsrSettings.of(p), 12)
    fast = history_objects(u8, 20.0, True, CfsrSettings.of(p), 12)
    np.testing.assert_array_equal(fast, full)
    assert full[10:18, 30:41].all()
    still = np.repeat(u8[:1], 12, axis=0)
    assert not history_objects(still, 20.0, True, CfsrSettings.of(p), 12).any()
    # the two-sided test (f: a sharp rate at t, not a history frame) on the varying pixels
    # gathered into one row finds what MOG on the whole frame finds
    rate = rng.random((40, 60)).astype(np.float32)
    sharp = SharpRate(rate, np.full((40, 60), 4, np.int32), u8[-1] / np.float32(255), 16)
    full = history_objects(u8, 20.0, False, CfsrSettings.of(p), 12, sharp, 1.0)
    fast = history_objects(u8, 20.0, True, CfsrSettings.of(p), 12, sharp, 1.0)
    np.testing.assert_array_equal(fast, full)
    assert full.any() and not full.all()


def _static_spikes(steps=900, h=24, w=36, seed=0):
    rng = np.random.default_rng(seed)
    inten = 0.1 + 0.8 * rng.random((h, w))
    v = rng.random((h, w))
    out = np.zeros((steps, h, w), np.uint8)
    for t in range(steps):
        v += 0.5 * inten
        out[t] = v >= 1.0
        v -= out[t]
    return out


@pytest.mark.parametrize("est", ["isi", "tfp"])
def test_static_window_is_the_tfp_path_adaptive_or_full(est):
    s = _static_spikes()
    p = _params(static_estimator=est)
    t = 700
    for adaptive in (True, False):
        r, masks = cfsr.reconstruct(
            s, "cfsr", [t], return_masks=True, adaptive=adaptive, static_estimator=est
        )
        assert not masks["fine"].any() and not masks["coarse"].any()
        want = static_rate(
            s, t, window=p["tfp_window"], mode=p["tfp_mode"], estimator=est, max_isi=p["max_isi"]
        )
        if est == "tfp":
            np.testing.assert_array_equal(
                want, tfp_rate(s, t, window=p["tfp_window"], mode=p["tfp_mode"])
            )
        np.testing.assert_array_equal(r[0], np.clip(want, 0, 1))
    a = cfsr.reconstruct(s, "cfsr", [t], adaptive=True, static_estimator=est)
    f = cfsr.reconstruct(s, "cfsr", [t], adaptive=False, static_estimator=est)
    np.testing.assert_array_equal(a, f)


def test_adaptive_within_a_tenth_of_a_db_of_the_full_pipeline():
    from cfsr.display import to_display
    from cfsr.metrics import psnr
    from cfsr.simulate import simulate

    sim = simulate("disk", 1000, seed=0, height=100, width=160)
    times = [700, 760]

    def isolated(**kw):
        # each output alone: two outputs 60 steps apart would carry work from the first to
        # the second (carry_groups), and what is carried differs between the pipelines
        outs = [cfsr.reconstruct(sim.spikes, "cfsr", [t], return_masks=True, **kw)
                for t in times]
        return (np.concatenate([r for r, _ in outs]),
                {k: np.concatenate([m[k] for _, m in outs]) for k in outs[0][1]})

    f, mf = isolated(adaptive=False)
    # without the gate per tile, the adaptive pipeline's masks are the full one's
    a, ma = isolated(adaptive=True, static_tile=0)
    # with it, the history of a static tile is its frame at t and the history frames' ATSR
    # scales are summed over the other tiles: masks and rates may move a little
    g, mg = isolated(adaptive=True)
    gain = sim.rate_scale
    for k, t in enumerate(times):
        np.testing.assert_array_equal(ma["fine"][k], mf["fine"][k])
        assert 0.0 < ma["fine"][k].mean() < 1.0
        gt = to_display(sim.gt_rate(t), gain)
        pf = psnr(gt, to_display(f[k], gain))
        for got in (a, g):
            pa = psnr(gt, to_display(got[k], gain))
            assert abs(pa - pf) <= 0.1, (t, pa, pf)
        # outside the fine mask both are the same scaled TFP, and PatchMatch's pixels there
        # (the ghosts it still averages) the same matches: it searches the same region
        out = ~ma["fine"][k]
        np.testing.assert_array_equal(a[k][out], f[k][out])
        both = mg["fine"][k] & mf["fine"][k]
        assert both.sum() >= 0.98 * (mg["fine"][k] | mf["fine"][k]).sum()


def test_region_edge_equal_to_the_full_pipeline_with_24_targets_2_steps_apart():
    # the temporal schedule searches blocks of the matched pixels of a row: when the
    # always-full pipeline matched every pixel, a ghost at the region's edge outside the fine
    # mask took other candidates than in the adaptive one (0.6 % off at (61, 52), t = 760)
    from cfsr.simulate import simulate

    sim = simulate("disk", 1000, seed=0, height=100, width=160)
    kw = {"pm_step": 2, "pm_count": 24, "static_tile": 0}
    f, mf = cfsr.reconstruct(sim.spikes, "cfsr", [760], return_masks=True, adaptive=False, **kw)
    a, ma = cfsr.reconstruct(sim.spikes, "cfsr", [760], return_masks=True, **kw)
    np.testing.assert_array_equal(ma["fine"], mf["fine"])
    out = ~ma["fine"][0]
    np.testing.assert_array_equal(a[0][out], f[0][out])


def test_static_tiles_take_their_frame_at_t_as_history_and_no_daisi():
    # the history scan outside the active tiles: no proof, no DAISI, every history frame the
    # MOG frame at t; inside them (and the static estimate at t everywhere) as without tiles
    from cfsr.simulate import simulate

    sim = simulate("disk", 1000, seed=0, height=64, width=96)
    p = _params()
    src = PackedWindow.from_frames(sim.spikes)
    c = 700
    active = np.zeros((64, 96), bool)
    active[8:56, 20:76] = True
    whole = history_scan(src, c, CfsrSettings.of(p))
    tiled = history_scan(src, c, CfsrSettings.of(p), active)
    np.testing.assert_array_equal(tiled.tfp, whole.tfp)
    np.testing.assert_array_equal(tiled.daisi[active], whole.daisi[active])
    assert not tiled.daisi[~active].any() and whole.daisi[~active].any()
    assert whole.coarse[active].any()  # a moving scene: the second pass ran
    np.testing.assert_array_equal(tiled.coarse, whole.coarse & active)
    np.testing.assert_array_equal(_tfi_at_t(tiled, src, c, p), _tfi_at_t(whole, src, c, p))
    rates = tiled.rates
    np.testing.assert_array_equal(rates[-1], whole.rates[-1])  # exact: it sets MOG's gain
    still = rates[:, ~active]
    np.testing.assert_array_equal(still, np.broadcast_to(rates[-1][~active], still.shape))


@pytest.mark.parametrize("fliplr", [False, True])
def test_packed_path_equals_frames_path_with_head_columns(fliplr):
    from cfsr._bits import unpack_layout
    from cfsr.layout import Layout

    rng = np.random.default_rng(7)
    lay = Layout(24, 16, head_cols=8, flipud=True, fliplr=fliplr)
    n = 500
    packed = rng.integers(0, 256, (n, lay.frame_bytes), dtype=np.uint8)
    packed &= rng.integers(0, 256, packed.shape, dtype=np.uint8)  # sparser spikes
    frames = unpack_layout(packed, lay)
    m = get_method("cfsr")
    p = _params(T=60, theta=3, max_isi=40, mog_frames=4, mog_stride=10, pm_count=4)
    c = 300
    a = m.compute(frames, c, 1000, p)
    b = m.compute_packed(packed, lay, c, 1000, p)
    np.testing.assert_array_equal(a.rate, b.rate)
    for k in a.masks:
        np.testing.assert_array_equal(a.masks[k], b.masks[k])


def test_history_scan_of_a_static_window_takes_the_static_pass_and_equals_the_kernels(
    monkeypatch,
):
    """Integrate-and-fire pixels of constant brightness (a static scene): every pixel is
    proven static by the first pass, and the results still equal the stand-alone kernels."""
    rng = np.random.default_rng(7)
    n, h, w = 900, 6, 70
    rate = rng.uniform(0.02, 0.9, (h, w))
    acc = rng.uniform(0, 1, (h, w))
    s = np.zeros((n, h, w), np.uint8)
    for t in range(n):
        acc += rate
        s[t] = acc >= 1.0
        acc -= s[t]
    p = _params()
    c = 800

    def second_pass(*args):
        raise AssertionError("the second pass ran on a static window")

    with monkeypatch.context() as mp:
        mp.setattr(history, "dynamic_kernel", second_pass)
        src = PackedWindow.from_frames(s)
        got = history_scan(src, c, CfsrSettings.of(p))
    assert not got.coarse.any()
    cs = [c - k * p["mog_stride"] for k in range(p["mog_frames"] - 1, -1, -1)]
    # the history frames are the paper's CSR frames (Eq. 5-7) on mog_window-step spans
    hp = {**p, "tfp_window": p["mog_window"], "static_span": 0, "distinction": "isi_set"}
    hs = CsrSettings.of({**hp, "static_estimator": p["mog_estimator"]})
    rates, masks, _ = csr_frames(s, cs, hs)
    assert not masks.any()
    np.testing.assert_array_equal(got.rates, rates)
    np.testing.assert_array_equal(_tfi_at_t(got, src, c, p), tfi_rate(s, c, max_isi=p["max_isi"]))
    want_tfp = static_rate(
        s,
        c,
        window=static_length(CfsrSettings.of(p)),
        mode=p["tfp_mode"],
        # the span rule; fine_stage applies the steady check
        estimator=span_estimator(CfsrSettings.of(p)),
        max_isi=p["max_isi"],
    )
    np.testing.assert_array_equal(got.tfp, want_tfp)
    want_d = daisi_strength(s, c, span=p["daisi_span"], max_isi=p["max_isi"])
    np.testing.assert_array_equal(got.daisi, want_d)


def test_pm_tiles_cover_the_search_margin_of_every_fine_pixel_and_skip_the_rest():
    fine = np.zeros((250, 400), bool)
    fine[100:110, 50:60] = True  # one small object
    fine[20, 390] = True  # one pixel near the right edge
    margin = 23
    tiles = pm_tiles(fine, margin)
    px = np.kron(tiles, np.ones((TILE, TILE), bool))[:250, :400]
    import cv2

    reach = cv2.dilate(fine.astype(np.uint8), np.ones((2 * margin + 1,) * 2, np.uint8)) > 0
    assert px[reach].all()  # everything PatchMatch and the guides' blur can read
    assert px.mean() < 0.25  # and the frame's far side is skipped
    assert not pm_tiles(np.zeros((250, 400), bool), margin).any()


def test_patchmatch_frames_on_tiles_equal_the_whole_box_where_computed():
    rng = np.random.default_rng(5)
    s = _random_window(rng, 300, 70, 90)
    p = _params(max_isi=60, pm_guide=3)
    cs = [150, 120, 180]
    tiles = np.zeros((-(-70 // TILE), -(-90 // TILE)), bool)
    tiles[1, 2] = tiles[3, 4] = tiles[3, 5] = True
    src = PackedWindow.from_frames(s)
    # a box starting on a tile row computes exactly the marked tiles; one starting inside a
    # tile row computes every crop row band that touches a marked tile (a superset)
    for box in [(16, 70, 3, 90), (5, 70, 3, 90)]:
        raw_t, _ = pm_frames(src, cs, box, CfsrSettings.of(p), tiles)
        raw_b, _ = pm_frames(src, cs, box, CfsrSettings.of(p))
        px = np.kron(tiles, np.ones((TILE, TILE), bool))[box[0] : box[1], box[2] : box[3]]
        np.testing.assert_array_equal(raw_t[:, px], raw_b[:, px])
        if box[0] % TILE == 0:  # unmarked tiles hold NaN (never matched): not computed
            assert np.isnan(raw_t[:, ~px]).all()
            assert np.isfinite(raw_b).all()


@pytest.mark.parametrize("trial", range(6))
def test_fine_mask_on_the_cues_bounding_box_equals_the_whole_frame(trial):
    rng = np.random.default_rng(40 + trial)
    h, w = 90, 120
    cues = np.zeros((3, h, w), bool)
    for _ in range(int(rng.integers(1, 5))):  # blobs with holes, specks, some at the border
        y, x = int(rng.integers(0, h)), int(rng.integers(0, w))
        r = int(rng.integers(2, 15))
        yy, xx = np.ogrid[:h, :w]
        d = (yy - y) ** 2 + (xx - x) ** 2
        cues[int(rng.integers(0, 3))] |= (d <= r * r) & (d >= (r // 2) ** 2)
    cues[2] |= rng.random((h, w)) < 0.002
    kw = {"close_size": (0, 5, 9)[trial % 3], "min_area": (1, 16)[trial % 2], "dilate": trial % 3}
    got = fine_mask(*cues, **kw)
    from cfsr.methods.cfsr.fine_mask import _regularise_crop

    want = _regularise_crop(
        cues[0] | cues[1] | cues[2], kw["close_size"], kw["min_area"], kw["dilate"]
    )
    np.testing.assert_array_equal(got, want)
