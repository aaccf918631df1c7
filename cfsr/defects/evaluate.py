"""The defect benchmark: the same scenes on a clean and on a defective sensor, with and
without correction, the map's precision and recall over time, and what correcting costs.

Scenes are simulator content (:func:`cfsr.simulate.make_scene` names, or ``"stars"`` for
:func:`cfsr.simulate.star_field`) seen by three sensors with the same seed: an ideal one
(``clean``), one with the ``noise`` defects (``defective``; default the ``defects`` preset:
0.5 % hot pixels, 0.1 % dead, 5 % threshold spread) and the same without its threshold spread
(``hot+dead``). Every method is scored on each sensor as it is and through the correction with
the map estimated from the stream's first ``map_steps`` steps (``...+corrected``);
``clean+corrected`` is what the correction costs where there is nothing to fix. PSNR is
against the same ideal ground truth as :func:`cfsr.evaluation.evaluate`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from cfsr.defects.correct import (
    CorrectedRecording,
    DefectCorrector,
    correct_packed,
    corrected,
    plan_donors,
)
from cfsr.defects.estimate import DefectParams, classify
from cfsr.defects.score import score_map
from cfsr.display import to_display
from cfsr.evaluation import _score_frames, _specs, _timed_outputs, default_times
from cfsr.methods.registry import get_method, resolve_params
from cfsr.simulate import SCENES, make_scene, simulate, star_field
from cfsr.spikes import SpikeRecording

__all__ = [
    "evaluate_defects",
    "map_over_time",
    "correction_cost",
    "clean_sensor_flags",
    "DEFECT_NOISE",
]

#: The defective sensor of the benchmark (a :class:`cfsr.simulate.Noise` spec).
DEFECT_NOISE = "defects"


def _scene(name: str, height: int, width: int) -> Any:
    return star_field(height, width) if name == "stars" else make_scene(name, height, width)


def map_over_time(sim: Any, checkpoints: Sequence[int],
                  params: DefectParams | None = None) -> list[dict[str, Any]]:
    """Precision and recall of the map estimated from the first ``n`` steps of ``sim`` (a
    :class:`~cfsr.simulate.Simulation`) against its sensor's true map, for each ``n``."""
    truth = sim.sensor.defect_map
    counts = np.cumsum(sim.spikes, axis=0, dtype=np.int32)
    out = []
    for n in checkpoints:
        if 0 < n <= sim.steps:
            found = classify(counts[n - 1], int(n), params)
            out.append({"steps": int(n), **score_map(found, truth)})
    return out


def correction_cost(rec: CorrectedRecording, window: int, *, reps: int = 20) -> dict[str, float]:
    """What correcting costs (wall time, this process).

    ``ms_per_frame``: one frame's window of ``window`` steps read through the correction
    (copy included, as the offline path reads it). ``live_us_per_step``: the live path once its
    map is ready, per streamed step when every step is read once: counting
    (:meth:`DefectCorrector.arrived`), correcting the copy in the ring the read returns
    (:meth:`DefectCorrector.before_read`) and a map rebuild shared out over the steps between
    two rebuilds. ``rebuild_ms``: one rebuild (classification and donors).
    """
    assert rec.plan is not None and rec.defect_map is not None
    raw = rec.packed_frames[:window]
    t0 = time.perf_counter()
    for _ in range(reps):
        correct_packed(raw, rec.plan)
    window_ms = 1e3 * (time.perf_counter() - t0) / reps
    live = DefectCorrector(rec.layout, learn=True)
    n = min(rec.n_frames, 4096)
    half = n // 2
    warm = live.params.warmup
    for a in range(0, warm, half):  # the warm-up, once per stream: not a per-frame cost
        live.learn_from(rec.packed_frames[:half], a)
    buf = np.array(rec.packed_frames[:n])
    t0 = time.perf_counter()
    for k in range(reps):
        live.arrived(buf[:half], warm + k * half)
        live.before_read(buf, half, warm + k * half, warm + (k + 1) * half)
    steady_us = 1e6 * (time.perf_counter() - t0) / (reps * half)
    est = live.estimator
    assert est is not None
    t0 = time.perf_counter()
    plan_donors(classify(est.counts(), est.steps, est.params), rec.layout, est.counts())
    rebuild_ms = 1e3 * (time.perf_counter() - t0)
    p = live.params
    per_step = steady_us + 1e3 * rebuild_ms / (p.refresh_ready * p.duty)
    return {"window_steps": int(window), "ms_per_frame": window_ms,
            "live_us_per_step": per_step, "rebuild_ms": rebuild_ms}


def _rows(specs: list[Any], recs: dict[str, Any], gts: list[np.ndarray],
          masks: list[np.ndarray], gain: float, ts: list[int], scene: str) -> list[dict]:
    rows = []
    for spec in specs:
        for sensor, rec in recs.items():
            outs, dt = _timed_outputs(rec, spec, ts, warm=False)
            row = {"method": spec.label, "scene": scene, "sensor": sensor}
            row.update(_score_frames(outs, gts, masks, gain))
            row["ms_per_frame"] = 1e3 * dt / len(ts)
            rows.append(row)
    return rows


