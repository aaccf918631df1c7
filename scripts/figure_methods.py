"""The README's figure: TFI, TFP, CSR and CFSR beside the ground truth on one simulated scene,
with each reconstruction's PSNR against the truth (8-bit display, the bench's rule).

    python scripts/figure_methods.py [--scene fan] [--out docs/img/methods.png]

Uses only the library (simulator, reconstructions, metrics) and Pillow; the numbers in the
picture are computed here, from the same frame that is shown.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

import cfsr
from cfsr.display import to_display
from cfsr.metrics import psnr
from cfsr.simulate import simulate

METHODS = ("tfi", "tfp", "csr", "cfsr")
LABEL_H = 22  # pixels of caption band above each picture


def _font(size: int) -> ImageFont.ImageFont:
    for name in ("DejaVuSans.ttf", "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf"):
        try:
            return ImageFont.truetype(name, size)
        except OSError:
            continue
    return ImageFont.load_default()


def make_figure(scene: str, steps: int, t: int, out: Path, *, crop: bool = True) -> dict:
    """Writes the PNG to ``out``; returns {method: PSNR dB} of the frame shown."""
    sim = simulate(scene, steps, seed=0)
    gain = sim.rate_scale
    truth = to_display(sim.ideal_rate(t), gain=gain)
    rec = cfsr.SpikeRecording.from_array(sim.spikes, meta={"gain": gain})
    panels = [("ground truth", truth)]
    scores = {}
    for m in METHODS:
        rate = cfsr.reconstruct(rec, m, [t])[0]
        img = to_display(rate, gain=gain)
        scores[m] = float(psnr(truth, img))
        panels.append((f"{m.upper()}  {scores[m]:.1f} dB", img))
    if crop:  # the moving part of the scene, with a margin: where the methods differ
        ys, xs = np.nonzero(sim.motion_mask(t))
        if ys.size:
            m = 12
            y0, y1 = max(0, ys.min() - m), min(truth.shape[0], ys.max() + m + 1)
            x0, x1 = max(0, xs.min() - m), min(truth.shape[1], xs.max() + m + 1)
            panels = [(n, im[y0:y1, x0:x1]) for n, im in panels]
    h, w = panels[0][1].shape
    scale = max(1, round(220 / h))
    gap = 6
    cols = len(panels)
    canvas = Image.new("L", (cols * w * scale + (cols - 1) * gap, h * scale + LABEL_H), 255)
    draw = ImageDraw.Draw(canvas)
    font = _font(14)
    for i, (name, im) in enumerate(panels):
        x = i * (w * scale + gap)
        pic = Image.fromarray(im).resize((w * scale, h * scale), Image.NEAREST)
        canvas.paste(pic, (x, LABEL_H))
        draw.text((x + 4, 3), name, fill=0, font=font)
    out.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(out, optimize=True)
    return scores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="fan", help="simulator scene (cfsr simulate --help)")
    ap.add_argument("--steps", type=int, default=2000, help="steps simulated")
    ap.add_argument("--t", type=int, default=1000, help="output step")
    ap.add_argument("--out", type=Path, default=Path("docs/img/methods.png"))
    args = ap.parse_args()
    scores = make_figure(args.scene, args.steps, args.t, args.out)
    print(args.out, ", ".join(f"{m} {v:.2f} dB" for m, v in scores.items()))


if __name__ == "__main__":
    main()
