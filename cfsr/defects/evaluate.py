"""The defect benchmark: the same scenes on a clean and on a defective sensor, with and
without correction, the map's precision and recall over time, and what correcting costs.

Scenes are simulator content (:func:`cfsr.simulate.make_scene` names, or ``"stars"`` for
:func:`cfsr.simulate.star_field`) seen by three sensors with the same seed: an ideal one
(``clean``), one with the ``noise`` defects (``defective``; default the ``defects`` preset:
0.5 % hot pixels, 0.1 % dead, 5 % threshold spread) and the same without its threshold spread
(``hot+dead``). Every method is scored on each sensor as it is and through the correction with
the map estimated from the stream's first ``map_steps`` steps (``...+corrected``), and the
clean and defective sensors through a flat-field calibration of their own (``...+calibrated``:
the map and every pixel's gain, :func:`cfsr.defects.calibrate`); ``clean+corrected`` and
``clean+calibrated`` are what the corrections cost where there is nothing to fix. PSNR is
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
    calibrate,
    correct_packed,
    corrected,
    in_buffer,
    plan_donors,
)
from cfsr.defects.estimate import DefectParams, classify
from cfsr.defects.gain import GainMap, flatten, inverse_gain
from cfsr.defects.score import score_map
from cfsr.display import to_display
from cfsr.evaluation import _score_frames, _specs, _timed_outputs, default_times
from cfsr.methods.registry import Output, get_method, resolve_params
from cfsr.simulate import SCENES, Scene, make_scene, simulate, star_field
from cfsr.spikes import SpikeRecording

__all__ = [
    "evaluate_defects",
    "map_over_time",
    "correction_cost",
    "clean_sensor_flags",
    "flat_field",
    "gain_error",
    "true_gain",
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
    """What correcting costs (CPU time of this process, :func:`time.process_time`), once the
    map is ready, for frames whose window is ``window`` steps.

    ``ms_per_frame``: the window corrected in place in a reconstructor's buffer as the
    offline streaming path (``cfsr reconstruct``, :func:`in_buffer`) reads it: blocks of
    1,024 steps pushed, a frame every 1,024 (:func:`_buffer_cost`). ``copy_ms_per_frame``:
    the window read through a corrected copy (:meth:`CorrectedRecording.packed`, what
    :func:`cfsr.reconstruct_outputs` and a pool read). ``live_ms_per_frame``: the live
    worker's buffer, blocks of 256 steps (a replay's), a frame every 1,280 steps (30
    frames/s at 40 kHz), the window corrected when read; ``upkeep_us_per_step``: what keeping
    the map costs per streamed step besides (counting, :meth:`DefectCorrector.arrived`, and
    a rebuild shared out over the steps between two). ``gain_ms_per_frame``: one output
    divided by a calibration's gain (:func:`cfsr.defects.gain.flatten`). ``rebuild_ms``: one
    rebuild (classification and donors).
    """
    assert rec.plan is not None and rec.defect_map is not None
    raw = rec.packed_frames[:window]
    t0 = time.process_time()
    for _ in range(reps):
        correct_packed(raw, rec.plan)
    copy_ms = 1e3 * (time.process_time() - t0) / reps
    out = Output(np.zeros(rec.layout.shape, np.float32))
    inv = inverse_gain(GainMap(np.ones(rec.layout.shape, np.float32)))
    t0 = time.process_time()
    for _ in range(reps):
        flatten(out, inv)
    gain_ms = 1e3 * (time.process_time() - t0) / reps
    _, window_ms, _ = _buffer_cost(rec, window, reps, block=1024, every=1024, learn=False)
    live, live_ms, count_us = _buffer_cost(rec, window, reps, block=256, every=1280,
                                           learn=True)
    est = live.estimator
    assert est is not None
    t0 = time.process_time()
    plan_donors(classify(est.counts(), est.steps, est.params), rec.layout, est.counts())
    rebuild_ms = 1e3 * (time.process_time() - t0)
    p = live.params
    return {"window_steps": int(window), "ms_per_frame": window_ms,
            "copy_ms_per_frame": copy_ms, "gain_ms_per_frame": gain_ms,
            "live_ms_per_frame": live_ms,
            "upkeep_us_per_step": count_us + 1e3 * rebuild_ms / (p.refresh_ready * p.duty),
            "rebuild_ms": rebuild_ms}


def _buffer_cost(rec: CorrectedRecording, window: int, frames: int, *, block: int,
                 every: int, learn: bool) -> tuple[DefectCorrector, float, float]:
    """A corrector in a mirrored ring of ``window`` + 1,024 steps, as a
    :class:`~cfsr.streaming.StreamingReconstructor` holds it: blocks of ``block`` steps
    written in (not timed: the buffer writes them anyway), the newest window read every
    ``every`` steps, ``frames`` times. ``learn``: a live corrector counting every block, its
    map ready (the warm-up, once per stream, not timed); else one given ``rec``'s donors.
    Returns the corrector, the CPU ms per frame of correcting the window and the CPU us per
    streamed step of counting."""
    m = rec.defect_map
    assert m is not None
    fix = (DefectCorrector(rec.layout, learn=True) if learn
           else in_buffer(rec)[1] or DefectCorrector(rec.layout, m))
    data = rec.packed_frames
    n = min(rec.n_frames, 4096) // block * block
    s = 0
    while learn and fix.estimator.map.steps < fix.params.warmup:
        fix.learn_from(data[:n], s)
        s += n
    cap = window + 1024
    ring = np.zeros((2 * cap, rec.layout.frame_bytes), np.uint8)
    read = count = 0.0
    steps = done = 0
    while done < frames:
        for a in range(0, n, block):
            blk = data[a : a + block]
            i = s % cap
            k = min(block, cap - i)
            for half in (0, cap):
                ring[half + i : half + i + k] = blk[:k]
                ring[half : half + block - k] = blk[k:]
            t0 = time.process_time()
            fix.arrived(blk, s)
            count += time.process_time() - t0
            s += block
            steps += block
            if steps % every == 0 and done < frames:
                t0 = time.process_time()
                fix.before_read(ring, cap, s - window, s)
                read += time.process_time() - t0
                done += 1
    return fix, 1e3 * read / frames, 1e6 * count / steps


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
        cal = {s: flat_field(sensors[s], seed, height, width) for s in ("clean", "defective")}
        for s, c in cal.items():
            recs[f"{s}+calibrated"] = corrected(recs[s], c)
        maps[scene] = {
            "over_time": map_over_time(bad, checkpoints),
            "true_hot": int(bad.sensor.hot_mask.sum()),
            "true_dead": int(bad.sensor.dead_mask.sum()),
            "clean_flags": int(recs["clean+corrected"].defect_map.mask.sum()),
            "calibration": {**score_map(cal["defective"], bad.sensor.defect_map),
                            "gain_rms_error": gain_error(cal["defective"], bad),
                            "true_gain_sd": float(true_gain(bad).std())},
        }
        del sims, clean, bad
        rows += _rows(specs, recs, gts, masks, gain, ts, scene)
        if scene == scenes[0]:
            cost = _costs(recs["defective+corrected"], specs, ts)
    return {"rows": rows, "maps": maps, "cost": cost, "noise": noise, "steps": n,
            "times": ts, "map_steps": int(map_steps), "height": height, "width": width}


def true_gain(sim: Any) -> np.ndarray:
    """The simulator's per-pixel gain: the rate over the nominal pixel's (light-to-charge gain
    over the threshold, each against its nominal value), upright (H, W)."""
    s = sim.sensor
    return (s.gain_map / s.gain) / (s.threshold_map / s.threshold)


def gain_error(cal: Any, sim: Any) -> float:
    """RMS difference between a calibration's gain and the truth, over the unflagged pixels."""
    good = ~cal.mask
    return float(np.sqrt(np.mean((cal.gain.gain - true_gain(sim))[good] ** 2)))


