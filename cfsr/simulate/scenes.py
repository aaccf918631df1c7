"""The named synthetic scenes (:data:`SCENES`, :func:`make_scene`) and the star field.

Each scene is a :class:`~cfsr.simulate.scene.Scene`: a static background plus moving layers
(:mod:`cfsr.simulate.layers`), rendered at every sensor step with exact ground truth and
motion masks. Sizes scale with the frame; speeds do not. :func:`star_field` (a night sky with
stars and lamps, for the defect map's false alarms) is built the same way but is not one of
the accuracy table's scenes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from cfsr.layout import STEP_RATE_HZ
from cfsr.simulate.layers import Layer, Mount, Rotor, Slider, drift, vibration
from cfsr.simulate.scene import Scene
from cfsr.simulate.textures import texture

__all__ = [
    "Scene", "Rotor", "Slider", "Mount", "SCENES", "make_scene", "star_field", "vibration", "drift",
]

_TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------- the scenes


def _supersampled(fn: Callable[[np.ndarray, np.ndarray], np.ndarray], h: int, w: int) -> np.ndarray:
    """Area coverage of the shape ``fn(y, x) -> bool`` (unit coords) on an h x w grid, 4x4 AA."""
    ss = 4
    yy = (np.arange(h * ss) + 0.5) / (h * ss)
    xx = (np.arange(w * ss) + 0.5) / (w * ss)
    inside = fn(yy[:, None], xx[None, :]).astype(np.float32)
    return inside.reshape(h, ss, w, ss).mean(axis=(1, 3))


def _car_sprite(sh: int, sw: int) -> tuple[np.ndarray, np.ndarray]:
    """A car silhouette (body, cabin, two wheels) textured with the coffee image."""
    ar = sh / sw

    def body(y, x):
        return (y >= 0.38) & (y <= 0.84) & (x >= 0.0) & (x <= 1.0)

    def cabin(y, x):
        # trapezoid: wider at the bottom (y = 0.40) than at the top (y = 0.02)
        f = np.clip((y - 0.02) / 0.38, 0.0, 1.0)
        left = 0.30 - 0.10 * f
        right = 0.68 + 0.08 * f
        return (y >= 0.02) & (y <= 0.40) & (x >= left) & (x <= right)

    def wheel(y, x, cx):
        return ((y - 0.80) ** 2 + ((x - cx) / ar) ** 2) <= 0.19**2

    def wheels(y, x):
        return wheel(y, x, 0.22) | wheel(y, x, 0.78)

    a_body = _supersampled(lambda y, x: body(y, x) | cabin(y, x), sh, sw)
    a_wheels = _supersampled(wheels, sh, sw)
    alpha = np.maximum(a_body, a_wheels)
    paint = texture("coffee", sh, sw, lo=0.45, hi=1.0)
    tyre = texture("gravel", sh, sw, lo=0.02, hi=0.2)
    # wheels over the body: blend by wheel coverage
    tex = paint * (1.0 - a_wheels) + tyre * a_wheels
    return np.ascontiguousarray(tex, np.float32), np.ascontiguousarray(alpha, np.float32)


def _disk(
    h: int,
    w: int,
    *,
    rpm: float = 2000.0,
    radius: float | None = None,
    name: str = "disk",
    floor: float = 0.0,
    illumination: float = 1.0,
    noise: str | None = None,
    summary: str = "",
) -> Scene:
    """The disk scene; ``floor`` raises the darkest intensity (both textures start there)."""
    m = min(h, w)
    r = 0.3 * m if radius is None else float(radius)
    d = 2 * math.ceil(r) + 3
    rotor = Rotor(
        texture("camera", d, d, lo=floor, hi=1.0),
        cy=(h - 1) / 2,
        cx=(w - 1) / 2,
        radius=r,
        rpm=rpm,
        label="disk",
    )
    bg = texture("brick", h, w, lo=max(0.05, floor), hi=0.95)
    what = f"textured disk (camera) rotating at {rpm:g} rpm over a static brick wall"
    return Scene(
        name,
        bg,
        [rotor],
        illumination=illumination,
        noise=noise,
        summary=f"{summary}{what}",
        info={"textures": {"background": "brick", "disk": "camera"}},
    )


def _disk_scene(h: int, w: int, *, rpm: float = 2000.0, radius: float | None = None) -> Scene:
    return _disk(h, w, rpm=rpm, radius=radius)


def _dim_scene(
    h: int, w: int, *, illumination: float = 0.1, rpm: float = 2000.0, radius: float | None = None
) -> Scene:
    # intensities in [0.1, 1] at rate_scale 0.5 * illumination: true rates 0.005..0.05 at 0.1
    return _disk(
        h,
        w,
        rpm=rpm,
        radius=radius,
        name="dim",
        floor=0.1,
        illumination=illumination,
        summary=f"dim ({illumination:g} x light, intensity >= 0.1): ",
    )


def _noisy_scene(
    h: int, w: int, *, noise: str = "sensor", rpm: float = 2000.0, radius: float | None = None
) -> Scene:
    return _disk(
        h,
        w,
        rpm=rpm,
        radius=radius,
        name="noisy",
        noise=noise,
        summary=f"sensor noise ({noise}): ",
    )


def _fan_scene(
    h: int,
    w: int,
    *,
    rpm: float = 2600.0,
    blades: int = 4,
    blade_width: float = 0.0,
    name: str = "fan",
) -> Scene:
    m = min(h, w)
    r = 0.42 * m
    d = 2 * math.ceil(r) + 3
    rotor = Rotor(
        texture("astronaut", d, d, lo=0.35, hi=1.0),
        cy=(h - 1) / 2,
        cx=(w - 1) / 2,
        radius=r,
        rpm=rpm,
        blades=int(blades),
        blade_fraction=0.4,
        blade_width=float(blade_width),
        hub=0.14 * m,
        label="fan",
    )
    bg = texture("gravel", h, w, lo=0.02, hi=0.6)
    shape = f" ({blade_width:g} px wide blades)" if blade_width else ""
    return Scene(
        name,
        bg,
        [rotor],
        summary=f"{blades}-blade fan{shape} rotating at {rpm:g} rpm over gravel",
        info={"textures": {"background": "gravel", "blades": "astronaut"}},
    )


def _blades_scene(
    h: int, w: int, *, rpm: float = 2600.0, blades: int = 4, blade_width: float = 3.0
) -> Scene:
    if not float(blade_width) > 0:
        raise ValueError(f"blade_width must be > 0 pixels, got {blade_width}")
    return _fan_scene(h, w, rpm=rpm, blades=blades, blade_width=blade_width, name="blades")


def _car_scene(
    h: int,
    w: int,
    *,
    speed_kmh: float = 100.0,
    px_per_m: float = 100.0,
    name: str = "car",
    illumination: float = 1.0,
) -> Scene:
    sh = max(4, round(0.34 * h))
    sw = max(8, round(0.36 * w))
    tex, alpha = _car_sprite(sh, sw)
    v = speed_kmh / 3.6 * px_per_m / STEP_RATE_HZ  # px/step
    car = Slider(
        tex,
        alpha,
        y=int(round(0.58 * h)),
        x=0.12 * w,
        velocity=v,
        frame_width=w,
        label="car",
        info={"speed_kmh": speed_kmh, "px_per_m": px_per_m},
    )
    bg = texture("brick", h, w, lo=0.03, hi=0.55)
    what = f"textured car (coffee) at {speed_kmh:g} km/h ({v:.4f} px/step at {px_per_m:g} px/m)"
    summary = f"{what} over a brick wall"
    if illumination < 1.0:
        summary = f"low light ({illumination:g} x): {summary}"
    return Scene(
        name,
        bg,
        [car],
        illumination=illumination,
        summary=summary,
        info={"textures": {"background": "brick", "car": "coffee"}},
    )


def _static_scene(h: int, w: int) -> Scene:
    frozen = _disk_scene(h, w, rpm=0.0)
    return Scene(
        "static",
        frozen.intensity(0),
        [],
        summary="the disk scene frozen: nothing moves (camera disk on a brick wall)",
        info={"textures": {"background": "brick", "disk": "camera"}},
    )


def _lowlight_scene(h: int, w: int, *, illumination: float = 0.1, **kw: Any) -> Scene:
    return _car_scene(h, w, name="lowlight", illumination=illumination, **kw)


def _still_plane(h: int, w: int) -> np.ndarray:
    """The still scene the mount scenes look at: the static scene's image."""
    return _disk_scene(h, w, rpm=0.0).intensity(0)


