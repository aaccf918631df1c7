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
pixels with a dark current far above the rest), and optional temporal photon shot noise.
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

import json
import math
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numba import prange

from cfsr._jit import njit
from cfsr._splitmix import GOLDEN, mix64
from cfsr.layout import STEP_RATE_HZ, Layout
from cfsr.simulate.scenes import Scene, make_scene

__all__ = [
    "DEFAULT_GAIN",
    "DEFAULT_THRESHOLD",
    "NOISE_PRESETS",
    "Noise",
    "Sensor",
    "Simulation",
    "GroundTruth",
    "simulate",
    "simulate_to_dat",
    "gt_path",
    "load_ground_truth",
]

#: Charge per step at intensity 1.0, in units of the nominal threshold (times illumination).
DEFAULT_GAIN = 0.5
#: Nominal firing threshold (charge units).
DEFAULT_THRESHOLD = 1.0

_CHUNK = 128  # steps rendered and integrated per kernel call


# --------------------------------------------------------------------------- noise


@dataclass(frozen=True)
class Noise:
    """Fixed-pattern sensor noise (all per pixel, drawn once from the seed).

    Parameters
    ----------
    threshold_sd : float
        Relative standard deviation of the per-pixel threshold (SPCS: 3/400 = 0.0075).
    gain_sd : float
        Relative standard deviation of the per-pixel gain (SPCS: 0.027).
    dark_rate : float
        Mean dark-current firing rate in spikes per step, i.e. the rate of a pixel in total
        darkness (SPCS: 1/400 = 0.0025).
    dark_sd : float
        Relative standard deviation of the per-pixel dark current (SPCS: 0.008).
    electrons_per_spike : float
        Temporal photon shot noise (ours, not in SPCS): the charge of one threshold counts
        this many photo-electrons, and each step's charge is a Poisson draw of its expected
        electron count (normal approximation above 12 per step). 0 (default) turns it off;
        the ``shot`` preset uses 100 (an illustrative value, not a measured one), giving an
        ISI jitter of about ``1/sqrt(100) = 10 %``. Expected rates are unchanged.
    hot_fraction : float
        Fraction of pixels that are *hot* (ours, not in SPCS): their dark current alone makes
        them fire at ``hot_rate`` times a uniform draw in [0.5, 1] spikes per step, whatever
        the light. Hot pixels are drawn once from the seed (``Sensor.hot_mask``); at least one
        pixel is hot when ``hot_fraction > 0``.
    hot_rate : float
        Dark firing rate of the hottest pixels in spikes per step (at most 1); required
        (> 0) with ``hot_fraction``.
    """

    threshold_sd: float = 0.0
    gain_sd: float = 0.0
    dark_rate: float = 0.0
    dark_sd: float = 0.0
    electrons_per_spike: float = 0.0
    hot_fraction: float = 0.0
    hot_rate: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"noise {f.name}={v!r}: must be a finite number >= 0")
        if self.threshold_sd >= 0.5:
            raise ValueError(f"noise threshold_sd={self.threshold_sd}: must be < 0.5 (relative)")
        if self.dark_rate >= 1:
            raise ValueError(f"noise dark_rate={self.dark_rate}: must be < 1 spike/step")
        if self.hot_fraction > 1:
            raise ValueError(f"noise hot_fraction={self.hot_fraction}: must be <= 1")
        if self.hot_rate > 1:
            raise ValueError(f"noise hot_rate={self.hot_rate}: must be <= 1 spike/step")
        if self.hot_fraction > 0 and self.hot_rate <= 0:
            raise ValueError("noise hot_fraction > 0 needs hot_rate > 0 (spikes/step)")

    @property
    def is_zero(self) -> bool:
        return not any(getattr(self, f.name) for f in fields(self))

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @classmethod
    def parse(cls, spec: str | Mapping[str, Any] | Noise | None) -> Noise:
        """A preset name (``none``, ``spcs``, ``shot``, ``sensor``), ``"NAME=VALUE,..."``
        (optionally after a preset, ``"spcs,dark_rate=0.01"``), a mapping, a Noise, or None
        (no noise)."""
        if spec is None:
            return cls()
        if isinstance(spec, Noise):
            return spec
        if isinstance(spec, Mapping):
            names = {f.name for f in fields(cls)}
            bad = sorted(set(spec) - names)
            if bad:
                raise ValueError(f"unknown noise parameter(s) {bad}; known: {sorted(names)}")
            return cls(**{k: float(v) for k, v in spec.items()})
        base: dict[str, float] = {}
        for part in str(spec).split(","):
            part = part.strip()
            if not part:
                continue
            if "=" in part:
                k, v = (s.strip() for s in part.split("=", 1))
                try:
                    base[k] = float(v)
                except ValueError:
                    raise ValueError(f"noise {k}={v!r}: not a number") from None
            elif part.lower() in NOISE_PRESETS:
                base.update(NOISE_PRESETS[part.lower()].to_dict())
            else:
                raise ValueError(
                    f"unknown noise preset {part!r}; presets: {', '.join(NOISE_PRESETS)}, "
                    "or NAME=VALUE with NAME in "
                    f"{', '.join(f.name for f in fields(cls))}"
                )
        return cls.parse(base)


