"""Synthetic scenes rendered at every sensor step, with exact ground truth and motion masks.

A :class:`Scene` is a static background plus moving *layers* (a rotating textured disk or fan,
a translating textured car). Intensity is the normalised scene radiance in [0, 1] at the pixel
centre; moving edges are anti-aliased by area coverage, so objects move smoothly by fractions
of a pixel per step. The true motion mask at step ``t`` marks every pixel a moving object
covers, even partly (coverage > 0): exactly the pixels whose intensity the moving objects
affect at ``t``.

Rendering only touches the region of interest (ROI) that moving layers can reach; the rest of
the frame is the background. Time ``t`` is the sensor step (1 step = 25 us at 40 kHz), so
2000 rpm is ``2000 * 2 pi / 60 / 40000 = 0.005236`` rad/step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numba import prange

from cfsr._jit import njit
from cfsr.layout import STEP_RATE_HZ
from cfsr.simulate.textures import texture

__all__ = ["Scene", "Rotor", "Slider", "Mount", "SCENES", "make_scene", "vibration", "drift"]

_TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------- kernels


@njit(helper=True)
def _clamp01(v):  # pragma: no cover - numba
    if v < 0.0:
        return 0.0
    if v > 1.0:
        return 1.0
    return v


@njit(helper=True)
def _bilinear_clamped(tex, v, u):  # pragma: no cover - numba
    """Bilinear sample of ``tex`` at row ``v``, column ``u`` with edge clamping."""
    h, w = tex.shape
    if v < 0.0:
        v = 0.0
    elif v > h - 1:
        v = h - 1.0
    if u < 0.0:
        u = 0.0
    elif u > w - 1:
        u = w - 1.0
    y0 = int(v)
    x0 = int(u)
    y1 = min(y0 + 1, h - 1)
    x1 = min(x0 + 1, w - 1)
    fy = v - y0
    fx = u - x0
    top = tex[y0, x0] * (1.0 - fx) + tex[y0, x1] * fx
    bot = tex[y1, x0] * (1.0 - fx) + tex[y1, x1] * fx
    return top * (1.0 - fy) + bot * fy


@njit(helper=True)
def _bilinear_zero(tex, v, u):  # pragma: no cover - numba
    """Bilinear sample of ``tex`` at (v, u) with zeros outside the texture."""
    h, w = tex.shape
    if v <= -1.0 or u <= -1.0 or v >= h or u >= w:
        return 0.0
    fy0 = math.floor(v)
    fx0 = math.floor(u)
    y0 = int(fy0)
    x0 = int(fx0)
    fy = v - fy0
    fx = u - fx0
    acc = 0.0
    if 0 <= y0 < h:
        if 0 <= x0 < w:
            acc += tex[y0, x0] * (1.0 - fy) * (1.0 - fx)
        if 0 <= x0 + 1 < w:
            acc += tex[y0, x0 + 1] * (1.0 - fy) * fx
    if 0 <= y0 + 1 < h:
        if 0 <= x0 < w:
            acc += tex[y0 + 1, x0] * fy * (1.0 - fx)
        if 0 <= x0 + 1 < w:
            acc += tex[y0 + 1, x0 + 1] * fy * fx
    return acc


class _Rotor(NamedTuple):
    """A rotor's outline in frame pixels: centre, radius and, for a fan, hub and blades."""

    cy: float  #: centre row (px)
    cx: float  #: centre column (px)
    radius: float  #: px
    hub: float  #: hub radius (px)
    period: float  #: blade repeat (rad); 0: a disk
    blade: float  #: blade width (rad)
    bwidth: float  #: > 0: blades are straight bars this wide (px)