def _vibrate_scene(
    h: int,
    w: int,
    *,
    amplitude: float = 1.0,
    hz: float = 50.0,
    mover: bool = False,
    rpm: float = 2000.0,
    name: str = "vibrate",
) -> Scene:
    if not 0.0 < float(amplitude) <= 64.0:
        raise ValueError(f"amplitude must be in (0, 64] pixels, got {amplitude}")
    if not 0.0 < float(hz) <= STEP_RATE_HZ / 4:
        raise ValueError(f"hz must be in (0, {STEP_RATE_HZ / 4:g}], got {hz}")
    peak = _TWO_PI * float(hz) / STEP_RATE_HZ * float(amplitude)
    mount = Mount(
        _still_plane(h, w),
        vibration(amplitude, hz),
        label="vibration",
        info={"amplitude_px": float(amplitude), "hz": float(hz), "peak_px_per_step": peak},
    )
    layers: list[Layer] = [mount]
    what = f"still scene on a mount vibrating {amplitude:g} px at {hz:g} Hz"
    if mover:
        m = min(h, w)
        r = 0.2 * m
        d = 2 * math.ceil(r) + 3
        layers.append(
            Rotor(
                texture("coffee", d, d, lo=0.1, hi=1.0),
                cy=0.3 * h,
                cx=0.75 * w,
                radius=r,
                rpm=rpm,
                label="disk",
            )
        )
        what += f", a textured disk (coffee) spinning at {rpm:g} rpm in front"
    return Scene(
        name,
        mount.texture,
        layers,
        summary=what,
        info={"textures": {"background": "brick", "disk": "camera"}},
    )


