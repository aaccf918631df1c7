"""SNM: the spiking neural model of Zhu et al. (CVPR 2020), a baseline of the CFSR paper.

The original is a three-layer spiking network: a motion local excitation layer, a spike refining
layer and a visual reconstruction layer with adaptive-threshold (STDP) neurons; motion/static
labels come from an MRF solved by graph cut. No reference implementation is public, so this is
a reduced, documented reading with the same four stages:

1. **Motion confidence** (local excitation): each pixel's excitation is the log ratio between its
   short-term rate (TFI, the interval containing t, Eq. 3) and its long-term rate (spike count
   over ``long_window`` steps centred on t); the excitations of the 3 x 3 neighbourhood are
   averaged (the local excitatory connections) and mapped to a confidence
   ``c = 1 - exp(-e / motion_sigma)`` in [0, 1).
2. **Graph-cut labels**: a binary MRF with data costs ``-log c`` (motion) and ``-log(1 - c)``
   (static) and a Potts smoothness term of weight ``smoothness`` on the 4-neighbour grid,
   minimised exactly by a max-flow/min-cut (PyMaxflow, Boykov-Kolmogorov).
3. **Refractory refinement**: in the motion region the ``motion_threshold`` intervals nearest t
   are taken, and a spike arriving sooner than ``refractory`` times their median interval after
   the previously kept spike is dropped as a refractory/noise spike.
4. **Adaptive-threshold reconstruction**: the reconstruction neuron of a motion pixel fires after
   ``motion_threshold`` (refined) intervals -- a short integration -- and that of a static pixel
   integrates the whole ``long_window``; the rate is intervals / time they span (motion) or count
   / window (static).

What is missing against the paper: the spiking dynamics themselves (LIF membranes, STDP
learning of the thresholds over time) are replaced by their steady-state equivalents above,
and the motion excitation uses interval statistics rather than synaptic delays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfsr.methods.registry import (
    MAX_UNPACKED_STEPS,
    Method,
    MethodSettings,
    Output,
    Param,
    register,
)
from cfsr.methods.tfa import adaptive_rate
from cfsr.methods.tfi import tfi_rate
from cfsr.methods.tfp import TfpMode, tfp_extent, tfp_rate

__all__ = ["motion_confidence", "graph_cut_labels", "snm_rate"]

_EPS = 1e-6


def _box3(a: np.ndarray) -> np.ndarray:
    """Mean over the 3 x 3 neighbourhood (edge-replicated)."""
    p = np.pad(a, 1, mode="edge")
    h, w = a.shape
    s = np.zeros((h, w), np.float64)
    for dy in range(3):
        for dx in range(3):
            s += p[dy : dy + h, dx : dx + w]
    return s / 9.0


def motion_confidence(
    spikes: np.ndarray, center: int, *, long_window: int, max_isi: int, motion_sigma: float
) -> np.ndarray:
    """Motion confidence in [0, 1) per pixel (stage 1), float64 (H, W)."""
    short = tfi_rate(spikes, center, max_isi=max_isi).astype(np.float64)
    long_ = tfp_rate(spikes, center, window=long_window, mode=TfpMode.CENTRED).astype(np.float64)
    floor = 1.0 / (2 * max_isi + 2)
    e = np.abs(np.log(np.maximum(short, floor)) - np.log(np.maximum(long_, floor)))
    e = _box3(e)
    return 1.0 - np.exp(-e / max(motion_sigma, _EPS))


def graph_cut_labels(conf: np.ndarray, smoothness: float) -> np.ndarray:
    """Binary MRF labels by min-cut (stage 2): True where motion. Bool (H, W)."""
    import maxflow

    c = np.clip(np.asarray(conf, np.float64), _EPS, 1.0 - _EPS)
    cost_motion = -np.log(c)
    cost_static = -np.log(1.0 - c)
    if smoothness <= 0:
        return cost_motion < cost_static
    g = maxflow.Graph[float]()
    nodes = g.add_grid_nodes(c.shape)
    g.add_grid_edges(nodes, float(smoothness))
    # a node ending in the sink segment (label motion) cuts its source edge: pays cost_motion
    g.add_grid_tedges(nodes, cost_motion, cost_static)
    g.maxflow()
    return np.asarray(g.get_grid_segments(nodes), dtype=bool)


@dataclass(frozen=True)
class SnmSettings(MethodSettings):
    """SNM's parameters (its Param table below)."""

    long_window: int  #: static integration window (centred), steps
    max_isi: int  #: interval search range each side of t, steps
    motion_sigma: float  #: excitation (log ratio) giving confidence 0.63
    smoothness: float  #: graph-cut Potts weight
    motion_threshold: int  #: intervals integrated in motion
    refractory: float  #: refractory fraction of the median interval


def snm_rate(spikes: np.ndarray, center: int, s: SnmSettings) -> tuple[np.ndarray, np.ndarray]:
    """SNM rate (spikes/step, float32) and motion labels (bool) at ``center``."""
    conf = motion_confidence(
        spikes, center, long_window=s.long_window, max_isi=s.max_isi, motion_sigma=s.motion_sigma
    )
    labels = graph_cut_labels(conf, s.smoothness)
    static = tfp_rate(spikes, center, window=s.long_window, mode=TfpMode.CENTRED)
    if not labels.any():
        return np.clip(static, 0.0, 1.0).astype(np.float32), labels
    moving = adaptive_rate(
        spikes,
        center,
        threshold=s.motion_threshold,
        max_window=s.max_isi,
        refractory=s.refractory,
    )
    rate = np.where(labels, moving, static).astype(np.float32)
    return np.clip(rate, 0.0, 1.0), labels


def _window(s: SnmSettings) -> tuple[int, int]:
    before, after = tfp_extent(s.long_window, TfpMode.CENTRED)
    return max(before, s.max_isi), max(after, s.max_isi)


def _compute(window: np.ndarray, center: int, start: int, s: SnmSettings) -> Output:
    rate, labels = snm_rate(window, center, s)
    return Output(rate, {"motion": labels})


register(
    Method(
        name="snm",
        summary="Spiking neural model: motion confidence, graph-cut labels, refractory, "
        "adaptive-threshold reconstruction",
        params={
            # no packed path: the whole window is unpacked, hence the tighter limits
            "long_window": Param.steps(
                160,
                "static integration window (centred)",
                minimum=2,
                maximum=MAX_UNPACKED_STEPS,
            ),
            "max_isi": Param.steps(
                200,
                "interval search range each side of t",
                maximum=MAX_UNPACKED_STEPS // 2,
            ),
            # |log ISI ratio| <= log(40,000) ~ 10.6 for any two intervals within 1 s
            "motion_sigma": Param(
                0.35, "log ratio", "excitation giving confidence 0.63", minimum=1e-3, maximum=20.0
            ),
            "smoothness": Param(
                1.0, "", "graph-cut Potts weight (0: no smoothing)", minimum=0, maximum=1000.0
            ),
            "motion_threshold": Param(
                4, "intervals", "intervals integrated in motion", minimum=1, maximum=1000
            ),
            "refractory": Param(
                0.5, "", "refractory fraction of the median interval", minimum=0.0, maximum=1.0
            ),
        },
        window=_window,
        compute=_compute,
        masks=("motion",),
        reference="Zhu et al., CVPR 2020 (SNM), reduced; see docs/methods.md",
        settings=SnmSettings,
    )
)