@njit(parallel=True)
def _render_rotor(out, cov, oy, ox, angles, tex, rotor):  # pragma: no cover - numba
    """Composite a rotating textured disk (``period == 0``) or fan over ``out`` in place.

    ``out`` is ``(n, rh, rw)`` float32, the ROI whose top-left pixel is frame ``(oy, ox)``;
    ``angles[k]`` is the rotation (rad) at step k; ``rotor`` (:class:`_Rotor`) the outline.
    A fan has blades ``blade`` rad wide repeating every ``period`` rad, plus a hub of radius
    ``hub`` px; with ``bwidth > 0`` each blade is instead a straight bar ``bwidth`` px wide
    along a ray (constant width at every radius). Edges are anti-aliased by coverage
    ``clip(distance_to_edge + 0.5, 0, 1)``; ``cov`` (same shape, or empty) receives max
    coverage.
    """
    cy, cx, radius, hub, period, blade, bwidth = rotor
    n, rh, rw = out.shape
    th, tw = tex.shape
    tcy = 0.5 * (th - 1)
    tcx = 0.5 * (tw - 1)
    want_cov = cov.shape[0] == n
    for i in prange(rh):
        dy = oy + i - cy
        rrow = np.empty(rw, np.float64)
        trow = np.empty(rw, np.float64)
        for j in range(rw):
            dx = ox + j - cx
            rrow[j] = math.sqrt(dx * dx + dy * dy)
            trow[j] = math.atan2(dy, dx)
        for k in range(n):
            a = angles[k]
            c = math.cos(a)
            s = math.sin(a)
            for j in range(rw):
                r = rrow[j]
                cv = radius - r + 0.5
                if cv <= 0.0:
                    continue
                if cv > 1.0:
                    cv = 1.0
                if period > 0.0:
                    phi = trow[j] - a
                    phi -= math.floor(phi / period) * period
                    if bwidth > 0.0:
                        # bar along the ray at phi = 0: perpendicular distance to its axis
                        dphi = phi if phi < 0.5 * period else phi - period
                        if abs(dphi) < 0.5 * math.pi:
                            cb = _clamp01(0.5 * bwidth - r * abs(math.sin(dphi)) + 0.5)
                        else:
                            cb = 0.0
                    else:
                        if phi < blade:
                            d = min(phi, blade - phi)
                        else:
                            d = -min(phi - blade, period - phi)
                        cb = _clamp01(d * r + 0.5)
                    ch = _clamp01(hub - r + 0.5)
                    cv *= max(cb, ch)
                    if cv <= 0.0:
                        continue
                dx = ox + j - cx
                # object coordinates: rotate the pixel back by -a
                u = c * dx + s * dy + tcx
                v = -s * dx + c * dy + tcy
                val = _bilinear_clamped(tex, v, u)
                out[k, i, j] = cv * val + (1.0 - cv) * out[k, i, j]
                if want_cov and cv > cov[k, i, j]:
                    cov[k, i, j] = cv
    return out


@njit(parallel=True)
def _render_slider(out, cov, oy, ox, offy, offx, tex_pm, alpha):  # pragma: no cover - numba
    """Composite a translating sprite over ``out`` in place.

    Sprite texel ``(p, q)`` sits at frame position ``(offy[k] + p, offx[k] + q)`` at step k;
    ``tex_pm`` is the texture premultiplied by ``alpha``. Sub-pixel positions are bilinear, with
    zero alpha outside the sprite, so edges move smoothly.
    """
    n, rh, rw = out.shape
    sh, sw = alpha.shape
    want_cov = cov.shape[0] == n
    for i in prange(rh):
        for k in range(n):
            v = oy + i - offy[k]
            if v <= -1.0 or v >= sh:
                continue
            j0 = max(0, int(math.floor(offx[k] - ox)) - 1)
            j1 = min(rw, int(math.ceil(offx[k] - ox + sw)) + 1)
            for j in range(j0, j1):
                u = ox + j - offx[k]
                a = _bilinear_zero(alpha, v, u)
                if a <= 0.0:
                    continue
                p = _bilinear_zero(tex_pm, v, u)
                out[k, i, j] = p + (1.0 - a) * out[k, i, j]
                if want_cov and a > cov[k, i, j]:
                    cov[k, i, j] = a
    return out


@njit(helper=True)
def _reflect(u, n):  # pragma: no cover - numba
    """Coordinate ``u`` folded into ``[0, n - 1]`` by mirroring at the edges (an endless
    plane with no seam in intensity)."""
    if n <= 1:
        return 0.0
    period = 2.0 * (n - 1)
    u = u - math.floor(u / period) * period
    return period - u if u > n - 1 else u


@njit(helper=True)
def _plane_at(tex, v, u):  # pragma: no cover - numba
    h, w = tex.shape
    return _bilinear_clamped(tex, _reflect(v, h), _reflect(u, w))


@njit(parallel=True)
def _render_plane(out, cov, oy, ox, dy, dx, tex, edge):  # pragma: no cover - numba
    """Overwrite ``out`` with the plane ``tex`` seen shifted by ``(dy[k], dx[k])`` at step k.

    Frame pixel ``(oy + i, ox + j)`` shows plane point ``(oy + i + dy[k], ox + j + dx[k])``
    (bilinear, mirrored beyond the plane's edges). ``cov`` (same shape, or empty) receives 1
    where the motion is visible: the intensity differs from a 4-neighbour's (a one-pixel
    shift) by at least ``edge``.
    """
    n, rh, rw = out.shape
    want_cov = cov.shape[0] == n
    for i in prange(rh):
        for k in range(n):
            v = oy + i + dy[k]
            for j in range(rw):
                u = ox + j + dx[k]
                val = _plane_at(tex, v, u)
                out[k, i, j] = val
                if want_cov:
                    d = max(
                        abs(_plane_at(tex, v - 1.0, u) - val),
                        abs(_plane_at(tex, v + 1.0, u) - val),
                        abs(_plane_at(tex, v, u - 1.0) - val),
                        abs(_plane_at(tex, v, u + 1.0) - val),
                    )
                    if d >= edge:
                        cov[k, i, j] = 1.0
    return out


