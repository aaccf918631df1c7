"""``cfsr bench --sweep``: cost against dynamic area, adaptive pipeline versus always-full.

Scenes: the static scene, then the rotating disk with radii that cover ~10 %, ~30 % and all of
the frame. For each, ``cfsr`` runs with ``adaptive=True`` (skip what the scene does not need)
and ``adaptive=False`` (every stage on the whole frame), adaptive with its gate per tile off
(``static_tile=0``: what the tiles save on a moving window), and adaptive with its static gate
off (``static_tol=-1``, which also turns the tiles off: what the exact proof of a static window
costs, and what the gate adds to a moving one); TFP is timed beside them as the floor a fully
static window should approach.
Costs are steady-state ms per output frame through the streaming reconstructor; errors are
PSNR against the simulator's ground truth.
"""

from __future__ import annotations

import argparse
from typing import Any

from cfsr import bench  # time_call read at call time (tests time one call)
from cfsr._bits import pack_frames
from cfsr.bench import TIER_BARS, carried_rows, format_rows, tier_rows
from cfsr.display import to_display
from cfsr.layout import Layout
from cfsr.methods import get_method
from cfsr.metrics import psnr
from cfsr.simulate import SCENES, make_scene, simulate
from cfsr.streaming import StreamingReconstructor

SCENARIOS = (
    ("static", "static", {}),
    ("~10% moving", "disk", {"radius": 56}),
    ("~30% moving", "disk", {"radius": 98}),
    ("full motion", "disk", {"radius": 240}),
)


def sweep(args: argparse.Namespace, bar) -> dict[str, Any]:
    import numpy as np

    if "adaptive" not in get_method("cfsr").params:
        raise ValueError("this build's cfsr has no 'adaptive' parameter to switch off skipping")
    steps = args.steps or 1400
    # PatchMatch's random search moves one frame's PSNR by ~0.03 dB (std over seeds), so
    # single frames of two pipelines can differ by 0.1 dB: errors are means over frames
    # (the worst frame's difference is reported beside them), in --quick too
    times = [steps - 600, steps - 500, steps - 400]
    variants = (
        ("tfp", {}),
        ("cfsr", {"adaptive": True}),
        ("cfsr", {"adaptive": True, "static_tile": 0}),
        ("cfsr", {"adaptive": True, "static_tol": -1}),
        ("cfsr", {"adaptive": False}),
    )
    bar.reset(total=len(SCENARIOS) * len(variants))
    rows = []
    for label, scene_name, opts in SCENARIOS:
        bar.set_description(f"sweep {label}")
        scene = make_scene(scene_name, height=250, width=400, **opts)
        sim = simulate(scene, steps, seed=0)
        gain = sim.rate_scale
        packed = pack_frames(sim.spikes)
        lay = Layout(400, 250)
        gts = {t: to_display(sim.gt_rate(t), gain) for t in times}
        motion = float(np.mean([sim.motion_mask(t).mean() for t in times]))
        for name, params in variants:
            sr = StreamingReconstructor(name, lay, params=params, slack=steps)
            sr.push(packed, 0)
            outs = {t: sr.compute(t) for t in times}
            ps = [psnr(gts[t], to_display(outs[t].rate, gain)) for t in times]
            # min_time bounds the slow pipelines; fast ones (TFP, gated) take many reps
            sec = bench.time_call(
                lambda sr=sr: sr.compute(times[0]),
                min_time=0.5 if args.quick else 1.0,
                max_reps=1000,
            )
            fine = outs[times[0]].masks.get("fine")
            rows.append(
                {
                    "scenario": label,
                    "motion_fraction": motion,
                    "method": name,
                    "adaptive": params.get("adaptive"),
                    # the gate belongs to the adaptive pipeline
                    "static_gate": None
                    if name != "cfsr"
                    else bool(params["adaptive"]) and params.get("static_tol") != -1,
                    # the gate per tile needs the gate (static_tol >= 0)
                    "tile_gate": None
                    if name != "cfsr"
                    else bool(params["adaptive"])
                    and params.get("static_tol") != -1
                    and params.get("static_tile") != 0,
                    "ms_per_frame": sec * 1e3,
                    "psnr_all": float(np.mean(ps)),
                    "psnr_frames": ps,
                    "fine_fraction": None if fine is None else float(fine.mean()),
                }
            )
            bar.update()
    for r in rows:  # cost relative to TFP and to the always-full pipeline on the same scene
        same = {_variant(x): x for x in rows if x["scenario"] == r["scenario"]}
        r["x_tfp_cost"] = r["ms_per_frame"] / same["tfp"]["ms_per_frame"]
        full = same.get("cfsr always-full")
        if r["method"] == "cfsr" and full:
            r["speedup_vs_full"] = full["ms_per_frame"] / r["ms_per_frame"]
            r["psnr_delta_vs_full"] = r["psnr_all"] - full["psnr_all"]
            deltas = [a - b for a, b in zip(r["psnr_frames"], full["psnr_frames"], strict=True)]
            r["psnr_delta_worst_frame"] = max(deltas, key=abs)
    return {"rows": rows, "steps": steps, "times": times}


