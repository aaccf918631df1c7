"""Integrate-and-fire spike sensor over a :class:`~cfsr.simulate.scenes.Scene`.

Model, per pixel and per step ``t`` (1 step = 25 us at 40 kHz)::

    potential += gain_px * I(t) + dark_px        # charge, in units of the nominal threshold
    if potential >= threshold_px:                 # at most one spike per step
        spike; potential -= threshold_px          # subtractive reset

with a uniform random initial potential in ``[0, threshold_px)`` (so the first frames already
fire at steady-state rates, as in REDS / Spike-Zoo / SpikeCV simulations). The expected firing
rate at intensity ``I`` is ``(gain_px * I + dark_px) / threshold_px`` spikes per step (clipped
to 1); :attr:`Sensor.rate_scale` is the rate at intensity 1.0 of an ideal pixel,
``gain / threshold``, and is the natural display gain (rate shown as white).

Defaults: ``gain = 0.5 * scene.illumination``, ``threshold = 1.0`` -> ``rate_scale = 0.5``
spikes/step: a mid-grey pixel (I = 0.5) fires every 4 steps, white every 2 steps. This is close
to the REDS simulations (``rate = 0.6`` for white) and to the SPCS simulator (raw 0..255
intensity, threshold 400 -> 0.64 for white). The ``lowlight`` scene has illumination 0.1, so
``rate_scale = 0.05``.

Optional noise (:class:`Noise`): SPCS-like fixed-pattern noise (per-pixel threshold mismatch,
gain spread, dark current: a charge added every step, independent of light), hot pixels (a few
pixels with a dark current far above the rest), dead pixels (never fire), and optional
temporal photon shot noise. The hot and dead pixels are the true defect map
(:attr:`Sensor.defect_map`).
Everything is deterministic for a given ``seed``, whatever the chunk size or thread count.
Without an explicit ``noise`` the sensor uses the scene's own (``Scene.noise``: the ``noisy``
scene has the ``sensor`` preset, every other scene none).

Sources. SPCS ("the first spiking camera simulator") comes with SCFlow: Hu et al., "Optical
flow estimation for spiking camera" (arXiv 2110.03916); the ``spcs`` preset's values are those
this module has always used for it. SpikingSIM (github.com/Evin-X/SpikingSIM) adds
light-independent "inherent noise" spikes (about 0.007 per pixel-step), which our dark current
models in integrate-and-fire form. Hu et al., "Spike stream denoising via spike camera
simulation" (arXiv 2304.03129) derive a spike-camera noise model from the pixel circuit, with
temporal and spatial (fixed-pattern) noise measured on a real camera; we took no numbers from
it. Hot pixels and the ``sensor`` preset's values are our own choices, except its gain spread
and mean dark current (SPCS); see :data:`NOISE_PRESETS` and docs/methods.md.

Without shot noise the model is deterministic given the initial potential, so a static pixel's
inter-spike interval only alternates between ``floor(1/r)`` and ``ceil(1/r)``: TFI is then
exact up to that quantisation, which flatters it at low rates (``lowlight``). Use
``noise="shot"`` for a regime where TFI also suffers from temporal noise.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any, NamedTuple

import numpy as np
from numba import prange

from cfsr._jit import njit
from cfsr._splitmix import GOLDEN, mix64
from cfsr.defects.defect_map import DefectMap
from cfsr.simulate.noise import NOISE_PRESETS, Noise
from cfsr.simulate.scenes import Scene

__all__ = ["DEFAULT_GAIN", "DEFAULT_THRESHOLD", "NOISE_PRESETS", "Noise", "Sensor"]

#: Charge per step at intensity 1.0, in units of the nominal threshold (times illumination).
DEFAULT_GAIN = 0.5
#: Nominal firing threshold (charge units).
DEFAULT_THRESHOLD = 1.0

_CHUNK = 128  # steps rendered and integrated per kernel call


# --------------------------------------------------------------------------- kernel


@njit(helper=True)
def _uniform(state):  # pragma: no cover - numba
    """Next (u in (0, 1], state) of a splitmix64 stream."""
    state = state + GOLDEN
    u = ((mix64(state) >> np.uint64(11)) + np.uint64(1)) * (1.0 / 9007199254740992.0)
    return u, state


@njit(helper=True)
def _poisson(lam, state):  # pragma: no cover - numba
    """Poisson(lam) draw (normal approximation for lam >= 12) and the advanced state."""
    if lam <= 0.0:
        return 0.0, state
    if lam < 12.0:
        limit = math.exp(-lam)
        k = -1.0
        p = 1.0
        while True:
            u, state = _uniform(state)
            p *= u
            k += 1.0
            if p <= limit:
                break
        return k, state
    u1, state = _uniform(state)
    u2, state = _uniform(state)
    z = math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
    return max(0.0, lam + math.sqrt(lam) * z), state


class _Pixels(NamedTuple):
    """The sensor's per-pixel maps (one row of each inside the kernels)."""

    gain: np.ndarray  #: float64: charge per unit intensity per step
    dark: np.ndarray  #: float64: dark charge per step
    thr: np.ndarray  #: float64: firing threshold
    pot: np.ndarray  #: float64: membrane potential, carried between calls