# --------------------------------------------------------------------------- layers


def _rpm_to_rad_per_step(rpm: float) -> float:
    return float(rpm) * _TWO_PI / 60.0 / STEP_RATE_HZ


@dataclass
class Rotor:
    """A textured disk, or a fan with blades, rotating about ``(cy, cx)``.

    Parameters
    ----------
    texture : ndarray (D, D) float32
        Texture in [0, 1] in object coordinates, centred on the rotation axis.
    cy, cx : float
        Rotation centre (pixels, frame coordinates of pixel centres).
    radius : float
        Outer radius (pixels).
    rpm : float
        Rotation speed (revolutions per minute; positive is clockwise on screen).
    blades : int
        0 for a full disk, else the number of fan blades.
    blade_fraction : float
        Angular fraction of each blade period covered by the blade (0..1).
    hub : float
        Radius of the solid hub of a fan (pixels).
    blade_width : float
        0 (default): wedge-shaped blades (``blade_fraction`` of the period at every radius).
        > 0: straight bars of this constant width in pixels (thin blades; ``blade_fraction``
        is then ignored).
    phase : float
        Rotation at step 0 (rad).
    """

    texture: np.ndarray
    cy: float
    cx: float
    radius: float
    rpm: float
    blades: int = 0
    blade_fraction: float = 0.4
    hub: float = 0.0
    blade_width: float = 0.0
    phase: float = 0.0
    label: str = "disk"

    @property
    def omega(self) -> float:
        """Angular speed in rad/step."""
        return _rpm_to_rad_per_step(self.rpm)

    def bbox(self, height: int, width: int) -> tuple[int, int, int, int]:
        r = self.radius + 1.0
        y0 = max(0, int(math.floor(self.cy - r)))
        y1 = min(height, int(math.ceil(self.cy + r)) + 1)
        x0 = max(0, int(math.floor(self.cx - r)))
        x1 = min(width, int(math.ceil(self.cx + r)) + 1)
        return y0, max(y0, y1), x0, max(x0, x1)

    def angles(self, t0: int, n: int) -> np.ndarray:
        t = np.arange(n, dtype=np.float64) + float(t0)
        return np.mod(self.phase + self.omega * t, _TWO_PI)

    def render(self, t0: int, n: int, out: np.ndarray, cov: np.ndarray, oy: int, ox: int) -> None:
        period = _TWO_PI / self.blades if self.blades > 0 else 0.0
        _render_rotor(
            out,
            cov,
            float(oy),
            float(ox),
            self.angles(t0, n),
            self.texture,
            _Rotor(
                float(self.cy),
                float(self.cx),
                float(self.radius),
                float(self.hub),
                float(period),
                float(period * self.blade_fraction),
                float(self.blade_width),
            ),
        )

    def describe(self) -> dict[str, Any]:
        return {
            "kind": "fan" if self.blades else "disk",
            "label": self.label,
            "rpm": self.rpm,
            "omega_rad_per_step": self.omega,
            "centre_px": [self.cy, self.cx],
            "radius_px": self.radius,
            "rim_speed_px_per_step": self.omega * self.radius,
            "blades": self.blades,
            "blade_fraction": (
                self.blade_fraction if self.blades and not self.blade_width else None
            ),
            "blade_width_px": self.blade_width if self.blades and self.blade_width else None,
            "hub_px": self.hub if self.blades else None,
        }


