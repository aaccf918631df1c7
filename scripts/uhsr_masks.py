"""CFSR's masks on the real uhsr capture (Spike-Zoo's 250 x 250, no ground truth): the share of
pixels each mask marks, and a picture of the reconstruction with the coarse (red) and fine
(green) masks over it, to see whether the fine mask covers the moving object or the noise.

    python scripts/uhsr_masks.py [--data ../shared/data] [--out docs/uhsr_masks.png] [-t 100]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

import cfsr

REPO = Path(__file__).resolve().parents[1]


def overlay(rate: np.ndarray, masks: dict[str, np.ndarray], gain: float) -> np.ndarray:
    """8-bit gray reconstruction with coarse (red) and fine (green) masks blended at 45 %."""
    g = cfsr.to_display(rate, gain=gain).astype(np.float32)
    rgb = np.repeat(g[..., None], 3, axis=2)
    for name, colour in (("coarse", (255, 64, 64)), ("fine", (64, 255, 96))):
        m = masks.get(name)
        if m is not None:
            rgb[m] = 0.55 * rgb[m] + 0.45 * np.asarray(colour, np.float32)
    return rgb.clip(0, 255).astype(np.uint8)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "uhsr_masks.png")
    ap.add_argument("-t", "--times", default="60,100,140", help="output steps")
    args = ap.parse_args()
    rec = cfsr.read_npz(args.data / "real" / "uhsr.npz")
    times = [int(t) for t in args.times.split(",")]
    rates, masks = cfsr.reconstruct(rec, "cfsr", times, return_masks=True)
    gain = float(np.percentile(rates, 99.5)) or 1.0
    tiles, report = [], []
    for i, t in enumerate(times):
        m = {k: v[i] for k, v in masks.items()}
        tiles.append(overlay(rates[i], m, gain))
        shares = {f"{k}_share": round(float(v.mean()), 4) for k, v in m.items()}
        report.append({"step": t, **shares})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(tiles, axis=1)).save(args.out)
    print(json.dumps(report, indent=1))
    print(f"picture: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
