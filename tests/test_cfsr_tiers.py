"""CFSR's quality tiers and the work it carries from one output to the next."""

from __future__ import annotations

import numpy as np
import pytest

import cfsr
from cfsr.config import MethodConfig
from cfsr.display import to_display
from cfsr.methods import get_method
from cfsr.methods.cfsr.carry import carry_groups
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.cfsr.tiers import QUALITY_TIERS, effective_params, fast_config
from cfsr.methods.registry import resolve_params
from cfsr.metrics import psnr
from cfsr.simulate import simulate
from cfsr.spikes import SpikeRecording

STEPS = 1400
TIMES = (700, 800, 900)


@pytest.fixture(scope="module")
def scenes():
    """Two small simulated scenes: a rotating disk and the slow translating car (the scene
    whose PatchMatch averaging the fast tier's fewer targets cost most)."""
    out = {}
    for name in ("disk", "car"):
        sim = simulate(name, STEPS, seed=0, height=96, width=144)
        out[name] = (
            SpikeRecording.from_array(sim.spikes),
            sim.rate_scale,
            {t: to_display(sim.ideal_rate(t), sim.rate_scale) for t in range(600, 1001, 4)},
            {t: sim.motion_mask(t) for t in range(600, 1001, 4)},
        )
    return out


def _scores(rates, gts, masks, gain):
    imgs = [to_display(r, gain) for r in rates]
    whole = np.mean([psnr(g, i) for g, i in zip(gts, imgs, strict=True)])
    motion = np.mean([psnr(g, i, mask=m) for g, i, m in zip(gts, imgs, masks, strict=True)])
    return float(whole), float(motion)


def _isolated(rec, times, **params):
    """Every output on its own (one reconstruct call per step: nothing carried)."""
    return [cfsr.reconstruct(rec, "cfsr", [t], **params)[0] for t in times]


def test_full_is_the_default_and_fast_changes_only_defaults():
    m = get_method("cfsr")
    p = resolve_params(m)
    assert p["quality"] == "full" and effective_params(p) is p
    fast = effective_params(resolve_params(m, {"quality": "fast"}))
    for k, v in QUALITY_TIERS["fast"].items():
        assert fast[k] == v
    # an explicit value wins over the tier's
    mine = effective_params(resolve_params(m, {"quality": "fast", "pm_count": 10, "T": 250}))
    assert mine["pm_count"] == 10 and mine["T"] == 250
    assert mine["mog_frames"] == QUALITY_TIERS["fast"]["mog_frames"]


def test_window_follows_the_effective_settings():
    full = MethodConfig("cfsr")
    fast = fast_config(full)
    assert fast.params["quality"] == "fast" and fast.method == "cfsr"
    assert fast.window == get_method("cfsr").window({**full.params, **QUALITY_TIERS["fast"]})
    assert fast.window != full.window  # the still reach and the history are shorter
    assert fast_config(MethodConfig("tfp")) == MethodConfig("tfp")
    with pytest.raises(ValueError, match="quality"):
        MethodConfig("cfsr", {"quality": "fastest"})


def test_fast_is_the_same_as_its_settings_spelled_out(scenes):
    rec, *_ = scenes["disk"]
    a = cfsr.reconstruct(rec, "cfsr", [TIMES[0]], quality="fast")
    b = cfsr.reconstruct(rec, "cfsr", [TIMES[0]], **QUALITY_TIERS["fast"])
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("scene", ["disk", "car"])
def test_fast_within_its_bars_and_above_csr(scenes, scene):
    rec, gain, gts, masks = scenes[scene]
    g, m = [gts[t] for t in TIMES], [masks[t] for t in TIMES]
    full = _scores(_isolated(rec, TIMES), g, m, gain)
    fast = _scores(_isolated(rec, TIMES, quality="fast"), g, m, gain)
    csr = _scores(cfsr.reconstruct(rec, "csr", list(TIMES)), g, m, gain)
    assert fast[0] >= full[0] - 0.5 and fast[1] >= full[1] - 1.0, (full, fast)
    assert fast[0] > csr[0], (fast, csr)