def _vibrate_mover_scene(h: int, w: int, **kw: Any) -> Scene:
    return _vibrate_scene(h, w, mover=True, name="vibrate_mover", **kw)


def _drift_scene(h: int, w: int, *, speed: float = 0.005, angle: float = 30.0) -> Scene:
    if not 0.0 < float(speed) <= 1.0:
        raise ValueError(f"speed must be in (0, 1] px/step, got {speed}")
    mount = Mount(
        _still_plane(h, w),
        drift(speed, angle),
        label="drift",
        info={"speed_px_per_step": float(speed), "angle_deg": float(angle)},
    )
    return Scene(
        "drift",
        mount.texture,
        [mount],
        summary=f"still scene drifting {speed:g} px/step at {angle:g} degrees",
        info={"textures": {"background": "brick", "disk": "camera"}},
    )


def _pan_scene(h: int, w: int, *, speed: float = 0.02) -> Scene:
    if not 0.0 < float(speed) <= 1.0:
        raise ValueError(f"speed must be in (0, 1] px/step, got {speed}")
    mount = Mount(
        texture("rocket", h, w, lo=0.05, hi=0.95),
        drift(speed, 0.0),
        label="pan",
        info={"speed_px_per_step": float(speed)},
    )
    return Scene(
        "pan",
        mount.texture,
        [mount],
        summary=f"a landscape (rocket) seen by a camera panning {speed:g} px/step",
        info={"textures": {"background": "rocket"}},
    )


_BUILDERS: dict[str, Callable[..., Scene]] = {
    "disk": _disk_scene,
    "fan": _fan_scene,
    "car": _car_scene,
    "static": _static_scene,
    "lowlight": _lowlight_scene,
    "dim": _dim_scene,
    "noisy": _noisy_scene,
    "blades": _blades_scene,
    "vibrate": _vibrate_scene,
    "vibrate_mover": _vibrate_mover_scene,
    "drift": _drift_scene,
    "pan": _pan_scene,
}

#: Scene names with a one-line description (iterate it for the names).
SCENES: dict[str, str] = {
    "disk": "textured disk rotating at 2000 rpm over a static background",
    "fan": "4-blade fan rotating at 2600 rpm over a static background",
    "car": "textured car translating at 100 km/h (100 px/m: 0.069 px/step)",
    "static": "static scene (no motion; empty motion mask)",
    "lowlight": "the car scene at 1/10 illumination (rate_scale 0.05 by default)",
    "dim": "the disk scene (2000 rpm) at 1/10 light: true rates 0.005-0.05 spikes/step",
    "noisy": "the disk scene (2000 rpm) seen by a noisy sensor (noise preset 'sensor')",
    "blades": "4 thin (3 px) blades rotating at 2600 rpm over a static background",
    "vibrate": "the static scene on a mount vibrating 1 px at 50 Hz (motion everywhere)",
    "vibrate_mover": "the vibrating mount with a disk spinning at 2000 rpm in front",
    "drift": "the static scene drifting 0.005 px/step (slow motion everywhere)",
    "pan": "a landscape seen by a camera panning 0.02 px/step",
}


