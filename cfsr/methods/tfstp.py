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
* Pure function of the window: the synapse starts at ``R = 1, u = u0`` on a grid of absolute
  steps, at the last multiple of ``ceil(warmup / 4)`` steps that lies at least ``warmup``
  steps before t (:func:`state_start`; the state forgets its start within a few spikes, ~F
  steps), and is updated causally up to t (SpikeCV's "online" mode), once per pixel per spike
  in a vectorised numba kernel -- no per-pixel Python loops. The grid is what lets dense
  outputs share work: every output whose start is the same grid step continues one state
  (``memo``) instead of rebuilding it over its whole warm-up, with identical numbers (SpikeCV
  keeps one state for a whole recording, which makes each frame depend on where reading began).
* A pixel with fewer than three spikes since the start (too few updates to invert) gets the
  count rate ``spikes / steps`` over the steps since the start, as TFP would.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from cfsr._bits import unpack_layout
from cfsr._jit import njit
from cfsr.methods.registry import (
    MAX_UNPACKED_STEPS,
    MAX_WINDOW_STEPS,
    Memo,
    Method,
    MethodSettings,
    Output,
    Param,
    register,
)

__all__ = ["stp_rate", "state_start", "state_grid"]

#: Starts per warm-up: the state starts every ``ceil(warmup / STARTS_PER_WARMUP)`` steps, so an
#: isolated frame reads at most 25 % more steps than ``warmup`` while dense frames rebuild a
#: state once per that many steps.
STARTS_PER_WARMUP = 4


class _Stp(NamedTuple):
    """Tsodyks-Markram constants: baseline ``u0`` and increment ``f`` of the utilisation,
    recovery ``d_tau`` and facilitation ``f_tau`` time constants (steps)."""

    u0: float
    d_tau: float
    f_tau: float
    f_inc: float


class _State(NamedTuple):
    """Per-pixel synapse state, ``(H, W)`` each: resources ``r``, utilisation ``u``, the
    absolute step of the last spike ``last`` (-1: none yet) and the spike count ``nsp``."""

    r: np.ndarray  #: float64
    u: np.ndarray  #: float64
    last: np.ndarray  #: int64
    nsp: np.ndarray  #: int64


@njit
def _stp_advance(spikes, t0, st, c):  # pragma: no cover - numba
    """Fold frames ``spikes`` (k, H, W), the first at absolute step ``t0``, into ``st``."""
    k, h, w = spikes.shape
    for y in range(h):
        r_st, u_st, last, nsp = st.r[y], st.u[y], st.last[y], st.nsp[y]
        # time in the middle, contiguous x innermost
        for i in range(k):
            t = t0 + i
            for x in range(w):
                if spikes[i, y, x]:
                    if last[x] >= 0:
                        dt = t - last[x]
                        r = r_st[x]
                        u = u_st[x]
                        r_st[x] = 1.0 - (1.0 - r * (1.0 - u)) * math.exp(-dt / c.d_tau)
                        u_st[x] = c.u0 + (u + c.f_inc * (1.0 - u) - c.u0) * math.exp(-dt / c.f_tau)
                    last[x] = t
                    nsp[x] += 1


@njit
def _stp_invert(st, length, c, out):  # pragma: no cover - numba
    """Steady-state inversion of ``st`` after ``length`` steps (rates into ``out``)."""
    h, w = out.shape
    for y in range(h):
        for x in range(w):
            n = st.nsp[y, x]
            if n < 3:
                out[y, x] = n / length
                continue
            u = st.u[y, x]
            r = st.r[y, x]
            acc = 0.0
            k = 0
            num = u - c.u0
            den = u * (1.0 - c.f_inc) + c.f_inc - c.u0
            if num > 0.0 and den > 0.0 and num < den:
                rho = -1.0 / (c.f_tau * math.log(num / den))
                if rho > 0.0:
                    acc += min(rho, 1.0)
                    k += 1
            num = 1.0 - r
            den = 1.0 - r * (1.0 - u)
            if num > 0.0 and den > 0.0 and num < den:
                rho = -1.0 / (c.d_tau * math.log(num / den))
                if rho > 0.0:
                    acc += min(rho, 1.0)
                    k += 1
            out[y, x] = acc / k if k > 0 else n / length
    return out


def state_grid(warmup: int) -> int:
    """Spacing (steps) of the absolute steps where a synapse state may start."""
    return max(1, -(-int(warmup) // STARTS_PER_WARMUP))


def state_start(t: int, warmup: int, first: int = 0) -> int:
    """Absolute step where the state for output step ``t`` starts: the last multiple of
    :func:`state_grid` at least ``warmup`` steps before ``t``, not before ``first`` (the first
    step there is)."""
    g = state_grid(warmup)
    return max(int(first), ((int(t) - int(warmup)) // g) * g)


@dataclass
class _Memo:
    """A state that output steps sharing its start continue (see :func:`_rate`)."""

    key: tuple[Any, ...]  #: (start, shape, constants)
    step: int  #: last absolute step folded in
    state: _State


FramesFn = Callable[[int, int], np.ndarray]


def _rate(
    frames: FramesFn,
    shape: tuple[int, int],
    t: int,
    start: int,
    c: _Stp,
    memo: Memo | None,
) -> np.ndarray:
    """TFSTP at absolute step ``t`` from a state begun at absolute step ``start``.

    ``frames(a, b)`` gives the unpacked frames of absolute steps ``[a, b)``. ``memo`` (any
    dict the caller keeps for one stream) holds the last state; an output with the same start
    and a later step continues it, folding only the new frames. The floating-point operations
    per pixel are the same in the same order however the steps are split, so the result is
    identical to a fresh computation (tested).
    """
    key = (int(start), shape, tuple(c))
    old = None if memo is None else memo.get("tfstp")
    if old is not None and old.key == key and old.step <= t:
        st, done = old.state, old.step
    else:
        h, w = shape
        st = _State(
            np.ones((h, w)),
            np.full((h, w), c.u0),
            np.full((h, w), -1, np.int64),
            np.zeros((h, w), np.int64),
        )
        done = start - 1
    if t > done:
        _stp_advance(np.ascontiguousarray(frames(done + 1, t + 1), np.uint8), done + 1, st, c)
    if memo is not None:
        memo["tfstp"] = _Memo(key, t, st)
    return _stp_invert(st, t - start + 1, c, np.empty(shape, np.float32))


def _constants(u0: float, D: float, F: float, f: float) -> _Stp:
    if not (0.0 < u0 < 1.0 and 0.0 <= f < 1.0 and D > 0 and F > 0):
        raise ValueError(f"bad STP parameters u0={u0} f={f} D={D} F={F}")
    return _Stp(float(u0), float(D), float(F), float(f))


def stp_rate(
    spikes: np.ndarray,
    center: int,
    *,
    warmup: int = 400,
    u0: float = 0.15,
    D: float = 1.0,
    F: float = 10.0,
    f: float = 0.15,
    start: int = 0,
    memo: Memo | None = None,
) -> np.ndarray:
    """TFSTP rate at ``center`` (spikes/step, float32 (H, W) in [0, 1]).

    Parameters
    ----------
    spikes : ndarray (n, H, W) uint8 0/1
    center : int
        Index of the output step t (causal: spikes after t are not used).
    warmup : int
        Least number of steps before t over which the synapse state is built (it starts at
        :func:`state_start`, up to ``ceil(warmup / 4) - 1`` steps earlier).
    u0, f : float
        Baseline and increment of the utilisation u (dimensionless).
    D, F : float
        Recovery and facilitation time constants (steps).
    start : int
        Absolute step of ``spikes[0]`` (the start grid is absolute, so a window gives the same
        frame wherever it is cut from).
    memo : dict, optional
        Kept by the caller between calls on one stream: dense outputs continue one state.
    """
    n, h, w = spikes.shape
    c = _constants(u0, D, F, f)
    window = lambda a, b: spikes[a - start : b - start]  # noqa: E731 - absolute steps
    return _at(window, (n, h, w), center, start, warmup, c, memo)


def _at(
    frames: FramesFn,
    shape: tuple[int, int, int],
    center: int,
    start: int,
    warmup: int,
    c: _Stp,
    memo: Memo | None,
) -> np.ndarray:
    """TFSTP at index ``center`` of an ``(n, H, W)`` window whose first step is ``start``."""
    n, h, w = shape
    if not 0 <= center < n:
        raise ValueError(f"center {center} outside window of {n} steps")
    t = int(start) + int(center)
    return _rate(frames, (h, w), t, state_start(t, warmup, first=int(start)), c, memo)


@dataclass(frozen=True)
class TfstpSettings(MethodSettings):
    """TFSTP's parameters (its Param table below)."""

    warmup: int  #: least steps before t that build the synapse state
    u0: float  #: baseline utilisation
    D: float  #: recovery time constant tau_D, steps
    F: float  #: facilitation time constant tau_F, steps
    f: float  #: facilitation increment


def _compute(
    window: np.ndarray,
    center: int,
    start: int,
    s: TfstpSettings,
    memo: Memo | None = None,
) -> Output:
    return Output(
        stp_rate(
            window, center, start=start, memo=memo, warmup=s.warmup, u0=s.u0, D=s.D, F=s.F, f=s.f
        )
    )


def _compute_packed(
    packed: np.ndarray,
    layout: Any,
    center: int,
    start: int,
    s: TfstpSettings,
    memo: Memo | None = None,
) -> Output:
    """As :func:`_compute`, unpacking only the frames the state has not folded in yet."""
    packed = np.asarray(packed)
    c = _constants(s.u0, s.D, s.F, s.f)

    def frames(a: int, b: int) -> np.ndarray:
        return unpack_layout(packed[a - start : b - start], layout)

    shape = (packed.shape[0], layout.height, layout.width)
    return Output(_at(frames, shape, center, start, s.warmup, c, memo))


def _window(s: TfstpSettings) -> tuple[int, int]:
    # the state starts up to one grid step before t - warmup
    warmup = s.warmup
    return warmup + state_grid(warmup) - 1, 0


register(
    Method(
        name="tfstp",
        summary="Texture from short-term plasticity: steady-state inversion of STP synapses",
        params={
            # no packed scan: the window's frames are unpacked, hence the tighter limit (the
            # state forgets its start within a few spikes, ~F steps)
            "warmup": Param.steps(
                400,
                "least steps before t that build the synapse state",
                maximum=MAX_UNPACKED_STEPS * STARTS_PER_WARMUP // (STARTS_PER_WARMUP + 1),
            ),
            "u0": Param(0.15, "", "baseline utilisation u0", minimum=1e-6, maximum=0.999),
            "D": Param.steps(
                1.0,
                "recovery time constant tau_D",
                minimum=1e-3,
                maximum=float(MAX_WINDOW_STEPS),
            ),
            "F": Param.steps(
                10.0,
                "facilitation time constant tau_F",
                minimum=1e-3,
                maximum=float(MAX_WINDOW_STEPS),
            ),
            "f": Param(0.15, "", "facilitation increment f", minimum=0.0, maximum=0.999),
        },
        window=_window,
        compute=_compute,
        compute_packed=_compute_packed,
        recurrent=True,
        max_window=MAX_UNPACKED_STEPS,
        presets={"spikecv": {"u0": 0.15, "D": 1.0, "F": 10.0, "f": 0.15}},
        reference="Zheng et al., TFSTP (CVPR 2021 / TPAMI 2023); SpikeCV tfstp.py",
        settings=TfstpSettings,
    )
)