NOISE_PRESETS: dict[str, Noise] = {
    "none": Noise(),
    "spcs": Noise(threshold_sd=3 / 400, gain_sd=0.027451, dark_rate=1 / 400, dark_sd=0.008),
    "shot": Noise(electrons_per_spike=100.0),
    # Fixed-pattern noise of a real sensor, for the ``noisy`` scene: SPCS's gain spread and
    # mean dark current, and our own choices for the rest (no published spike-camera values
    # verified): threshold mismatch 3 % (4x SPCS), per-pixel dark current spread 50 %, 0.1 %
    # hot pixels firing at 0.25-0.5 spikes/step.
    "sensor": Noise(
        threshold_sd=0.03,
        gain_sd=0.027451,
        dark_rate=1 / 400,
        dark_sd=0.5,
        hot_fraction=0.001,
        hot_rate=0.5,
    ),
}


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
        self.hot_mask = hot
        self.threshold_map = thr
        self.gain_map = gmap
        self.dark_map = dmap
        self._pot = u0 * thr  # uniform in [0, threshold_px)
        self._stream_seed = np.uint64(rng.integers(0, 2**63, dtype=np.int64))

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


# --------------------------------------------------------------------------- simulation


@dataclass
class Simulation:
    """Spikes of a simulated scene with their ground truth.

    Index ``t`` below is the frame index into :attr:`spikes` (scene step ``start + t``).

    Attributes
    ----------
    spikes : ndarray (steps, H, W) uint8 0/1, upright
    scene : Scene
    sensor : Sensor
        The sensor after the run (its per-pixel gain/threshold/dark maps define ``gt_rate``).
    """

    spikes: np.ndarray
    scene: Scene
    sensor: Sensor
    seed: int = 0
    start: int = 0
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        return int(self.spikes.shape[0])

    @property
    def rate_scale(self) -> float:
        """Firing rate (spikes/step) at intensity 1.0 (``gain / threshold``); the display gain."""
        return self.sensor.rate_scale

    def _check(self, t: int) -> int:
        t = int(t)
        if not 0 <= t < self.steps:
            raise ValueError(f"step {t} outside the simulation (0..{self.steps - 1})")
        return t

    def gt_image(self, t: int) -> np.ndarray:
        """Scene intensity at frame ``t``: float32 ``(H, W)`` in [0, 1]."""
        return self.scene.intensity(self.start + self._check(t))

    def gt_rate(self, t: int) -> np.ndarray:
        """Expected firing rate at frame ``t`` (spikes/step, float32), dark current included."""
        return self.sensor.rate_from_intensity(self.gt_image(t))

    def ideal_rate(self, t: int) -> np.ndarray:
        """Rate of an ideal (noise-free) pixel at frame ``t``: ``clip(rate_scale * I, 0, 1)``.

        The evaluation's ground truth: the scene, not the sensor's fixed pattern (equal to
        :meth:`gt_rate` without fixed-pattern noise).
        """
        r = self.rate_scale * self.gt_image(t).astype(np.float64)
        return np.clip(r, 0.0, 1.0).astype(np.float32)

    def motion_mask(self, t: int) -> np.ndarray:
        """True motion mask at frame ``t`` (bool ``(H, W)``)."""
        return self.scene.motion_mask(self.start + self._check(t))

    def describe(self) -> dict[str, Any]:
        return {"scene": self.scene.describe(), "simulator": self.sensor.params(), **self.meta}


