"""Every method's frames and masks on simulated scenes, saved or compared bit for bit.

A refactor that must not change behaviour runs this before (``save``) and after
(``compare``): every method, every preset and the CFSR settings that pick other code paths
(the ``fast`` tier, the whole frame without adaptive skipping, the isi history, the past-only
Eq. 9, no carried work) on the demo scene (the rotating disk, 400 x 250) and on a slow pan
(slow motion and still pixels), at output steps close enough to carry work from one to the
next. ``describe`` also writes ``cfsr.methods()`` as JSON for a diff.

    python scripts/method_outputs.py save before.npz
    python scripts/method_outputs.py compare before.npz
    python scripts/method_outputs.py describe methods.json
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np

import cfsr
from cfsr.simulate import simulate

#: (scene, height, width, steps, output steps)
SCENES = {
    "disk": ("disk", 250, 400, 1300, [700, 732, 764, 1000]),
    "pan": ("pan", 96, 128, 1300, [700, 764, 1000]),
}

#: CFSR settings beyond its presets that take other code paths
CFSR_VARIANTS: dict[str, dict[str, Any]] = {
    "fast": {"quality": "fast"},
    "whole-frame": {"adaptive": False},
    "isi-history": {"mog_estimator": "isi"},
    "past-only": {"mog_sides": "past"},
    "isolated": {"carry_span": 0},
    "no-tiles": {"static_tile": 0, "pm_far_count": 2},
}


def configs() -> list[tuple[str, str, str | None, dict[str, Any]]]:
    """(key, method, preset, params) for every method, preset and CFSR variant."""
    out = []
    for name, desc in cfsr.methods().items():
        out.append((f"{name}", name, None, {}))
        for preset in desc["presets"]:
            out.append((f"{name}@{preset}", name, preset, {}))
    out += [(f"cfsr+{k}", "cfsr", None, v) for k, v in CFSR_VARIANTS.items()]
    return out


def outputs() -> dict[str, np.ndarray]:
    """Every frame and mask, keyed ``scene/config/rate`` and ``scene/config/mask``."""
    got: dict[str, np.ndarray] = {}
    for scene, (name, h, w, steps, times) in SCENES.items():
        sim = simulate(name, steps, seed=0, height=h, width=w)
        for key, method, preset, params in configs():
            rates, masks = cfsr.reconstruct(
                sim.spikes, method, times, preset=preset, return_masks=True, workers=1, **params
            )
            got[f"{scene}/{key}/rate"] = rates
            for mname, m in masks.items():
                got[f"{scene}/{key}/{mname}"] = m
            print(f"{scene}/{key}", file=sys.stderr, flush=True)
    return got


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("action", choices=("save", "compare", "describe"))
    ap.add_argument("path")
    a = ap.parse_args(argv)
    if a.action == "describe":
        with open(a.path, "w") as f:
            json.dump(cfsr.methods(), f, indent=1, sort_keys=True)
        return 0
    if a.action == "save":
        np.savez_compressed(a.path, **outputs())
        return 0
    ref = dict(np.load(a.path))
    now = outputs()
    bad = sorted(k for k in ref.keys() | now.keys()
                 if k not in ref or k not in now or not np.array_equal(ref[k], now[k]))
    for k in bad:
        print(f"DIFFERS {k}")
    print(f"{len(ref)} arrays before, {len(now)} now, {len(bad)} differ")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