class _Light(NamedTuple):
    """What the sensor sees: ``bg[y, x]`` outside the ROI, ``dyn[t, y - oy, x - ox]`` in it."""

    bg: np.ndarray  #: float (H, W)
    dyn: np.ndarray  #: float (n, RH, RW)
    oy: int
    ox: int


class _Shot(NamedTuple):
    """Photon shot noise: ``epc`` electrons per unit charge (0: none), the noise stream's
    ``seed`` and the first step ``t0`` of the call."""

    epc: float
    seed: np.uint64
    t0: np.int64


@njit(helper=True)
def _threshold(p, th):  # pragma: no cover - numba
    """Fire on charge ``p`` against threshold ``th``: (spike 0/1, potential left)."""
    if p >= th:
        p -= th
        # charge above one threshold per step saturates at one spike/step
        return 1, th if p > th else p
    return 0, p


@njit(helper=True)
def _fire(src, s0, row, out, x0, x1):  # pragma: no cover - numba
    """Integrate one row segment ``x0..x1-1`` for one step; intensity is ``src[x - s0]``;
    ``row``: the row's :class:`_Pixels`."""
    gain, dark, thr, pot = row
    for x in range(x0, x1):
        out[x], pot[x] = _threshold(pot[x] + gain[x] * src[x - s0] + dark[x], thr[x])


@njit(helper=True)
def _fire_shot(src, s0, row, out, x0, x1, epc, state):  # pragma: no cover - numba
    """Like :func:`_fire` with Poisson photon shot noise; ``epc`` = electrons per unit charge."""
    gain, dark, thr, pot = row
    for x in range(x0, x1):
        k, state = _poisson((gain[x] * src[x - s0] + dark[x]) * epc, state)
        out[x], pot[x] = _threshold(pot[x] + k / epc, thr[x])
    return state


