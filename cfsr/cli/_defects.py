"""``cfsr bench --defects``: every method on a clean and on a defective sensor, with and
without the hot/dead pixel correction; the map's precision and recall over time; what the
correction costs per frame beside each method (:func:`cfsr.defects.evaluate.evaluate_defects`).
"""

from __future__ import annotations

import argparse
from typing import Any

from cfsr.bench import format_rows
from cfsr.defects.evaluate import clean_sensor_flags, evaluate_defects
from cfsr.evaluation import split_method_specs

#: Every method of the accuracy table at its defaults.
DEFECT_METHODS = ("tfi", "tfp", "tfa", "tfstp", "snm", "csr", "cfsr")
QUICK_METHODS = ("tfp", "cfsr")


def defects_bench(args: argparse.Namespace, bar: Any) -> dict[str, Any]:
    methods = (split_method_specs(args.methods) if args.methods
               else list(QUICK_METHODS if args.quick else DEFECT_METHODS))
    scenes = [s.strip() for s in args.scenes.split(",")] if args.scenes else ["disk", "stars"]

    bar.set_description("defects")
    res = evaluate_defects(methods, scenes, steps=args.steps or 1200)
    bar.set_description("clean scenes")
    res["clean_scenes"] = clean_sensor_flags(methods, steps=args.steps or 1200)
    return res


def print_defects(res: dict[str, Any]) -> None:
    print(format_rows(res["rows"], [
        ("method", "method", ""), ("scene", "scene", ""), ("sensor", "sensor", ""),
        ("psnr_all", "PSNR all", ".2f"), ("psnr_motion", "PSNR motion", ".2f"),
        ("ms_per_frame", "ms/frame", ".1f"),
    ]))
    for scene, m in res["maps"].items():
        print(f"\n{scene}: {m['true_hot']} hot, {m['true_dead']} dead; "
              f"{m['clean_flags']} flagged on the clean sensor")
        if "calibration" in m:
            c = m["calibration"]
            print(f"flat-field calibration: hot {c['hot_precision']}/{c['hot_recall']}, dead "
                  f"{c['dead_precision']}/{c['dead_recall']} (precision/recall), gain error "
                  f"{c['gain_rms_error']:.4f} rms against a spread of {c['true_gain_sd']:.4f}")
        print(format_rows(m["over_time"], [
            ("steps", "steps", ""), ("hot_precision", "hot precision", ".3f"),
            ("hot_recall", "hot recall", ".3f"), ("dead_precision", "dead precision", ".3f"),
            ("dead_recall", "dead recall", ".3f"),
        ]))
    print("\nflagged on an ideal sensor: " + ", ".join(
        f"{r['scene']} {r['flags']}" for r in res.get("clean_scenes", [])))
    cost = {k: v for k, v in res["cost"].items() if isinstance(v, dict)}
    print()
    print(format_rows([{"method": k, **v} for k, v in cost.items()], [
        ("method", "method", ""), ("window_steps", "window", ""),
        ("method_ms_per_frame", "method ms", ".1f"), ("ms_per_frame", "offline ms", ".3f"),
        ("fraction", "share", ".3f"), ("copy_ms_per_frame", "copy ms", ".3f"),
        ("copy_fraction", "share", ".3f"), ("live_ms_per_frame", "live ms", ".3f"),
        ("live_fraction", "share", ".3f"), ("upkeep_us_per_step", "upkeep us/step", ".2f"),
    ]))
