"""Spike-camera simulator with exact ground truth (CFSR design, section 4).

Scenes are rendered at every sensor step from images bundled with scikit-image (offline) and
fed to an integrate-and-fire sensor model with a random initial potential and optional SPCS-like
fixed-pattern noise. Ground truth at any step is the rendered intensity; true motion masks come
free.

>>> from cfsr.simulate import simulate
>>> sim = simulate("disk", steps=200, height=48, width=64, seed=0)
>>> sim.spikes.shape, sim.rate_scale
((200, 48, 64), 0.5)
"""

from cfsr.simulate.noise import NOISE_PRESETS, Noise
from cfsr.simulate.scenes import (
    SCENES,
    Mount,
    Rotor,
    Scene,
    Slider,
    drift,
    make_scene,
    star_field,
    vibration,
)
from cfsr.simulate.sensor import DEFAULT_GAIN, DEFAULT_THRESHOLD, Sensor
from cfsr.simulate.simulation import (
    GroundTruth,
    Simulation,
    check_dat_sizes,
    gt_path,
    load_ground_truth,
    simulate,
    simulate_to_dat,
)

__all__ = [
    "DEFAULT_GAIN",
    "DEFAULT_THRESHOLD",
    "NOISE_PRESETS",
    "SCENES",
    "GroundTruth",
    "Mount",
    "Noise",
    "Rotor",
    "Scene",
    "Sensor",
    "Simulation",
    "Slider",
    "check_dat_sizes",
    "gt_path",
    "drift",
    "load_ground_truth",
    "make_scene",
    "simulate",
    "simulate_to_dat",
    "star_field",
    "vibration",
]