@njit(parallel=True)
def _integrate(light, pixels, shot, out):  # pragma: no cover - numba
    """Integrate-and-fire for ``out.shape[0]`` steps; rows in parallel, time in the middle.

    ``light`` (:class:`_Light`) gives the intensity, ``pixels`` (:class:`_Pixels`) the maps;
    ``pot`` carries the membrane potential between calls. With ``shot.epc > 0`` the charge
    is shot-noisy (:class:`_Shot`); the random stream of row ``y`` at step ``t0 + t`` is
    seeded from ``(seed, t0 + t, y)``, so results do not depend on threads or chunking.
    """
    bg, dyn, oy, ox = light
    epc, seed, t0 = shot
    n, h, w = out.shape
    rh = dyn.shape[1]
    rw = dyn.shape[2]
    for y in prange(h):
        iy = y - oy
        in_roi = 0 <= iy < rh and rw > 0 and dyn.shape[0] >= n
        bgy = bg[y]
        row = _Pixels(pixels.gain[y], pixels.dark[y], pixels.thr[y], pixels.pot[y])
        for t in range(n):
            oyt = out[t, y]
            if epc > 0.0:
                key = np.uint64(t0 + t) * GOLDEN + np.uint64(y)
                st = mix64(seed ^ mix64(key))
                if in_roi:
                    st = _fire_shot(bgy, 0, row, oyt, 0, ox, epc, st)
                    st = _fire_shot(dyn[t, iy], ox, row, oyt, ox, ox + rw, epc, st)
                    st = _fire_shot(bgy, 0, row, oyt, ox + rw, w, epc, st)
                else:
                    st = _fire_shot(bgy, 0, row, oyt, 0, w, epc, st)
            elif in_roi:
                _fire(bgy, 0, row, oyt, 0, ox)
                _fire(dyn[t, iy], ox, row, oyt, ox, ox + rw)
                _fire(bgy, 0, row, oyt, ox + rw, w)
            else:
                _fire(bgy, 0, row, oyt, 0, w)
    return out


# --------------------------------------------------------------------------- sensor