@dataclass
class Slider:
    """A textured sprite translating horizontally at constant speed, wrapping around.

    Parameters
    ----------
    texture, alpha : ndarray (sh, sw) float32
        Texture in [0, 1] and coverage (alpha) in [0, 1] of the sprite.
    y : int
        Top row of the sprite (pixels).
    x : float
        Left edge of the sprite at step 0 (pixels).
    velocity : float
        Horizontal speed (pixels per step; positive moves right). When the sprite has left
        the frame on one side it re-enters on the other (period ``width + sw`` pixels).
    """

    texture: np.ndarray
    alpha: np.ndarray
    y: int
    x: float
    velocity: float
    frame_width: int
    label: str = "car"
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._tex_pm = np.ascontiguousarray(self.texture * self.alpha, dtype=np.float32)
        self.alpha = np.ascontiguousarray(self.alpha, dtype=np.float32)

    def bbox(self, height: int, width: int) -> tuple[int, int, int, int]:
        sh = self.alpha.shape[0]
        y0 = max(0, int(self.y) - 1)
        y1 = min(height, int(self.y) + sh + 1)
        return y0, max(y0, y1), 0, width

    def offsets(self, t0: int, n: int) -> np.ndarray:
        sw = self.alpha.shape[1]
        span = float(self.frame_width + sw + 2)
        t = np.arange(n, dtype=np.float64) + float(t0)
        return np.mod(self.x + sw + 1 + self.velocity * t, span) - (sw + 1)

    def render(self, t0: int, n: int, out: np.ndarray, cov: np.ndarray, oy: int, ox: int) -> None:
        offx = self.offsets(t0, n)
        offy = np.full(n, float(self.y))
        _render_slider(out, cov, float(oy), float(ox), offy, offx, self._tex_pm, self.alpha)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": "translation",
            "label": self.label,
            "size_px": list(self.alpha.shape),
            "top_px": self.y,
            "left_px_at_step0": self.x,
            "velocity_px_per_step": self.velocity,
            **self.info,
        }