def flat_field(noise: str, seed: int, height: int, width: int, steps: int = 2000) -> Any:
    """The calibration (:func:`cfsr.defects.calibrate`) of a flat field (uniform intensity
    0.5) seen for ``steps`` steps by the sensor ``noise`` with ``seed`` (the same sensor as a
    scene simulated with that seed: its maps depend on the seed and size only)."""
    sim = simulate(Scene("flat", np.full((height, width), 0.5, np.float32)), steps, seed=seed,
                   noise=noise)
    return calibrate(SpikeRecording.from_array(sim.spikes))


def _costs(rec: CorrectedRecording, specs: list[Any], ts: list[int]) -> dict[str, Any]:
    """The correction's cost per frame beside each method's own (same scene, same run): a
    frame's window corrected in a reconstructor's buffer (offline, ``fraction``), read
    through a corrected copy (``copy_fraction``) and corrected in the live ring (every step of
    the window read once, counting and rebuilds included: ``live_fraction``); a calibration's
    gain divided out of the frame (``gain_fraction``). Every time here is CPU time of this
    process on one thread, as the correction runs (``method_ms_per_frame``: the method's, on
    the defective sensor's spikes)."""
    out: dict[str, Any] = {"defects": int(rec.plan.targets.size) if rec.plan else 0}
    for spec in specs:
        m = get_method(spec.name)
        before, after = m.window(resolve_params(m, spec.params, spec.preset))
        c = correction_cost(rec, min(rec.n_frames, before + after + 1))
        own = _single_thread_ms(in_buffer(rec)[0], spec, ts)
        live_ms = c["live_ms_per_frame"]
        out[spec.label] = {**c, "method_ms_per_frame": own,
                           "fraction": c["ms_per_frame"] / own if own else None,
                           "copy_fraction": c["copy_ms_per_frame"] / own if own else None,
                           "gain_fraction": c["gain_ms_per_frame"] / own if own else None,
                           "live_fraction": live_ms / own if own else None}
    return out


def _single_thread_ms(rec: Any, spec: Any, ts: list[int]) -> float:
    """CPU ms per frame of ``spec`` at ``ts`` on one numba thread (the correction's own)."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        t0 = time.process_time()
        _timed_outputs(rec, spec, ts, warm=False)
        return 1e3 * (time.process_time() - t0) / len(ts)
    finally:
        numba.set_num_threads(threads)


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