class Sensor:
    """A spike camera looking at a scene; :meth:`read` returns the next frames.

    Parameters
    ----------
    scene : Scene
    seed : int
        Seeds the initial potentials and the noise maps (deterministic).
    gain : float, optional
        Charge per step at intensity 1.0 (threshold units); default
        ``DEFAULT_GAIN * scene.illumination``.
    threshold : float
        Nominal threshold (charge units), default 1.0.
    noise : Noise, str, mapping or None
        Sensor noise (see :class:`Noise`); None: the scene's own (``scene.noise``, an ideal
        sensor for every scene but ``noisy``); ``"none"`` for an ideal sensor whatever the scene.
    start : int
        Scene step of the first frame read (so ``read`` returns steps ``start, start+1, ...``).
    """

    def __init__(
        self,
        scene: Scene,
        *,
        seed: int = 0,
        gain: float | None = None,
        threshold: float = DEFAULT_THRESHOLD,
        noise: Noise | str | Mapping[str, Any] | None = None,
        start: int = 0,
    ) -> None:
        if gain is None:
            gain = DEFAULT_GAIN * scene.illumination
        gain = float(gain)
        threshold = float(threshold)
        if not (math.isfinite(gain) and gain > 0):
            raise ValueError(f"gain must be a positive charge per step, got {gain}")
        if not (math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold must be positive, got {threshold}")
        if int(start) < 0:
            raise ValueError(f"start must be a step >= 0, got {start}")
        self.scene = scene
        self.seed = int(seed)
        self.gain = gain
        self.threshold = threshold
        self.noise = Noise.parse(noise if noise is not None else getattr(scene, "noise", None))
        self.start = int(start)
        self.t = int(start)  # scene step of the next frame
        h, w = scene.shape
        rng = np.random.default_rng(self.seed)
        u0 = rng.random((h, w))
        nz = self.noise
        thr = np.full((h, w), threshold, np.float64)
        gmap = np.full((h, w), gain, np.float64)
        dmap = np.full((h, w), nz.dark_rate * threshold, np.float64)
        if nz.threshold_sd:
            thr *= 1.0 + nz.threshold_sd * rng.standard_normal((h, w))
            np.maximum(thr, 0.05 * threshold, out=thr)
        if nz.gain_sd:
            gmap *= 1.0 + nz.gain_sd * rng.standard_normal((h, w))
            np.maximum(gmap, 0.0, out=gmap)
        if nz.dark_rate and nz.dark_sd:
            dmap *= 1.0 + nz.dark_sd * rng.standard_normal((h, w))
            np.maximum(dmap, 0.0, out=dmap)
        hot = np.zeros((h, w), bool)
        if nz.hot_fraction:  # drawn last, so the other maps do not depend on it
            k = min(h * w, max(1, round(nz.hot_fraction * h * w)))
            idx = rng.choice(h * w, size=k, replace=False)
            rates = nz.hot_rate * rng.uniform(0.5, 1.0, size=k)
            hot.ravel()[idx] = True
            dmap.ravel()[idx] += rates * thr.ravel()[idx]  # in darkness: `rates` spikes/step
        dead = np.zeros((h, w), bool)
        if nz.dead_fraction:  # drawn after the hot pixels, among the others
            k = min(int((~hot).sum()), max(1, round(nz.dead_fraction * h * w)))
            idx = rng.choice(np.flatnonzero(~hot), size=k, replace=False)
            dead.ravel()[idx] = True
            gmap[dead] = 0.0
            dmap[dead] = 0.0
        self.hot_mask = hot
        self.dead_mask = dead
        self.threshold_map = thr
        self.gain_map = gmap
        self.dark_map = dmap
        self._pot = u0 * thr  # uniform in [0, threshold_px)
        self._stream_seed = np.uint64(rng.integers(0, 2**63, dtype=np.int64))

    @property
    def defect_map(self) -> DefectMap:
        """The true defect map: the hot and dead pixels drawn from the seed."""
        return DefectMap(self.hot_mask, self.dead_mask, 0, "simulator")

    @property
    def rate_scale(self) -> float:
        """Firing rate (spikes/step) of an ideal pixel at intensity 1.0: ``gain / threshold``."""
        return self.gain / self.threshold

    @property
    def shape(self) -> tuple[int, int]:
        return self.scene.shape

    def read(self, n: int, out: np.ndarray | None = None) -> np.ndarray:
        """Simulate the next ``n`` steps: upright ``(n, H, W)`` uint8 0/1."""
        n = int(n)
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        h, w = self.shape
        if out is None:
            out = np.empty((n, h, w), np.uint8)
        elif out.shape != (n, h, w) or out.dtype != np.uint8:
            raise ValueError(f"out must be uint8 {(n, h, w)}, got {out.dtype} {out.shape}")
        y0, _, x0, _ = self.scene.roi
        for a in range(0, n, _CHUNK):
            b = min(n, a + _CHUNK)
            dyn, _ = self.scene.render_roi(self.t, b - a)
            _integrate(
                _Light(self.scene.background, dyn, y0, x0),
                _Pixels(self.gain_map, self.dark_map, self.threshold_map, self._pot),
                _Shot(
                    self.noise.electrons_per_spike / self.threshold,
                    self._stream_seed,
                    np.int64(self.t),
                ),
                out[a:b],
            )
            self.t += b - a
        return out

    def iter_chunks(self, steps: int, chunk: int = 1024) -> Iterator[np.ndarray]:
        """Yield successive blocks of at most ``chunk`` frames until ``steps`` are read."""
        left = int(steps)
        while left > 0:
            k = min(chunk, left)
            yield self.read(k)
            left -= k

    def rate_from_intensity(self, intensity: np.ndarray) -> np.ndarray:
        """Expected firing rate (spikes/step, float32 in [0, 1]) of each pixel at ``intensity``."""
        r = (self.gain_map * intensity + self.dark_map) / self.threshold_map
        return np.clip(r, 0.0, 1.0).astype(np.float32)

    def params(self) -> dict[str, Any]:
        return {
            "model": "integrate-and-fire, subtractive reset, uniform random initial potential",
            "gain": self.gain,
            "threshold": self.threshold,
            "rate_scale": self.rate_scale,
            "illumination": self.scene.illumination,
            "noise": self.noise.to_dict(),
            "seed": self.seed,
            "start": self.start,
        }