def _as_scene(scene: str | Scene, height: int, width: int) -> Scene:
    if isinstance(scene, Scene):
        return scene
    return make_scene(scene, height=height, width=width)


def simulate(
    scene: str | Scene,
    steps: int,
    *,
    seed: int = 0,
    height: int = 250,
    width: int = 400,
    gain: float | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    noise: Noise | str | Mapping[str, Any] | None = None,
    start: int = 0,
    progress: Callable[[int], Any] | None = None,
) -> Simulation:
    """Simulate ``steps`` spike frames of a scene, in memory.

    Parameters
    ----------
    scene : str or Scene
        A name from :data:`~cfsr.simulate.SCENES` or a Scene (then ``height``/``width`` are
        ignored).
    steps : int
        Number of frames (1 step = 25 us).
    seed : int
        Random seed (initial potentials, noise maps); same seed, same spikes.
    height, width : int
        Frame size in pixels (default 400 x 250).
    gain : float, optional
        Charge per step at intensity 1.0 in threshold units; default ``0.5 *
        scene.illumination`` (rate_scale 0.5 spikes/step; 0.05 for ``lowlight``).
    threshold : float
        Nominal threshold (default 1.0).
    noise : Noise, str, mapping or None
        ``None`` (the scene's own: ideal for all but ``noisy``), ``"none"`` (ideal),
        ``"spcs"`` (SPCS-like fixed-pattern noise), ``"sensor"``, ``"shot"`` or
        ``"NAME=VALUE,..."``.
    start : int
        Scene step of frame 0.
    progress : callable, optional
        Called with the number of frames simulated after each block.

    Returns
    -------
    Simulation
        ``spikes`` is ``(steps, H, W)`` uint8; at 400 x 250 that is 100 kB per step, so use
        :func:`simulate_to_dat` for long runs.

    Examples
    --------
    >>> sim = simulate("static", 100, height=16, width=16)
    >>> sim.spikes.shape, sim.rate_scale
    ((100, 16, 16), 0.5)
    """
    steps = int(steps)
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    sc = _as_scene(scene, height, width)
    sensor = Sensor(sc, seed=seed, gain=gain, threshold=threshold, noise=noise, start=start)
    out = np.empty((steps,) + sc.shape, np.uint8)
    block = 1024
    for a in range(0, steps, block):
        b = min(steps, a + block)
        sensor.read(b - a, out=out[a:b])
        if progress is not None:
            progress(b - a)
    return Simulation(out, sc, sensor, seed=int(seed), start=int(start))


def gt_path(dat_path: str | os.PathLike) -> Path:
    """``NAME.dat`` -> ``NAME.gt.npz`` (the ground truth written beside a simulated file)."""
    p = Path(dat_path)
    stem = p.name[: -len(p.suffix)] if p.suffix else p.name
    return p.with_name(stem + ".gt.npz")