@dataclass
class Mount:
    """The camera's own motion: the whole still scene seen through a moving mount.

    The scene is a plane (``texture``, frame pixels) that the camera sees shifted by
    ``offsets(t)`` pixels at step t (a vibration, a drift, a pan); the plane is mirrored
    beyond its edges, so any shift shows a continuous scene. Composited first, it replaces the
    background everywhere; movers in front of it come after it in the layer list.

    The motion mask of a moving mount is where the motion is *visible*: pixels whose
    intensity differs by at least ``edge`` from a 4-neighbour's at the current shift (a
    one-pixel shift would change them by that much). Elsewhere (flat regions) a shift of
    less than a pixel changes the intensity by less than ``edge``.

    Parameters
    ----------
    texture : ndarray (H, W) float32
        The still scene in [0, 1], in frame coordinates at zero shift.
    path : callable
        ``path(t) -> (dy, dx)``: the shift in pixels at the steps ``t`` (float64 array).
    edge : float
        Intensity step (0..1) that makes a pixel's motion visible (default 0.02: 5 display
        levels of 255).
    """

    texture: np.ndarray
    path: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    edge: float = 0.02
    label: str = "mount"
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.texture = np.ascontiguousarray(self.texture, dtype=np.float32)

    def bbox(self, height: int, width: int) -> tuple[int, int, int, int]:
        return 0, height, 0, width

    def offsets(self, t0: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Shift ``(dy, dx)`` in pixels at steps ``t0 .. t0 + n - 1`` (float64 arrays)."""
        t = np.arange(n, dtype=np.float64) + float(t0)
        dy, dx = self.path(t)
        return (
            np.ascontiguousarray(np.broadcast_to(dy, t.shape), np.float64),
            np.ascontiguousarray(np.broadcast_to(dx, t.shape), np.float64),
        )

    def render(self, t0: int, n: int, out: np.ndarray, cov: np.ndarray, oy: int, ox: int) -> None:
        dy, dx = self.offsets(t0, n)
        _render_plane(out, cov, float(oy), float(ox), dy, dx, self.texture, float(self.edge))

    def describe(self) -> dict[str, Any]:
        return {"kind": "mount", "label": self.label, "edge": self.edge, **self.info}


def vibration(
    amplitude: float, hz: float, *, phase: float = 0.0
) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """A mount vibrating on an ellipse: ``dx = A sin(w t)``, ``dy = A/2 sin(w t + pi/3)``,
    ``w = 2 pi hz / 40,000`` rad/step (A in pixels); its peak speed is ``A w`` px/step."""
    a = float(amplitude)
    w = _TWO_PI * float(hz) / STEP_RATE_HZ

    def path(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return 0.5 * a * np.sin(w * t + phase + math.pi / 3), a * np.sin(w * t + phase)

    return path


def drift(
    speed: float, angle_deg: float = 0.0
) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """A constant drift of ``speed`` px/step along ``angle_deg`` (0: rightwards, 90: down)."""
    v = float(speed)
    a = math.radians(float(angle_deg))

    def path(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return v * math.sin(a) * t, v * math.cos(a) * t

    return path


Layer = Rotor | Slider | Mount


# --------------------------------------------------------------------------- scene


class Scene:
    """A scene: static background plus moving layers, renderable at any step.

    Attributes
    ----------
    name : str
    height, width : int
        Frame size (pixels).
    background : ndarray (H, W) float32
        Static part of the scene, intensity in [0, 1].
    layers : list of Rotor or Slider
        Moving objects, composited in order.
    illumination : float
        Relative light level (1.0 normal; ``lowlight`` and ``dim`` use 0.1). The simulator
        multiplies its gain by it, so intensities stay normalised to [0, 1] while firing rates
        drop.
    noise : str, mapping or None
        The scene's default sensor noise (a :class:`cfsr.simulate.Noise` spec, e.g.
        ``"sensor"`` for the ``noisy`` scene); the simulator uses it when no noise is given
        (an explicit noise, ``"none"`` included, replaces it). None: an ideal sensor.
    roi : (y0, y1, x0, x1)
        Bounding box of everything the layers can cover; empty for a static scene.
    """

    def __init__(
        self,
        name: str,
        background: np.ndarray,
        layers: Sequence[Layer] = (),
        *,
        illumination: float = 1.0,
        noise: str | dict[str, float] | None = None,
        summary: str = "",
        info: dict[str, Any] | None = None,
    ) -> None:
        bg = np.ascontiguousarray(background, dtype=np.float32)
        if bg.ndim != 2:
            raise ValueError(f"background must be (H, W), got shape {bg.shape}")
        if not 0.0 < illumination <= 1.0:
            raise ValueError(f"illumination must be in (0, 1], got {illumination}")
        self.name = name
        self.background = np.clip(bg, 0.0, 1.0)
        self.layers = list(layers)
        self.illumination = float(illumination)
        self.noise = noise
        self.summary = summary
        self.info = dict(info or {})
        h, w = self.background.shape
        boxes = [ly.bbox(h, w) for ly in self.layers]
        boxes = [b for b in boxes if b[1] > b[0] and b[3] > b[2]]
        if boxes:
            self.roi = (
                min(b[0] for b in boxes),
                max(b[1] for b in boxes),
                min(b[2] for b in boxes),
                max(b[3] for b in boxes),
            )
        else:
            self.roi = (0, 0, 0, 0)

    @property
    def height(self) -> int:
        return int(self.background.shape[0])

    @property
    def width(self) -> int:
        return int(self.background.shape[1])

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def moving(self) -> bool:
        """True if anything in the scene moves."""
        y0, y1, x0, x1 = self.roi
        return y1 > y0 and x1 > x0

    def render_roi(
        self, t0: int, n: int, *, coverage: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Intensity of the ROI at steps ``t0 .. t0+n-1``: ``(n, rh, rw)`` float32 in [0, 1].

        Also returns the coverage of moving objects (same shape, float32 0..1) when
        ``coverage``, else an empty ``(0, 0, 0)`` array.
        """
        y0, y1, x0, x1 = self.roi
        dyn = np.empty((n, y1 - y0, x1 - x0), np.float32)
        dyn[:] = self.background[y0:y1, x0:x1]
        cov = np.zeros(dyn.shape, np.float32) if coverage else np.zeros((0, 0, 0), np.float32)
        if dyn.size:
            for layer in self.layers:
                layer.render(int(t0), n, dyn, cov, y0, x0)
            np.clip(dyn, 0.0, 1.0, out=dyn)
        return dyn, cov

    def intensity_and_mask(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth intensity (float32 (H, W) in [0, 1]) and motion mask at step ``t``."""
        img = self.background.copy()
        mask = np.zeros(self.shape, bool)
        if self.moving:
            y0, y1, x0, x1 = self.roi
            dyn, cov = self.render_roi(int(t), 1, coverage=True)
            img[y0:y1, x0:x1] = dyn[0]
            mask[y0:y1, x0:x1] = cov[0] > 0.0
        return img, mask

    def intensity(self, t: int) -> np.ndarray:
        """Ground-truth intensity at step ``t``: float32 ``(H, W)`` in [0, 1]."""
        return self.intensity_and_mask(t)[0]

    def motion_mask(self, t: int) -> np.ndarray:
        """Pixels covered (even partly) by a moving object at step ``t`` (bool ``(H, W)``)."""
        return self.intensity_and_mask(t)[1]

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "summary": self.summary,
            "height": self.height,
            "width": self.width,
            "illumination": self.illumination,
            "noise": self.noise,
            "moving": self.moving,
            "roi": list(self.roi),
            "layers": [ly.describe() for ly in self.layers],
            **self.info,
        }

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, {self.width}x{self.height}, layers={len(self.layers)})"


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
