"""Finding hot and dead pixels from the spike stream itself, online, without calibration.

Every pixel's long-run firing rate is counted straight from the packed frames
(:func:`cfsr._packed.count_packed`, no unpacking) and compared with its neighbourhood's:

* **hot**: the rate stands above the median of its 8 neighbours by more than
  ``hot_excess + hot_relative * median`` spikes/step (so a bright pixel of a ``threshold
  spread`` of a few percent is not called hot), above its second-brightest neighbour by
  ``isolation`` (a clump of bright pixels is scene content), and its neighbours are not
  raised above the ring around them by more than ``bump`` times that excess: a star or a
  lamp lights its neighbours through the lens, a hot pixel does not.
* **dead**: not one spike in the observed steps while its neighbours' median rate promised at
  least ``dead_spikes`` of them.

Moving texture averages out in a long-run rate, so it is never an isolated peak. Counting
every step costs about a third of what the sensor can deliver on one core, so only runs of
``run`` steps, one in ``duty``, are counted once the map is ready (rates, not phases, are what
the map needs); during the warm-up every step is counted, so the map of the first ``warmup``
steps is as good as a first pass over them. The map is rebuilt every ``refresh`` counted steps
during the warm-up and every ``refresh_ready`` after it.

Limits (see docs/methods.md): a static point source whose light falls on one pixel only (no
lens blur) is, from spikes alone, a hot pixel; a threshold spread is a multiplicative fixed
pattern the map does not flag and the correction does not undo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfsr._packed import count_packed, stored_to_image
from cfsr.defects.defect_map import DefectMap
from cfsr.layout import Layout

__all__ = ["DefectParams", "DefectEstimator", "classify"]


@dataclass(frozen=True)
class DefectParams:
    """Tunables of the online map (calibrated on the simulator, docs/methods.md).

    Attributes
    ----------
    warmup : int
        Counted steps before the map is called ready (its confidence reaches 1).
    min_steps : int
        Counted steps before any pixel is flagged.
    hot_excess : float
        Spikes/step a hot pixel exceeds its neighbours' median by, at least...
    hot_relative : float
        ...plus this fraction of that median (a threshold spread scales rates).
    isolation : float
        Spikes/step it exceeds its second-brightest neighbour by.
    bump : float
        Largest rise of its neighbours above the next ring, as a fraction of its excess.
    dead_spikes : float
        Spikes the neighbours' median rate must promise over the counted steps before a pixel
        that never fired is called dead.
    run, duty : int
        Once ready, count runs of ``run`` steps, one run in ``duty`` (every step before).
    refresh : int
        Counted steps between rebuilds of the map during the warm-up.
    refresh_ready : int
        Counted steps between rebuilds once ready (a rebuild costs tens of ms at 400 x 250,
        and defects do not come and go within seconds).
    """

    warmup: int = 2000
    min_steps: int = 256
    hot_excess: float = 0.07
    hot_relative: float = 0.15
    isolation: float = 0.03
    bump: float = 0.3
    dead_spikes: float = 12.0
    run: int = 64
    duty: int = 128
    refresh: int = 512
    refresh_ready: int = 16384


def _rings(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted 8 neighbours ``(8, H, W)`` and the median of the 16 at distance 2 ``(H, W)``,
    edges mirrored."""
    h, w = r.shape
    p = np.pad(r, 2, mode="reflect") if min(h, w) > 2 else np.pad(r, 2, mode="edge")
    near, far = [], []
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            if dy or dx:
                s = p[2 + dy : 2 + dy + h, 2 + dx : 2 + dx + w]
                (near if max(abs(dy), abs(dx)) == 1 else far).append(s)
    return np.sort(np.stack(near), axis=0), np.median(np.stack(far), axis=0)


def classify(counts: np.ndarray, steps: int, params: DefectParams | None = None,
             *, source: str = "stream") -> DefectMap:
    """The defect map of upright spike ``counts`` (H, W) over ``steps`` steps (see module)."""
    params = params or DefectParams()
    counts = np.asarray(counts)
    if steps < max(1, params.min_steps):
        return DefectMap.empty(counts.shape, source=source)
    r = counts.astype(np.float64) / steps
    near, far = _rings(r)
    med = 0.5 * (near[3] + near[4])
    above_second = r - near[-2]
    # count noise: a Poisson bound, far above an integrate-and-fire pixel's own
    noise = np.sqrt(np.maximum(med, 1e-3) / steps)
    hot = (r - med > params.hot_excess + params.hot_relative * med + noise)
    hot &= above_second > params.isolation
    hot &= med - far < params.bump * above_second
    dead = (counts == 0) & (med * steps >= params.dead_spikes)
    return DefectMap(hot, dead, int(steps), source)


class DefectEstimator:
    """Online spike counts of every pixel and the defect map they give.

    Parameters
    ----------
    layout : Layout
        Geometry of the packed frames pushed in.
    params : DefectParams
    """

    def __init__(self, layout: Layout, params: DefectParams | None = None) -> None:
        params = params or DefectParams()
        if params.run < 1 or params.duty < 1:
            raise ValueError(f"run {params.run} and duty {params.duty} must be >= 1 steps")
        self.layout = layout
        self.params = params
        self._counts = np.zeros(layout.frame_bytes * 8, np.int64)  # stored pixel order
        self.steps = 0  # counted steps
        self._since = 0  # counted steps since the map was last rebuilt
        self.map = DefectMap.empty(layout.shape)

    @property
    def confidence(self) -> float:
        """Counted steps over the warm-up, at most 1."""
        return min(1.0, self.steps / max(1, self.params.warmup))

    @property
    def ready(self) -> bool:
        return self.steps >= self.params.warmup

    def counts(self) -> np.ndarray:
        """Upright spike counts (H, W) over the counted steps."""
        return stored_to_image(self._counts, self.layout)

    def update(self, packed: np.ndarray, start: int) -> bool:
        """Count the sampled steps of packed frames ``packed`` (first one step ``start``);
        True when the map was rebuilt."""
        run = self.params.run
        duty = self.params.duty if self.ready else 1
        n = len(packed)
        t, counted = int(start), 0
        while t < start + n:
            end = min(start + n, (t // run + 1) * run)
            if (t // run) % duty == 0:
                count_packed(packed, t - start, end - start, self._counts)
                counted += end - t
            t = end
        self.steps += counted
        self._since += counted
        every = self.params.refresh_ready if self.map.steps >= self.params.warmup \
            else self.params.refresh
        if counted and (self._since >= every or self.map.steps == 0
                        and self.steps >= self.params.min_steps):
            self._since = 0
            self.map = classify(self.counts(), self.steps, self.params)
            return True
        return False
