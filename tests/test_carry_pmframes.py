"""Dense CFSR output shares its PatchMatch frames: the frames a later output of a group takes
from the bank are the numbers a fresh computation gives, so sharing them changes no output,
and carried outputs stay within 0.1 dB of isolated ones."""

from __future__ import annotations

import numpy as np
import pytest

import cfsr
from cfsr._words import PackedWindow
from cfsr.display import to_display
from cfsr.methods import get_method
from cfsr.methods.cfsr import patchmatch_frames as pmframes
from cfsr.methods.cfsr import refinement
from cfsr.methods.cfsr.patchmatch_frames import TILE, pm_frames
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.registry import resolve_params
from cfsr.metrics import psnr
from cfsr.simulate import simulate
from cfsr.spikes import SpikeRecording
from cfsr.streaming import StreamingReconstructor

STEPS = 1400


@pytest.fixture(scope="module")
def disk():
    sim = simulate("disk", STEPS, seed=0, height=96, width=144)
    return sim, SpikeRecording.from_array(sim.spikes)


def _window(sim, lo, hi):
    return PackedWindow.from_frames(np.ascontiguousarray(sim.spikes[lo:hi]))


def test_banked_frames_are_the_computed_ones(disk):
    sim, _ = disk
    p = resolve_params(get_method("cfsr"))
    src = _window(sim, 0, 400)
    th, tw = -(-src.h // TILE), -(-src.w // TILE)
    tiles = np.zeros((th, tw), bool)
    tiles[2:9, 3:14] = True
    small = tiles.copy()
    small[2, :] = False  # a later call on fewer tiles, inside the first one's box
    box = (16, 72, 24, 112)
    bank: dict = {}
    first = [150, 153, 156, 159]
    raw0, guide0 = pm_frames(src, first, box, CfsrSettings.of(p), tiles, bank=bank, shift=1000)
    assert sorted(bank["times"].tolist()) == [1150, 1153, 1156, 1159]
    later = [151, 153, 159, 162]  # two banked steps, two new ones
    calls = []
    kernel = pmframes._computed

    def spy(src, cs, *rest):
        calls.append(sorted(int(c) for c in cs))
        return kernel(src, cs, *rest)

    pmframes._computed = spy
    try:
        raw1, guide1 = pm_frames(src, later, box, CfsrSettings.of(p), small, bank=bank, shift=1000)
    finally:
        pmframes._computed = kernel
    assert calls == [[151, 162]]  # only the frames the bank does not hold
    fresh_raw, fresh_guide = pm_frames(src, later, box, CfsrSettings.of(p), small)
    np.testing.assert_array_equal(raw1, fresh_raw)
    np.testing.assert_array_equal(guide1, fresh_guide)
    # the first call's frames are the isolated ones (a bank changes nothing on its own)
    plain_raw, plain_guide = pm_frames(src, first, box, CfsrSettings.of(p), tiles)
    np.testing.assert_array_equal(raw0, plain_raw)
    np.testing.assert_array_equal(guide0, plain_guide)
    # more tiles than the bank computed: nothing taken from it
    calls.clear()
    pmframes._computed = spy
    try:
        pm_frames(src, later, box, CfsrSettings.of(p), np.ones_like(tiles), bank=bank, shift=1000)
    finally:
        pmframes._computed = kernel
    assert calls == [sorted(later)]


def test_outputs_a_multiple_of_pm_step_apart_share_frames_exactly(disk, monkeypatch):
    """Outputs 30 steps apart (10 PatchMatch steps): a later output takes the frames it
    shares with the previous one from the bank, computes only the new ones, and gives the
    very frames it gives when it computes them all."""
    _, rec = disk
    times = [704, 734, 764, 794]
    computed = []  # frames each PatchMatch stage computed
    orig = pmframes._computed

    def spy(src, cs, *rest):
        computed.append(len(cs))
        return orig(src, cs, *rest)

    def run(share: bool):
        sr = StreamingReconstructor("cfsr", rec.layout, slack=STEPS)
        sr.push(rec.packed(0, STEPS), 0)
        if not share:  # the same group, every frame computed
            plain = refinement.pm_frames
            monkeypatch.setattr(
                refinement,
                "pm_frames",
                lambda *a, bank=None, shift=0, **k: plain(*a, **k),
            )
        out = [sr.compute(t).rate for t in times]
        monkeypatch.undo()
        return out

    monkeypatch.setattr(pmframes, "_computed", spy)
    shared = run(True)
    total = 2 * resolve_params(get_method("cfsr"))["pm_count"] + 1
    # every frame computed once for the first output; later ones compute their new frames,
    # and the shared ones only on the tiles the previous output did not compute
    assert computed[0] == total and total not in computed[1:], computed
    assert sum(computed) < len(times) * total, computed
    for a, b in zip(shared, run(False), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("scene", ["car", "vibrate"])
def test_carried_outputs_within_a_tenth_of_a_db(scene):
    sim = simulate(scene, STEPS, seed=0, height=96, width=144)
    rec = SpikeRecording.from_array(sim.spikes)
    times = list(range(608, 1001, 32))
    carried = cfsr.reconstruct(rec, "cfsr", times)
    isolated = [cfsr.reconstruct(rec, "cfsr", [t])[0] for t in times]
    np.testing.assert_array_equal(carried[0], isolated[0])
    gain = sim.rate_scale
    gts = [to_display(sim.ideal_rate(t), gain) for t in times]
    masks = [sim.motion_mask(t) for t in times]

    def scores(rates):
        imgs = [to_display(r, gain) for r in rates]
        whole = np.mean([psnr(g, i) for g, i in zip(gts, imgs, strict=True)])
        motion = np.mean([psnr(g, i, mask=m) for g, i, m in zip(gts, imgs, masks, strict=True)])
        return whole, motion

    (ca, cm), (ia, im) = scores(carried), scores(isolated)
    assert abs(ca - ia) <= 0.1 and abs(cm - im) <= 0.1, ((ca, cm), (ia, im))