def _variant(r: dict[str, Any]) -> str:
    if r["adaptive"] is None:
        return r["method"]
    if not r["adaptive"]:
        return "cfsr always-full"
    if not r["static_gate"]:
        return "cfsr adaptive, gate off"
    return "cfsr adaptive" if r["tile_gate"] else "cfsr adaptive, tiles off"


def print_sweep(res: dict[str, Any]) -> None:
    rows = [{**r, "variant": _variant(r)} for r in res["rows"]]
    print(
        format_rows(
            rows,
            [
                ("scenario", "scene", ""),
                ("motion_fraction", "moving", ".0%"),
                ("variant", "pipeline", ""),
                ("ms_per_frame", "ms/frame", ".1f"),
                ("x_tfp_cost", "x TFP cost", ".1f"),
                ("speedup_vs_full", "speed-up", ".2f"),
                ("psnr_all", "PSNR all", ".2f"),
                ("psnr_delta_vs_full", "dPSNR vs full", "+.3f"),
                ("psnr_delta_worst_frame", "worst frame", "+.3f"),
                ("fine_fraction", "fine mask", ".0%"),
            ],
        )
    )


def tiers(args: argparse.Namespace, bar) -> dict[str, Any]:
    """``--tiers``: :func:`cfsr.bench.tier_rows`; ``--dense``: :func:`cfsr.bench.carried_rows`
    (both on ``--scenes``, default every simulated scene; ``--quick``: disk and car)."""
    scenes = (
        [s.strip() for s in args.scenes.split(",") if s.strip()]
        if args.scenes
        else (["disk", "car"] if args.quick else list(SCENES))
    )
    out: dict[str, Any] = {"scenes": scenes}
    bar.reset(total=int(args.tiers) + int(args.dense))
    if args.tiers:
        bar.set_description("quality tiers")
        out["tiers"] = tier_rows(scenes, rounds=1 if args.quick else 3)
        bar.update()
    if args.dense:
        bar.set_description("dense output")
        out["dense"] = carried_rows(scenes, rounds=1 if args.quick else 2)
        bar.update()
    return out


def print_tiers(res: dict[str, Any]) -> None:
    if res.get("tiers"):
        print(
            f"quality tiers: PSNR in dB, loss against full (bars {TIER_BARS[0]} whole, "
            f"{TIER_BARS[1]} motion), CPU ms per isolated frame where measured"
        )
        print(
            format_rows(
                res["tiers"],
                [
                    ("scene", "scene", ""),
                    ("tier", "setting", ""),
                    ("psnr_all", "PSNR all", ".2f"),
                    ("psnr_motion", "PSNR motion", ".2f"),
                    ("d_all", "d all", "+.2f"),
                    ("d_motion", "d motion", "+.2f"),
                    ("within_bars", "in bars", ""),
                    ("above_csr", "> CSR", ""),
                    ("ms_per_frame", "CPU ms", ".1f"),
                    ("x_full_cost", "x full", ".2f"),
                ],
            )
        )
    if res.get("dense"):
        print("dense output carried from frame to frame against the same frames isolated:")
        print(
            format_rows(
                res["dense"],
                [
                    ("scene", "scene", ""),
                    ("stride", "stride", ""),
                    ("psnr_all_isolated", "all iso", ".2f"),
                    ("d_all", "d all", "+.3f"),
                    ("psnr_motion_isolated", "motion iso", ".2f"),
                    ("d_motion", "d motion", "+.3f"),
                    ("ms_isolated", "CPU ms iso", ".1f"),
                    ("ms_carried", "CPU ms carried", ".1f"),
                    ("speedup", "x cheaper", ".2f"),
                ],
            )
        )
