"""TFSTP: texture from short-term plasticity (Zheng et al.; baseline of the CFSR paper).

Each pixel drives a Tsodyks-Markram synapse: at every spike, with ``dt`` the interval since the
previous spike (steps),

.. math::  R \\leftarrow 1 - (1 - R (1 - u))\\, e^{-dt / D}
.. math::  u \\leftarrow u_0 + (u + f (1 - u) - u_0)\\, e^{-dt / F}

For a steady train of period dt both states converge to fixed points that are monotonic in dt,
so inverting them gives the rate (the "steady-state inversion" of the method):

.. math::  \\rho_u = -1 / (F \\log\\frac{u - u_0}{u (1 - f) + f - u_0}), \\qquad
           \\rho_R = -1 / (D \\log\\frac{1 - R}{1 - R (1 - u)})

Parameters follow SpikeCV's TFSTP (``u0 = 0.15, D = 1, F = 10, f = 0.15``, time unit one step).

Differences from SpikeCV, on purpose:

* Output is a rate in spikes per step: the mean of the two estimates that are valid (the log's
  argument in (0, 1)), each clipped to 1. SpikeCV adds them, then min-max normalises and
  histogram-equalises each frame: display steps that destroy the units (and frame-to-frame
  comparability).
* SpikeCV's ``rho_u`` divides by ``F - u0 + u (1 - f)``; solving the fixed point gives
  ``f - u0 + u (1 - f)`` (lower-case f), used here.
* Pure function of the window: the synapse starts at ``R = 1, u = u0`` ``warmup`` steps before
  t (the state forgets its start within a few spikes, ~F steps) and is updated causally up to t
  (SpikeCV's "online" mode), once per pixel per spike in a vectorised numba kernel -- no
  per-pixel Python loops.
* A pixel with fewer than three spikes in the warm-up (too few updates to invert) gets the
  count rate ``spikes / steps`` over the warm-up, as TFP would.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numba import njit, prange

from cfsr.methods.registry import (
    MAX_UNPACKED_STEPS,
    MAX_WINDOW_STEPS,
    Method,
    Output,
    Param,
    register,
)

__all__ = ["stp_rate"]


@njit(parallel=True, cache=True)
def _stp_kernel(spikes, lo, c, u0, d_tau, f_tau, f_inc, out):  # pragma: no cover - numba
    _, h, w = spikes.shape
    length = c - lo + 1
    for y in prange(h):
        r_st = np.ones(w)
        u_st = np.full(w, u0)
        last = np.full(w, -1, np.int64)
        nsp = np.zeros(w, np.int64)
        # time in the middle, contiguous x innermost
        for t in range(lo, c + 1):
            for x in range(w):
                if spikes[t, y, x]:
                    if last[x] >= 0:
                        dt = t - last[x]
                        r = r_st[x]
                        u = u_st[x]
                        r_st[x] = 1.0 - (1.0 - r * (1.0 - u)) * math.exp(-dt / d_tau)
                        u_st[x] = u0 + (u + f_inc * (1.0 - u) - u0) * math.exp(-dt / f_tau)
                    last[x] = t
                    nsp[x] += 1
        for x in range(w):
            if nsp[x] < 3:
                out[y, x] = nsp[x] / length
                continue
            u = u_st[x]
            r = r_st[x]
            acc = 0.0
            k = 0
            num = u - u0
            den = u * (1.0 - f_inc) + f_inc - u0
            if num > 0.0 and den > 0.0 and num < den:
                rho = -1.0 / (f_tau * math.log(num / den))
                if rho > 0.0:
                    acc += min(rho, 1.0)
                    k += 1
            num = 1.0 - r
            den = 1.0 - r * (1.0 - u)
            if num > 0.0 and den > 0.0 and num < den:
                rho = -1.0 / (d_tau * math.log(num / den))
                if rho > 0.0:
                    acc += min(rho, 1.0)
                    k += 1
            if k > 0:
                out[y, x] = acc / k
            else:
                out[y, x] = nsp[x] / length
    return out


def stp_rate(
    spikes: np.ndarray,
    center: int,
    *,
    warmup: int = 400,
    u0: float = 0.15,
    D: float = 1.0,
    F: float = 10.0,
    f: float = 0.15,
) -> np.ndarray:
    """TFSTP rate at ``center`` (spikes/step, float32 (H, W) in [0, 1]).

    Parameters
    ----------
    spikes : ndarray (n, H, W) uint8 0/1
    center : int
        Index of the output step t (causal: spikes after t are not used).
    warmup : int
        Steps before t over which the synapse state is built.
    u0, f : float
        Baseline and increment of the utilisation u (dimensionless).
    D, F : float
        Recovery and facilitation time constants (steps).
    """
    n, h, w = spikes.shape
    if not 0 <= center < n:
        raise ValueError(f"center {center} outside window of {n} steps")
    if not (0.0 < u0 < 1.0 and 0.0 <= f < 1.0 and D > 0 and F > 0):
        raise ValueError(f"bad STP parameters u0={u0} f={f} D={D} F={F}")
    lo = max(0, center - warmup)
    out = np.empty((h, w), np.float32)
    return _stp_kernel(
        np.ascontiguousarray(spikes, dtype=np.uint8),
        lo,
        center,
        float(u0),
        float(D),
        float(F),
        float(f),
        out,
    )


def _compute(window: np.ndarray, center: int, start: int, p: Mapping[str, Any]) -> Output:
    r = stp_rate(window, center, warmup=p["warmup"], u0=p["u0"], D=p["D"], F=p["F"], f=p["f"])
    return Output(r)


register(
    Method(
        name="tfstp",
        summary="Texture from short-term plasticity: steady-state inversion of STP synapses",
        params={
            # no packed path: the whole window is unpacked, hence the tighter limit (the
            # state forgets its start within a few spikes, ~F steps)
            "warmup": Param(
                400,
                "steps",
                "steps before t that build the synapse state",
                minimum=1,
                maximum=MAX_UNPACKED_STEPS,
            ),
            "u0": Param(0.15, "", "baseline utilisation u0", minimum=1e-6, maximum=0.999),
            "D": Param(
                1.0,
                "steps",
                "recovery time constant tau_D",
                minimum=1e-3,
                maximum=float(MAX_WINDOW_STEPS),
            ),
            "F": Param(
                10.0,
                "steps",
                "facilitation time constant tau_F",
                minimum=1e-3,
                maximum=float(MAX_WINDOW_STEPS),
            ),
            "f": Param(0.15, "", "facilitation increment f", minimum=0.0, maximum=0.999),
        },
        window=lambda p: (p["warmup"], 0),
        compute=_compute,
        presets={"spikecv": {"u0": 0.15, "D": 1.0, "F": 10.0, "f": 0.15}},
        reference="Zheng et al., TFSTP (CVPR 2021 / TPAMI 2023); SpikeCV tfstp.py",
    )
)