def test_carry_groups_partition_by_span_and_gap():
    p = resolve_params(get_method("cfsr"), {"carry_span": 256, "carry_gap": 40})
    times = [900, 10, 40, 40, 70, 130, 250, 260, 290, 600]
    groups = carry_groups(times, CfsrSettings.of(p))
    assert [t for g in groups for t in g] == sorted(set(times))
    assert groups == [[10, 40, 70], [130], [250], [260, 290], [600], [900]]
    for g in groups:  # one span, consecutive gaps within carry_gap
        assert len({t // 256 for t in g}) == 1
        assert all(0 < b - a <= 40 for a, b in zip(g, g[1:], strict=False))
    alone = CfsrSettings.of({**p, "carry_span": 0})
    assert carry_groups(times, alone) == [[t] for t in sorted(set(times))]
    # the rule sees only the steps: a subset of a group's steps never joins two groups
    assert get_method("cfsr").carry_groups(times, CfsrSettings.of(p)) == groups
    assert get_method("tfp").carry_groups([5, 1, 5], resolve_params(get_method("tfp"))) == [
        [1],
        [5],
    ]


def test_carried_outputs_stay_close_to_isolated_ones(scenes):
    rec, gain, gts, masks = scenes["disk"]
    times = list(range(608, 1001, 32))  # one span of 512 steps, 32 steps apart
    assert len(carry_groups(times, CfsrSettings.of(resolve_params(get_method("cfsr"))))) == 1
    carried = cfsr.reconstruct(rec, "cfsr", times)
    isolated = _isolated(rec, times)
    # the first output of a group is the isolated one, bit for bit
    np.testing.assert_array_equal(carried[0], isolated[0])
    g, m = [gts[t] for t in times], [masks[t] for t in times]
    ca, cm = _scores(carried, g, m, gain)
    ia, im = _scores(isolated, g, m, gain)
    assert abs(ca - ia) <= 0.1 and abs(cm - im) <= 0.1, ((ca, cm), (ia, im))
    # carry_span = 0: nothing carried, the isolated frames exactly
    np.testing.assert_array_equal(
        cfsr.reconstruct(rec, "cfsr", times[:3], carry_span=0), np.stack(isolated[:3])
    )


def test_groups_give_the_same_frames_in_any_split(scenes):
    """What a pool of processes relies on: each group run alone, from an empty memo, gives
    the frames the whole sequence gives in one stream."""
    from cfsr.streaming import StreamingReconstructor

    rec, *_ = scenes["disk"]
    p = {"carry_span": 128}
    times = [700, 732, 764, 800, 820, 900]
    cfg = MethodConfig("cfsr", p)
    groups = cfg.spec.carry_groups(times, cfg.params)
    assert len(groups) > 1
    sr = StreamingReconstructor(cfg, rec.layout, slack=STEPS)
    sr.push(rec.packed(0, STEPS), 0)
    whole = {t: sr.compute(t).rate for t in times}  # one memo, never emptied
    for g in reversed(groups):  # groups in another order, each from nothing
        sr.memo.clear()
        for t in g:
            np.testing.assert_array_equal(sr.compute(t).rate, whole[t])


def test_a_carried_output_scans_only_its_new_history_frames(scenes, monkeypatch):
    from cfsr.methods.cfsr import history
    from cfsr.streaming import StreamingReconstructor

    scanned = []  # history frames (and the span at t) each scan computes
    kernel = history.static_kernel

    def spy(src, union, spans, *rest):
        scanned.append(len(spans.cents))
        return kernel(src, union, spans, *rest)

    monkeypatch.setattr(history, "static_kernel", spy)
    rec, *_ = scenes["disk"]
    sr = StreamingReconstructor("cfsr", rec.layout, slack=STEPS)
    sr.push(rec.packed(0, STEPS), 0)
    k, stride = sr.params["mog_frames"], sr.params["mog_stride"]
    sr.compute(704)
    sr.compute(704 + stride)  # one stride later: the frame at t is the only new one
    sr.compute(704 + 2 * stride + 8)  # off the grid: the nearest carried frames stand in
    sr.compute(704 + 3 * stride + 200)  # beyond carry_gap: scanned anew
    assert scanned == [k + 1, 2, 2, k + 1]
    assert sorted(sr.memo["cfsr"].frames)[-1] == 704 + 3 * stride + 200