def evaluate_defects(
    methods: Sequence[str] | str,
    scenes: Sequence[str] = ("disk", "stars"),
    *,
    noise: str = DEFECT_NOISE,
    steps: int = 1200,
    map_steps: int = 2000,
    checkpoints: Sequence[int] = (250, 500, 1000, 2000),
    seed: int = 0,
    height: int = 250,
    width: int = 400,
) -> dict[str, Any]:
    """Score ``methods`` on ``scenes`` on a clean and a defective sensor (see module).

    Returns ``{"rows", "maps", "cost", "noise", ...}``: a row per (method, scene, sensor) with
    the keys of :func:`cfsr.evaluation.evaluate`; per scene the map's precision/recall at each
    checkpoint (steps) and the flags on the clean sensor; the correction's cost per frame.
    """
    specs = _specs(methods, None)
    ts = default_times(steps)
    n = max(int(steps), int(map_steps), max(checkpoints, default=0))
    rows: list[dict[str, Any]] = []
    maps: dict[str, Any] = {}
    cost: dict[str, Any] = {}
    sensors = {"clean": "none", "defective": noise, "hot+dead": f"{noise},threshold_sd=0"}
    for spec in specs:  # compile outside the timings
        _timed_outputs(SpikeRecording.from_array(np.zeros((64, 16, 16), np.uint8)), spec,
                       [32], warm=False)
    for scene in scenes:
        content = _scene(scene, height, width)
        sims = {s: simulate(content, n, seed=seed, noise=nz) for s, nz in sensors.items()}
        clean, bad = sims["clean"], sims["defective"]
        gain = clean.rate_scale
        gts = [to_display(clean.ideal_rate(t), gain=gain) for t in ts]
        masks = [clean.motion_mask(t) for t in ts]
        recs: dict[str, Any] = {}
        for s, sim in sims.items():
            recs[s] = SpikeRecording.from_array(sim.spikes, meta={"gain": gain})
            recs[f"{s}+corrected"] = corrected(recs[s], steps=map_steps)
        maps[scene] = {
            "over_time": map_over_time(bad, checkpoints),
            "true_hot": int(bad.sensor.hot_mask.sum()),
            "true_dead": int(bad.sensor.dead_mask.sum()),
            "clean_flags": int(recs["clean+corrected"].defect_map.mask.sum()),
        }
        del sims, clean, bad
        rows += _rows(specs, recs, gts, masks, gain, ts, scene)
        if scene == scenes[0]:
            cost = _costs(recs["defective+corrected"], specs, rows)
    return {"rows": rows, "maps": maps, "cost": cost, "noise": noise, "steps": n,
            "times": ts, "map_steps": int(map_steps), "height": height, "width": width}


def _costs(rec: CorrectedRecording, specs: list[Any], rows: list[dict]) -> dict[str, Any]:
    """The correction's cost per frame beside each method's own (same scene, same run): a
    frame's window read through a corrected copy (offline) and corrected in the live ring
    (every step of the window read once, counting and rebuilds included)."""
    out: dict[str, Any] = {"defects": int(rec.plan.targets.size) if rec.plan else 0}
    for spec in specs:
        m = get_method(spec.name)
        before, after = m.window(resolve_params(m, spec.params, spec.preset))
        c = correction_cost(rec, min(rec.n_frames, before + after + 1))
        own = next(r["ms_per_frame"] for r in rows
                   if r["method"] == spec.label and r["sensor"] == "defective")
        live_ms = c["window_steps"] * c["live_us_per_step"] / 1e3  # the window, read once
        out[spec.label] = {**c, "method_ms_per_frame": own, "live_ms_per_frame": live_ms,
                           "fraction": c["ms_per_frame"] / own if own else None,
                           "live_fraction": live_ms / own if own else None}
    return out


def clean_sensor_flags(methods: Sequence[str] | str, scenes: Sequence[str] | None = None, *,
                       steps: int = 1200, map_steps: int = 2000, seed: int = 0,
                       height: int = 250, width: int = 400) -> list[dict[str, Any]]:
    """Every scene (default :data:`cfsr.simulate.SCENES`) on an ideal sensor: the pixels the
    map flags after ``map_steps`` steps and, where it flags any, each method's whole-frame
    PSNR change through the correction (none flagged: the spikes, so the outputs, are
    unchanged bit for bit)."""
    specs = _specs(methods, None)
    ts = default_times(steps)
    out = []
    for scene in scenes or list(SCENES):
        sim = simulate(_scene(scene, height, width), max(steps, map_steps), seed=seed,
                       noise="none")
        raw = SpikeRecording.from_array(sim.spikes, meta={"gain": sim.rate_scale})
        fixed = corrected(raw, steps=map_steps)
        row: dict[str, Any] = {"scene": scene, "flags": int(fixed.defect_map.mask.sum())}
        if row["flags"]:
            gts = [to_display(sim.ideal_rate(t), gain=sim.rate_scale) for t in ts]
            masks = [sim.motion_mask(t) for t in ts]
            for spec in specs:
                a, b = (_score_frames(_timed_outputs(r, spec, ts, warm=False)[0], gts, masks,
                                      sim.rate_scale)["psnr_all"] for r in (raw, fixed))
                row[f"{spec.label}_dpsnr"] = b - a
        out.append(row)
    return out
