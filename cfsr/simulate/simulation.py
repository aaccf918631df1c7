"""Simulated runs with their ground truth: in memory (:func:`simulate`) or to a ``.dat``
file, its sidecar and a ground-truth NPZ (:func:`simulate_to_dat`, :func:`load_ground_truth`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cfsr.cli._common import available_memory, free_disk
from cfsr.datfile import MAX_FRAME_PIXELS, MAX_FRAMES, DatWriter
from cfsr.layout import STEP_RATE_HZ, Layout
from cfsr.simulate.noise import Noise
from cfsr.simulate.scenes import Scene, make_scene
from cfsr.simulate.sensor import DEFAULT_THRESHOLD, Sensor

__all__ = [
    "Simulation",
    "GroundTruth",
    "simulate",
    "simulate_to_dat",
    "gt_path",
    "load_ground_truth",
]

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


#: bytes of ground truth per pixel per stored frame: a float32 image and a bool mask
GT_BYTES_PER_PIXEL = 5


def check_dat_sizes(
    steps: int,
    height: int,
    width: int,
    path: str | os.PathLike,
    *,
    start: int = 0,
    gt_every: int | None = None,
    names: Mapping[str, str] | None = None,
) -> None:
    """Refuse, before anything is allocated or written, a simulation to ``path`` the machine
    cannot hold: a frame over the format's pixels, a scene clock past
    :data:`~cfsr.datfile.MAX_FRAMES`, a ``.dat`` larger than the free disk, ground truth over
    half the available memory. ValueError naming the argument (``names`` maps an argument to
    what the caller calls it, e.g. a command's flags), the value and the limit."""
    n = {k: k for k in ("steps", "height", "width", "start", "gt_every")} | dict(names or {})
    h, w = height, width
    if w * h > MAX_FRAME_PIXELS:
        raise ValueError(f"{n['width']} {w} x {n['height']} {h} = {w * h} pixels a frame, more "
                         f"than the {MAX_FRAME_PIXELS} a .dat frame may hold")
    if start + steps > MAX_FRAMES:
        raise ValueError(f"{n['start']} {start} + {n['steps']} {steps} passes step {MAX_FRAMES},"
                         " the last a recording may reach")
    need = steps * -(-h * w // 8)  # rows padded to whole bytes at most
    free, folder = free_disk(path)
    if need > free:
        raise ValueError(f"{n['steps']} {steps}: {need / 1e9:.3g} GB of spikes at {w} x {h}, "
                         f"more than the {free / 1e9:.3g} GB free in {folder}")
    if gt_every:
        n_gt = -(-steps // gt_every)
        gt = n_gt * h * w * GT_BYTES_PER_PIXEL
        avail = available_memory()
        if gt > avail // 2:
            raise ValueError(
                f"{n['gt_every']} {gt_every}: {n_gt} ground-truth frames need {gt / 1e9:.3g} GB "
                f"of memory, more than half the {avail / 1e9:.3g} GB available; give a larger "
                f"{n['gt_every']} (or 0 for none)")
        if need + gt > free:
            raise ValueError(f"{n['steps']} {steps} with {n['gt_every']} {gt_every}: "
                             f"{(need + gt) / 1e9:.3g} GB of spikes and ground truth, more than "
                             f"the {free / 1e9:.3g} GB free in {folder}")


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
      masks), ``rate_scale``, the true defect map (``hot_map``, ``dead_map``, bool (H, W)),
      and the per-pixel ``gain_map``, ``threshold_map``, ``dark_map``
      (so the expected rate is ``clip((gain_map * I + dark_map) / threshold_map, 0, 1)``; see
      :func:`load_ground_truth`). ``gt_every=None`` or 0 writes no ground truth.

    Other parameters are those of :func:`simulate`. Returns the ``.dat`` path.
    """
    steps = int(steps)
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if gt_every is not None and int(gt_every) < 0:
        raise ValueError(f"gt_every must be >= 0 steps, got {gt_every}")
    path = Path(path)
    # bounded before the scene (its textures) or a byte of the file exists
    shape = scene.shape if isinstance(scene, Scene) else (height, width)
    check_dat_sizes(steps, *shape, path, start=start, gt_every=gt_every)
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
            hot_map=sensor.hot_mask,
            dead_map=sensor.dead_mask,
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
    #: the true defect map (bool (H, W)); all False in files written before it was stored
    hot_map: np.ndarray | None = None
    dead_map: np.ndarray | None = None

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
            hot_map=z["hot_map"] if "hot_map" in z.files else None,
            dead_map=z["dead_map"] if "dead_map" in z.files else None,
        )
