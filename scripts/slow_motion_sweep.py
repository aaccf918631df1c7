"""CFSR against every baseline on the slow-motion scenes at other settings than the named ones.

The named scenes (``vibrate``, ``vibrate_mover``, ``drift``, ``pan``) are in ``cfsr bench`` and
``cfsr evaluate``; this sweeps their options (vibration amplitude and frequency, drift speed)
with the same geometry and scoring (``cfsr.evaluation``: display = rate / rate_scale * 255,
PSNR whole frame and inside the true motion mask, mean over the output steps)::

    python scripts/slow_motion_sweep.py                       # the default sweep
    python scripts/slow_motion_sweep.py --cases vibrate:amplitude=3,hz=200 drift:speed=0.02
    python scripts/slow_motion_sweep.py --json sweep.json

Prints one line per case: CFSR (whole / motion), the best other method on each, and the lead.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

DEFAULT_CASES = (
    "vibrate:amplitude=0.5,hz=20",
    "vibrate:amplitude=0.5,hz=200",
    "vibrate:amplitude=3,hz=20",
    "vibrate:amplitude=3,hz=200",
    "vibrate_mover:amplitude=3,hz=200",
    "drift:speed=0.001",
    "drift:speed=0.02",
)
WINDOWS = (8, 16, 32, 64, 128, 160)
TFPS = [f"tfp:window={w},mode={m}" for w in WINDOWS for m in ("trailing", "centred")]
OTHERS = ["tfi", *TFPS, "tfa", "tfstp", "snm", "csr"]


def _case(text: str) -> tuple[str, dict[str, float]]:
    name, _, rest = text.partition(":")
    opts = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        opts[k.strip()] = float(v)
    return name.strip(), opts


def run_case(text: str, *, steps: int, times: list[int], height: int, width: int) -> dict[str, Any]:
    from cfsr.api import reconstruct_outputs
    from cfsr.display import to_display
    from cfsr.evaluation import _score_frames, parse_method_spec
    from cfsr.simulate import make_scene, simulate
    from cfsr.spikes import SpikeRecording

    name, opts = _case(text)
    sim = simulate(make_scene(name, height=height, width=width, **opts), steps, seed=0)
    gain = sim.rate_scale
    gts = [to_display(sim.ideal_rate(t), gain=gain) for t in times]
    masks = [sim.motion_mask(t) for t in times]
    rec = SpikeRecording.from_array(sim.spikes, meta={"gain": gain})
    scores = {}
    for label in [*OTHERS, "cfsr", "cfsr:slow_reach=0"]:
        spec = parse_method_spec(label)
        outs = reconstruct_outputs(rec, spec.name, times, preset=spec.preset, params=spec.params)
        row = _score_frames(outs, gts, masks, gain)
        scores[label] = (row["psnr_all"], row["psnr_motion"])
    return {"case": text, "scores": scores}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), help="SCENE:KEY=V,...")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--height", type=int, default=250)
    ap.add_argument("--width", type=int, default=400)
    ap.add_argument("--json", help="write the scores here")
    a = ap.parse_args(argv)
    times = [a.steps // 2 - 200, a.steps // 2, a.steps // 2 + 200]
    results = []
    for case in a.cases:
        res = run_case(case, steps=a.steps, times=times, height=a.height, width=a.width)
        results.append(res)
        sc = res["scores"]
        cells = []
        for k, what in ((0, "whole"), (1, "motion")):
            best = max(OTHERS, key=lambda m: sc[m][k])
            lead = sc["cfsr"][k] - sc[best][k]
            cells.append(
                f"{what} {sc['cfsr'][k]:.2f} (without stage {sc['cfsr:slow_reach=0'][k]:.2f}), "
                f"best other {best} {sc[best][k]:.2f}, lead {lead:+.2f}"
            )
        print(f"{case:34s} " + " | ".join(cells), flush=True)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
