"""Correction of flagged pixels before any reconstruction, in the spikes themselves.

A hot or dead pixel takes, step by step, the spikes of one good neighbour (its *donor*: of
the good side neighbours, the one whose long-run rate is the median of theirs; diagonals when
no side neighbour is good). Every method then sees a pixel with a plausible rate and plausible
intervals, so TFI, TFP, TFA, TFSTP, SNM, CSR and CFSR gain alike; the copy is done on the
packed words (:func:`correct_packed`), one bit per defect per step. Defects spread over
every cache line of a frame, so correcting a window reads and writes all of it: its cost is
bounded by memory (docs/results.md, "Sensor defects").

Two places run it, both through :func:`_copy_bits`: :class:`DefectCorrector` in the buffer of
a :class:`~cfsr.streaming.StreamingReconstructor` (the live path: it learns the map online
from every pushed block and corrects a step when a method first reads it) and
:class:`CorrectedRecording` on the windows read from a recording (the offline path, with the
map from the sidecar or from a first pass over the file).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from cfsr._jit import njit
from cfsr._packed import stored_to_image
from cfsr.defects.defect_map import DEFECTS_KEY, DefectMap, load_map
from cfsr.defects.estimate import DefectEstimator, DefectParams, classify
from cfsr.defects.gain import flatten, gain_from_counts, inverse_gain
from cfsr.layout import Layout
from cfsr.spikes import SpikeRecording

__all__ = [
    "DonorPlan",
    "plan_donors",
    "correct_packed",
    "DefectCorrector",
    "CorrectedRecording",
    "calibrate",
    "estimate_map",
    "corrected",
    "in_buffer",
    "map_of",
    "with_defects",
]

_SIDE = ((0, -1), (0, 1), (-1, 0), (1, 0))
_DIAGONAL = ((-1, -1), (-1, 1), (1, -1), (1, 1))


class DonorPlan(NamedTuple):
    """Stored pixel indices: ``targets[j]`` takes the spikes of ``donors[j]`` (int64)."""

    targets: np.ndarray
    donors: np.ndarray


def _stored_index(layout: Layout) -> np.ndarray:
    """Upright (H, W) image of each pixel's index in the stored (packed) raster."""
    return stored_to_image(np.arange(layout.frame_bytes * 8, dtype=np.int64), layout)


