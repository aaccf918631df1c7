"""The benchmark's plots, in one place: every figure gives a method the same colour, and no
label is cut off at the figure's edge.

matplotlib is an optional extra (``cfsr[bench]``): :func:`have_matplotlib` says whether
plots can be made, and the functions import it only when called (``import cfsr`` never does).

Colours: :data:`METHOD_COLOURS` fixes one colour per registered method (a method's variants,
``cfsr:fast`` or ``tfp:window=32``, share their method's colour and differ by marker); a name
it does not know gets a colour from its name's hash, so it too keeps its colour from plot to
plot. Labels: figures are saved with ``bbox_inches="tight"`` and legends sit outside the
axes, so nothing is clipped whatever the data.
"""

from __future__ import annotations

import importlib.util
import math
import zlib
from collections.abc import Sequence
from typing import Any

from cfsr.bench import pareto_front

__all__ = [
    "METHOD_COLOURS",
    "have_matplotlib",
    "method_colour",
    "plot_metric_bars",
    "plot_pareto",
]

#: One colour per method (colour-blind-safe Okabe-Ito hues first; CFSR and CSR, the ones
#: people compare most, get the two most distinct).
METHOD_COLOURS: dict[str, str] = {
    "cfsr": "#D55E00",  # vermillion
    "csr": "#0072B2",  # blue
    "tfp": "#009E73",  # green
    "tfi": "#CC79A7",  # purple
    "tfa": "#E69F00",  # orange
    "tfstp": "#56B4E9",  # sky blue
    "snm": "#7F7F7F",  # grey
}
_SPARE = ("#8C564B", "#BCBD22", "#17BECF", "#9467BD", "#1F77B4", "#2CA02C", "#F0E442")
_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "h")


def have_matplotlib() -> bool:
    """True when matplotlib can be imported (the ``cfsr[bench]`` extra is installed)."""
    try:
        return importlib.util.find_spec("matplotlib") is not None
    except (ImportError, ValueError):
        return False


def method_colour(name: str) -> str:
    """The colour of method ``name`` (``"cfsr:fast"`` -> the colour of ``cfsr``), the same in
    every plot; a name not in :data:`METHOD_COLOURS` gets one from its name's CRC-32."""
    base = name.partition(":")[0].strip().lower()
    if base in METHOD_COLOURS:
        return METHOD_COLOURS[base]
    return _SPARE[zlib.crc32(base.encode()) % len(_SPARE)]


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _pyplot():
    import matplotlib  # the cfsr[bench] extra

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_pareto(
    rows: Sequence[dict[str, Any]],
    path: str,
    *,
    cost: str = "ms_per_frame",
    score: str = "psnr_all",
    title: str = "run time against error",
) -> str:
    """Cost (ms per output frame, log axis) against ``score`` per method, one panel per scene,
    with each scene's Pareto front dashed; writes a PNG to ``path`` and returns it.

    ``rows`` are ``cfsr bench`` accuracy rows (``method`` spec, ``name`` method name,
    ``scene``, ``cost`` and ``score`` keys); rows whose score is not finite are left out.
    A method's variants share its colour and are told apart by marker, named in the legend.
    """
    plt = _pyplot()
    ok = [r for r in rows if _finite(r.get(score)) and _finite(r.get(cost)) and r[cost] > 0]
    scenes = sorted({r["scene"] for r in ok})
    if not scenes:
        raise ValueError(f"no rows with a finite {score} and {cost} to plot")
    specs = sorted({r["method"] for r in ok}, key=lambda s: (s.partition(":")[0], s))
    marker = {}
    for s in specs:
        n = sum(1 for m in marker if m.partition(":")[0] == s.partition(":")[0])
        marker[s] = _MARKERS[n % len(_MARKERS)]
    ncol = min(3, len(scenes))
    nrow = math.ceil(len(scenes) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.6 * nrow), squeeze=False)
    for ax, scene in zip(axes.ravel(), scenes, strict=False):
        sub = [r for r in ok if r["scene"] == scene]
        for s in specs:
            pts = [r for r in sub if r["method"] == s]
            if pts:
                ax.scatter([r[cost] for r in pts], [r[score] for r in pts], s=34,
                           color=method_colour(s), marker=marker[s], edgecolors="black",
                           linewidths=0.4, zorder=3)
        front = pareto_front(sub, cost=cost, score=score)
        ax.plot([r[cost] for r in front], [r[score] for r in front], "k--", lw=0.8, zorder=2)
        ax.set_xscale("log")
        ax.set_title(scene, fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.tick_params(labelsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("ms per output frame (log)", fontsize=9)
    ylabel = score.replace("_", " ") + (" (dB)" if "psnr" in score else "")
    for ax in axes[:, 0]:
        ax.set_ylabel(ylabel, fontsize=9)
    for ax in axes.ravel()[len(scenes):]:
        ax.axis("off")
    handles = [
        plt.Line2D([], [], linestyle="", marker=marker[s], color=method_colour(s),
                   markeredgecolor="black", markeredgewidth=0.4, markersize=7, label=s)
        for s in specs
    ]
    handles.append(plt.Line2D([], [], linestyle="--", color="black", lw=0.8,
                              label="Pareto front"))
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    # the legend below the panels, outside every axis; bbox_inches="tight" keeps it and every
    # label inside the saved image
    fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.0),
               ncol=min(5, len(handles)), fontsize=8, frameon=False)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_metric_bars(
    rows: Sequence[dict[str, Any]],
    path: str,
    *,
    metric: str = "psnr_all",
    title: str = "",
    methods: Sequence[str] | None = None,
) -> str:
    """Grouped bars of ``metric`` per scene (groups) and method (bars, in ``methods`` order,
    default sorted), one fixed colour per method; writes a PNG to ``path`` and returns it.
    Rows whose metric is not finite are left out (no bar)."""
    plt = _pyplot()
    ok = [r for r in rows if _finite(r.get(metric))]
    if not ok:
        raise ValueError(f"no rows with a finite {metric} to plot")
    scenes = sorted({r["scene"] for r in ok})
    names = list(methods) if methods else sorted({r["method"] for r in ok})
    value = {(r["scene"], r["method"]): r[metric] for r in ok}
    width = 0.8 / max(1, len(names))
    bars = len(scenes) * max(1, len(names))
    fig, ax = plt.subplots(figsize=(min(12.0, max(6.0, 0.2 * bars + 2.0)), 4.0))
    for i, name in enumerate(names):
        xs = [k + (i - (len(names) - 1) / 2) * width for k, s in enumerate(scenes)
              if (s, name) in value]
        ys = [value[(s, name)] for s in scenes if (s, name) in value]
        ax.bar(xs, ys, width=width, color=method_colour(name), label=name,
               edgecolor="black", linewidth=0.3)
    ax.set_xticks(range(len(scenes)))
    ax.set_xticklabels(scenes, fontsize=8, rotation=20, ha="right")
    ax.set_ylabel(metric.replace("_", " ") + (" (dB)" if "psnr" in metric else ""), fontsize=9)
    lo = min(value.values())
    if "psnr" in metric:
        ax.set_ylim(max(0.0, math.floor(lo / 5) * 5 - 5), None)
    ax.grid(axis="y", alpha=0.3)
    ax.tick_params(axis="y", labelsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