def simulate_to_dat(
    scene: str | Scene,
    steps: int,
    path: str | os.PathLike,
    *,
    seed: int = 0,
    gt_every: int | None = 100,
    height: int = 250,
    width: int = 400,
    gain: float | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    noise: Noise | str | Mapping[str, Any] | None = None,
    start: int = 0,
    chunk: int = 1024,
    progress: Callable[[int], Any] | None = None,
) -> Path:
    """Simulate a scene straight to a ``.dat`` file, its sidecar and a ground-truth NPZ.

    Frames are simulated and written ``chunk`` at a time, so memory stays bounded however long
    the run. Writes

    * ``path``: the spikes, ``.dat`` layout (rows upside down, LSB first);
    * ``path.json``: sidecar with ``gain`` = rate_scale (spikes/step shown as white), the scene
      description, ``seed`` and the simulator parameters;
    * ``NAME.gt.npz``: ground truth every ``gt_every`` frames: ``steps`` (int64 frame indices),
      ``images`` (float32 (n, H, W) intensity in [0, 1]), ``masks`` (bool (n, H, W) true motion
      masks), ``rate_scale``, and the per-pixel ``gain_map``, ``threshold_map``, ``dark_map``
      (so the expected rate is ``clip((gain_map * I + dark_map) / threshold_map, 0, 1)``; see
      :func:`load_ground_truth`). ``gt_every=None`` or 0 writes no ground truth.

    Other parameters are those of :func:`simulate`. Returns the ``.dat`` path.
    """
    from cfsr.datfile import DatWriter

    steps = int(steps)
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if gt_every is not None and int(gt_every) < 0:
        raise ValueError(f"gt_every must be >= 0 steps, got {gt_every}")
    path = Path(path)
    sc = _as_scene(scene, height, width)
    sensor = Sensor(sc, seed=seed, gain=gain, threshold=threshold, noise=noise, start=start)
    h, w = sc.shape
    # a frame must be a whole number of bytes: pad rows with zero head columns if needed
    pad = next(k for k in range(8) if (h * (w + k)) % 8 == 0)
    layout = Layout(width=w, height=h, head_cols=pad)
    gpath = gt_path(path) if gt_every else None
    meta = {
        # the display gain is a rate (spikes/step, at most 1): an ideal pixel at intensity 1.0
        # fires at rate_scale, clipped to one spike per step like the sensor itself
        "gain": min(sensor.rate_scale, 1.0),
        "source": "cfsr.simulate",
        "scene": sc.describe(),
        "seed": int(seed),
        "simulator": sensor.params(),
        "ground_truth": gpath.name if gpath else None,
        "gt_every": int(gt_every) if gt_every else None,
    }
    with DatWriter(path, layout, rate_hz=float(STEP_RATE_HZ), meta=meta) as wr:
        for block in sensor.iter_chunks(steps, chunk):
            wr.write_frames(block)
            if progress is not None:
                progress(block.shape[0])
    if gpath is not None:
        ks = np.arange(0, steps, int(gt_every), dtype=np.int64)
        images = np.empty((len(ks), h, w), np.float32)
        masks = np.empty((len(ks), h, w), bool)
        for i, k in enumerate(ks):
            images[i], masks[i] = sc.intensity_and_mask(int(start + k))
        np.savez_compressed(
            gpath,
            steps=ks,
            images=images,
            masks=masks,
            rate_scale=np.float64(sensor.rate_scale),
            gain_map=sensor.gain_map.astype(np.float32),
            threshold_map=sensor.threshold_map.astype(np.float32),
            dark_map=sensor.dark_map.astype(np.float32),
            scene=np.array(json.dumps(sc.describe())),
        )
    return path


@dataclass
class GroundTruth:
    """Ground truth of a simulated ``.dat`` (see :func:`simulate_to_dat`)."""

    steps: np.ndarray
    images: np.ndarray
    masks: np.ndarray
    rate_scale: float
    gain_map: np.ndarray
    threshold_map: np.ndarray
    dark_map: np.ndarray
    scene: dict[str, Any]

    def index(self, t: int) -> int:
        hit = np.flatnonzero(self.steps == int(t))
        if not hit.size:
            raise ValueError(
                f"no ground truth at step {t}; stored steps {self.steps[0]}..{self.steps[-1]} "
                f"every {int(self.steps[1] - self.steps[0]) if len(self.steps) > 1 else '-'}"
            )
        return int(hit[0])

    def rate(self, t: int) -> np.ndarray:
        """Expected firing rate at frame ``t`` (spikes/step, float32)."""
        img = self.images[self.index(t)]
        r = (self.gain_map * img + self.dark_map) / self.threshold_map
        return np.clip(r, 0.0, 1.0).astype(np.float32)


def load_ground_truth(path: str | os.PathLike) -> GroundTruth:
    """Read ``NAME.gt.npz`` (or the ground truth of ``NAME.dat``)."""
    p = Path(path)
    if not p.name.endswith(".gt.npz"):
        p = gt_path(p)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no ground-truth file")
    with np.load(p, allow_pickle=False) as z:
        return GroundTruth(
            steps=z["steps"],
            images=z["images"],
            masks=z["masks"],
            rate_scale=float(z["rate_scale"]),
            gain_map=z["gain_map"],
            threshold_map=z["threshold_map"],
            dark_map=z["dark_map"],
            scene=json.loads(str(z["scene"])),
        )