def plan_donors(dmap: DefectMap, layout: Layout, rates: np.ndarray | None = None) -> DonorPlan:
    """Pick a good neighbour for every flagged pixel of ``dmap``.

    ``rates``: upright long-run rates (spikes/step) used to pick the median side neighbour;
    without them the first good side neighbour is taken. A pixel with no good neighbour at
    all is left as it is.
    """
    bad = dmap.mask
    h, w = bad.shape
    if (h, w) != layout.shape:
        raise ValueError(f"defect map {w} x {h} does not fit frames {layout.width} x "
                         f"{layout.height}")
    index = _stored_index(layout)
    targets, donors = [], []
    for y, x in zip(*np.nonzero(bad), strict=True):
        for ring in (_SIDE, _DIAGONAL):
            good = [(y + dy, x + dx) for dy, dx in ring
                    if 0 <= y + dy < h and 0 <= x + dx < w and not bad[y + dy, x + dx]]
            if good:
                if rates is not None:
                    good.sort(key=lambda p: rates[p])
                pick = good[(len(good) - 1) // 2]
                targets.append(index[y, x])
                donors.append(index[pick])
                break
    t, d = np.asarray(targets, np.int64), np.asarray(donors, np.int64)
    order = np.argsort(t, kind="stable")  # in memory order: each frame's bytes once, in turn
    return DonorPlan(t[order], d[order])


@njit
def _copy_bits(packed, targets, donors):  # pragma: no cover - numba
    """Bit ``targets[j]`` of every frame of ``packed`` (n, bytes) := bit ``donors[j]``."""
    for t in range(packed.shape[0]):
        row = packed[t]
        for j in range(targets.shape[0]):
            p = targets[j]
            q = donors[j]
            bit = (np.int64(row[q >> 3]) >> (q & 7)) & 1
            keep = np.int64(row[p >> 3]) & ~(np.int64(1) << (p & 7))
            row[p >> 3] = np.uint8(keep | (bit << (p & 7)))
    return packed


def correct_packed(packed: np.ndarray, plan: DonorPlan, *, copy: bool = True) -> np.ndarray:
    """Packed frames ``(n, frame_bytes)`` with every target pixel given its donor's spikes
    (a corrected copy, or ``packed`` itself changed when ``copy=False``)."""
    out = np.array(packed, np.uint8, copy=True) if copy else packed
    if plan.targets.size and len(out):
        _copy_bits(out, plan.targets, plan.donors)
    return out


@dataclass
class DefectCorrector:
    """Learns the defect map from pushed blocks and corrects them (the live path).

    Parameters
    ----------
    layout : Layout
    defect_map : DefectMap, optional
        A map given from outside (sidecar, calibration file); then nothing is learned unless
        ``learn`` is True, and a learned map replaces it only once ready.
    learn : bool, optional
        Estimate the map online (default: when no map is given).
    enabled : bool
        False: learn (if asked) but leave the spikes as they are.
    """

    layout: Layout
    defect_map: DefectMap | None = None
    learn: bool | None = None
    enabled: bool = True
    params: DefectParams = field(default_factory=DefectParams)

    def __post_init__(self) -> None:
        if self.learn is None:
            self.learn = self.defect_map is None
        self.estimator = DefectEstimator(self.layout, self.params) if self.learn else None
        self.plan = plan_donors(self.map, self.layout)
        #: 1 / gain (float32 H, W) of a flat-field calibration, kept when a learned map
        #: replaces the given one (the stream cannot measure it); None: none given
        self._gain = self.defect_map.gain if self.defect_map else None
        self.inv_gain = inverse_gain(self._gain)
        #: bumped whenever the map in use changes (a live recording takes the newest)
        self.version = 0
        # per half of the mirrored ring, the steps [lo, hi) corrected in it (before_read)
        self._fixed = [(0, 0), (0, 0)]

    @property
    def map(self) -> DefectMap:
        """The map in use (given, learned, or empty)."""
        if self.defect_map is not None:
            return self.defect_map
        return self.estimator.map if self.estimator else DefectMap.empty(self.layout.shape)

    def learn_from(self, packed: np.ndarray, start: int) -> None:
        """Count packed frames ``packed`` (first frame step ``start``) into the online map."""
        est = self.estimator
        if est is not None and est.update(packed, start):
            # a learned map replaces a given one only once it is ready
            if self.defect_map is None or est.ready:
                self.defect_map = None
                self.plan = plan_donors(est.map, self.layout, est.counts())
                self._fixed = [(0, 0), (0, 0)]  # buffered steps get the new map when read
                self.version += 1

    def current(self) -> DefectMap:
        """The map in use with the given calibration's gain, if any (what a recording of
        this stream keeps in its sidecar)."""
        m = self.map
        return m if m.gain is self._gain else DefectMap(m.hot, m.dead, m.steps, m.source,
                                                        self._gain)

    # -- the mirrored ring of a StreamingReconstructor: steps are corrected when first read --
    def arrived(self, packed: np.ndarray, start: int) -> None:
        """Frames ``packed`` (steps ``start``..) entered the ring: learn from them; they are
        corrected only when read (:meth:`before_read`), so steps nobody reads cost nothing."""
        self.learn_from(packed, start)
        if start < max(hi for _, hi in self._fixed):  # the stream started again
            self._fixed = [(start, start), (start, start)]

    def before_read(self, buf: np.ndarray, cap: int, a: int, b: int) -> None:
        """Correct, in place, the rows a read of steps ``[a, b)`` returns from the mirrored
        ring ``buf`` of ``cap`` frames, where not corrected yet.

        Step s is stored twice, at rows ``s % cap`` (first half) and ``s % cap + cap``
        (second); the read is the slice from row ``a % cap``, so its first ``cap - a % cap``
        steps come from the first half and the rest from the second. Each half keeps the span
        of steps corrected in it, so a step costs one correction per half it is read from.
        """
        if not (self.enabled and self.plan.targets.size) or a >= b:
            return
        cut = a + cap - a % cap  # the first step the read takes from the second half
        for half, (x, y) in enumerate(((a, min(b, cut)), (cut, b))):
            if y > x:
                self._fix_half(buf, cap, half, x, y)

    def _fix_half(self, buf: np.ndarray, cap: int, half: int, a: int, b: int) -> None:
        """Correct steps ``[a, b)`` (at most ``cap``) in ``half`` of the ring, but those its
        corrected span already holds; the span grows to cover them."""
        lo, hi = self._fixed[half]
        if b < lo or a > hi:  # apart from what is corrected: start a new corrected span
            todo, self._fixed[half] = [(a, b)], (a, b)
        else:
            todo = [(a, min(b, lo)), (max(a, hi), b)]
            self._fixed[half] = (min(a, lo), max(b, hi))
        for x, y in todo:
            if y > x:  # rows x % cap .. of this half, with no wrap inside one read's half
                r = x % cap + half * cap
                _copy_bits(buf[r : r + (y - x)], self.plan.targets, self.plan.donors)

    def flatten(self, out: Any, method: Any = None) -> Any:
        """``method``'s output with the calibration's gain divided out (when enabled and
        given: :func:`cfsr.defects.gain.flatten`)."""
        return flatten(out, self.inv_gain, method) if self.enabled else out

    def state(self) -> dict[str, Any]:
        """What a status shows: ``state`` (off / learning / ready / given), the counts of hot
        and dead pixels, the steps counted, the confidence (0..1) and whether a flat-field
        ``gain`` map is applied."""
        m = self.map
        est = self.estimator
        if not self.enabled:
            state = "off"
        elif self.defect_map is not None:
            state = "given"
        else:
            state = "ready" if est is not None and est.ready else "learning"
        return {
            "state": state,
            "hot": m.n_hot,
            "dead": m.n_dead,
            "steps": est.steps if est is not None else m.steps,
            "confidence": est.confidence if est is not None else 1.0,
            "gain": self.inv_gain is not None,
        }


@dataclass
class CorrectedRecording(SpikeRecording):
    """A recording read through a defect correction: ``packed``/``frames`` return corrected
    copies of the stored frames (which stay untouched in ``packed_frames``); ``inv_gain``:
    1 / the calibration's gain, which every output read through :func:`cfsr.reconstruct_outputs`
    or the offline streaming path is divided by (:meth:`flatten`)."""

    defect_map: DefectMap | None = None
    plan: DonorPlan | None = None
    inv_gain: np.ndarray | None = None

    def flatten(self, out: Any, method: Any = None) -> Any:
        """``method``'s output with the calibration's gain divided out (if any)."""
        return flatten(out, self.inv_gain, method)

    def packed(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        raw = super().packed(start, stop)
        return raw if self.plan is None else correct_packed(raw, self.plan)


def in_buffer(rec: SpikeRecording) -> tuple[SpikeRecording, DefectCorrector | None]:
    """How a reconstructor's buffer reads ``rec`` with no corrected copy: a
    :class:`CorrectedRecording` gives its stored frames and a corrector with its donors, which
    corrects each buffered step in place when first read (one pass over the bits, where a
    corrected copy is a second pass over every byte); its gain stays with ``rec.flatten``.
    Any other recording: itself, no corrector."""
    if not isinstance(rec, CorrectedRecording) or rec.plan is None:
        return rec, None
    raw = SpikeRecording(rec.packed_frames, rec.layout, rec.rate_hz, rec.meta, rec.path)
    m = rec.defect_map
    fix = DefectCorrector(rec.layout, DefectMap(m.hot, m.dead, m.steps, m.source))
    fix.plan = rec.plan
    return raw, fix


def map_of(rec: SpikeRecording) -> DefectMap | None:
    """The defect map in ``rec``'s sidecar (checked), or None."""
    obj = rec.meta.get(DEFECTS_KEY)
    if obj is None:
        return None
    return DefectMap.from_dict(obj, rec.layout.shape, where=f"{rec.path or 'recording'} defects")


def estimate_map(rec: SpikeRecording, steps: int = 2000, *,
                 params: DefectParams | None = None) -> tuple[DefectMap, np.ndarray]:
    """A first pass over ``rec``'s first ``steps`` steps: the map and the upright counts
    (every step counted: offline there is no stream to keep up with)."""
    base = params or DefectParams()
    est = DefectEstimator(rec.layout, DefectParams(**{**base.__dict__, "duty": 1}))
    n = min(int(steps), rec.n_frames)
    for a in range(0, n, 1024):
        est.update(rec.packed(a, min(n, a + 1024)), a)
    return classify(est.counts(), est.steps, est.params), est.counts()


def calibrate(rec: SpikeRecording, steps: int | None = None) -> DefectMap:
    """A flat-field calibration: the defect map and every pixel's gain
    (:func:`cfsr.defects.gain.gain_from_counts`) from ``rec``, a recording of uniform light,
    over its first ``steps`` steps (default all); hot are also the pixels far above the
    gains' spread. A sensor with shot noise needs about
    ``(1 / precision)**2`` spikes a pixel: 10,000 (a second at 0.25 spikes/step) for 1 %."""
    found, counts = estimate_map(rec, rec.n_frames if steps is None else steps)
    # uniform light has no texture to hide a hot pixel in: one whose count stands 8 robust
    # deviations of the spread (at least 20 %) above the median is hot, where the stream's
    # rule, made to spare textures, can miss the faintest ones beside a bright neighbour
    g = counts / max(1.0, float(np.median(counts[~found.mask])))
    spread = 1.4826 * float(np.median(np.abs(g[~found.mask] - 1.0)))
    hot = found.hot | ((g > 1.0 + max(8.0 * spread, 0.2)) & ~found.dead)
    return DefectMap(hot, found.dead, found.steps, "calibration",
                     gain_from_counts(counts, found.steps, hot | found.dead))


def corrected(rec: SpikeRecording, defect_map: DefectMap | None = None, *,
              steps: int = 2000) -> CorrectedRecording:
    """``rec`` read through the correction of ``defect_map`` (default: the sidecar's, else one
    estimated from its first ``steps`` steps)."""
    rates = None
    if defect_map is None:
        defect_map = map_of(rec)
    if defect_map is None:
        defect_map, counts = estimate_map(rec, steps)
        rates = counts / max(1, defect_map.steps)
    return CorrectedRecording(rec.packed_frames, rec.layout, rec.rate_hz, dict(rec.meta),
                              rec.path, defect_map, plan_donors(defect_map, rec.layout, rates),
                              inverse_gain(defect_map.gain))


def with_defects(rec: SpikeRecording, option: str | None) -> SpikeRecording:
    """``rec`` as the ``--defects`` option asks: ``"sidecar"`` (default, None) corrects with the
    map in the recording's sidecar and leaves a recording without one as it is; ``"auto"``
    uses the sidecar's map, else one found in the first 2,000 steps; ``"off"`` leaves the
    spikes as recorded; anything else is a calibration file (:func:`load_map`)."""
    if option == "off":
        return rec
    if option in (None, "sidecar"):
        given = map_of(rec)
        return rec if given is None else corrected(rec, given)
    if option == "auto":
        return corrected(rec)
    return corrected(rec, load_map(option, rec.layout.shape))
