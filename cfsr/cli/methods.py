"""``cfsr methods``: list reconstruction methods with their parameters and defaults."""

from __future__ import annotations

import argparse
import json

from cfsr.methods import methods


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    ms = methods()
    if args.json:
        print(json.dumps(ms, indent=2))
        return 0
    for name, d in ms.items():
        masks = f"  masks: {', '.join(d['masks'])}" if d["masks"] else ""
        print(f"{name:7s} {d['summary']}{masks}")
        if d["reference"]:
            print(f"        ref: {d['reference']}")
        for k, p in d["params"].items():
            unit = f" [{p['unit']}]" if p["unit"] else ""
            rng = f" (range {p['range']})" if p.get("range") else ""
            print(f"        {k} = {p['default']!r}{unit}{rng}  {p['help']}")
        for pn, pv in d["presets"].items():
            print(f"        preset {pn}: {pv}")
    return 0