def make_scene(name: str, height: int = 250, width: int = 400, **options: Any) -> Scene:
    """Build a named scene.

    Parameters
    ----------
    name : str
        One of :data:`SCENES` (``disk``, ``fan``, ``car``, ``static``, ``lowlight``, ``dim``,
        ``noisy``, ``blades``, ``vibrate``, ``vibrate_mover``, ``drift``, ``pan``).
    height, width : int
        Frame size in pixels (default 400 x 250, the sensor). Object sizes scale with the
        frame; speeds do not (rpm, and pixels per step for the car).
    **options
        Scene-specific overrides: ``disk(rpm=2000, radius=None)``, ``fan(rpm=2600,
        blades=4, blade_width=0)``, ``car(speed_kmh=100, px_per_m=100)``,
        ``lowlight(illumination=0.1, speed_kmh=100, px_per_m=100)``, ``dim(illumination=0.1,
        rpm=2000, radius=None)``, ``noisy(noise="sensor", rpm=2000, radius=None)``,
        ``blades(rpm=2600, blades=4, blade_width=3)``, ``vibrate(amplitude=1, hz=50)``
        (pixels, Hz), ``vibrate_mover(amplitude=1, hz=50, rpm=2000)``, ``drift(speed=0.005,
        angle=30)`` (px/step, degrees), ``pan(speed=0.02)`` (px/step).

    Returns
    -------
    Scene

    Examples
    --------
    >>> s = make_scene("disk", height=48, width=64)
    >>> s.intensity(0).shape, bool(s.motion_mask(0).any())
    ((48, 64), True)
    """
    key = str(name).strip().lower()
    if key not in _BUILDERS:
        raise ValueError(f"unknown scene {name!r}; choices: {', '.join(SCENES)}")
    if int(height) < 8 or int(width) < 8:
        raise ValueError(f"scene size must be at least 8 x 8 pixels, got {width} x {height}")
    try:
        return _BUILDERS[key](int(height), int(width), **options)
    except TypeError as exc:
        raise ValueError(f"scene {key!r}: bad option ({exc})") from None


def star_field(height: int = 250, width: int = 400, *, stars: int = 120, lamps: int = 12,
               blur: tuple[float, float] = (0.7, 1.0), seed: int = 1) -> Scene:
    """A still night sky (intensity 0.05) with ``stars`` point sources and ``lamps`` small
    discs (radius 1-3 px), the bright small objects a defect map must never flag.

    Each star is the lens's blur of a point: a Gaussian of standard deviation drawn from
    ``blur`` (pixels; 0.7-1.0 px, a sharp lens at this pixel size) with a peak intensity of
    0.3-1.0; lamps are anti-aliased discs at full intensity. Nothing moves (the hardest case:
    no motion ever moves a star off its pixel).
    """
    h, w = int(height), int(width)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    sky = np.full((h, w), 0.05, np.float32)
    for _ in range(int(stars)):
        cy, cx = rng.uniform(3, h - 3), rng.uniform(3, w - 3)
        peak, sd = rng.uniform(0.3, 1.0), rng.uniform(*blur)
        sky += peak * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * sd * sd))
    for _ in range(int(lamps)):
        cy, cx, r = rng.uniform(4, h - 4), rng.uniform(4, w - 4), rng.uniform(1.0, 3.0)
        sky = np.maximum(sky, np.clip(r + 0.5 - np.hypot(yy - cy, xx - cx), 0.0, 1.0))
    return Scene(
        "stars",
        np.clip(sky, 0.0, 1.0),
        summary=f"still night sky: {stars} stars (blur {blur[0]:g}-{blur[1]:g} px), {lamps} lamps",
        info={"stars": int(stars), "lamps": int(lamps), "blur_px": list(blur)},
    )
