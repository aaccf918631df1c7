"""Moving layers of a simulated scene and the kernels that render them.

A layer is a rotating textured disk or fan (:class:`Rotor`), a translating textured sprite
(:class:`Slider`) or the whole view moved by its mount (:class:`Mount`, with the paths
:func:`vibration` and :func:`drift`). Moving edges are anti-aliased by area coverage, so
objects move smoothly by fractions of a pixel per step. Time is the sensor step (1 step =
25 us at 40 kHz), so 2000 rpm is ``2000 * 2 pi / 60 / 40000 = 0.005236`` rad/step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numba import prange

from cfsr._jit import njit
from cfsr.layout import STEP_RATE_HZ

__all__ = ["Rotor", "Slider", "Mount", "Layer", "vibration", "drift"]

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
