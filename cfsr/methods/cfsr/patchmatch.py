"""PatchMatch temporal fusion for the fine reconstruction (CFSR paper, fine stage).

For every pixel of the fine dynamic region, the 6 x 6 patch around it in the reference frame
(TFI at t) is matched in each target frame (TFI at t +- step*i, i = 1..count; the paper uses
t +- 5i, i = 1..10); the matched centre values of all targets and the reference are averaged.
Patches of neighbouring pixels overlap, so this is the "overlapping patches" form of the paper's
patch search.

The nearest-neighbour field (NNF) per target is found with PatchMatch (Barnes et al., 2009):
alternating forward/backward scans that try the offsets of the already-visited left/up
(right/down) neighbours (propagation) and random offsets around the current best at radii
``max_radius, max_radius/2, ..., 1`` (random search). Only the masked pixels are visited.

Two schedules, two entry points (:func:`nnf_multi` picks one from ``offsets_steps``):

* :func:`nnf_independent` (the original form): every target starts from zero motion and gets
  the full search, pixel by pixel (the SSD over the patch stops early once it exceeds the
  current best); the targets are independent and run in parallel.
* :func:`nnf_temporal` (each target's signed step from t), the temporal schedule: motion over
  these short spans is smooth, so the targets run by increasing ``|step|`` and each starts from
  offsets *predicted* from the NNFs already found - the nearer target on the same side scaled by
  the step ratio (linear motion), the mirror target negated, and the quadratic through the
  nearest pair ``t -+ u`` (curved paths: rotation). A predicted target then needs only a local
  search (``near_radius``, ``near_iters`` scans); only the first target gets the full one
  (zero-motion start, ``max_radius``, ``iters`` scans). Targets depend on each other, so the
  parallelism is over bands of ``band`` full-frame rows instead (propagation stays inside a
  band).

  This schedule searches *blocks*: the masked pixels of one row inside one 8-column cell of the
  full frame. Each candidate offset is tried for every pixel of the block at once, and each
  pixel keeps its own best. The candidates of a block are the predicted offsets of its two end
  pixels (first scan), the offsets of the already-visited neighbours (the row above/below the
  block and the pixel before/after it: propagation), and, at radii ``r, r/2, ..., 1``, one
  random offset around each distinct best of the block: in the full search (first target) the
  current bests, re-collected at every radius; in a predicted target's local search the first
  two distinct bests after propagation, fixed for all radii (the draws then do not depend on
  each other's results and overlap in the CPU; 0.05 dB either way on disk/fan/car). For the
  6 x 6 patch the eight SSDs of a block share their rows: the squared differences of the 6 rows
  are summed per column over 16 columns with 8-wide vectors, then box-summed over 6 columns and
  folded into the block's per-lane bests with a vector compare-and-select
  (:func:`cfsr._simd.box6x8_min`, LLVM IR, or its pure-numba twin when ``CFSR_SIMD=0``: no
  early exit, no per-pixel branches); other patch sizes use the same per-column sums in
  scalar code, and offsets that leave the frame for some pixel of the block fall back to
  clamped per-pixel SSDs (no software prefetch: the hardware prefetcher follows these rows, and
  explicit prefetches of every candidate's rows cost 10-15 % of the search). On the simulated
  disk/fan/car scenes this is
  2-3x faster than the per-pixel schedule at equal or better PSNR.

Randomness comes from a counter-based hash of (seed, target, the pixel's - or, in the temporal
schedule, the block's - full-frame position, iteration, radius), and the bands and blocks are cut
at fixed full-frame rows and columns, so the result does not depend on thread scheduling or the
number of threads (the same window always gives the same frame, which keeps the streaming and
whole-array paths identical) nor on which other pixels are matched (a crop and the whole frame
draw alike, away from the crop's borders).

Matching happens on a *guide* (a lightly smoothed TFI): matching the raw TFI locks onto its
quantisation noise. The averaged values are the raw TFI rates at the matched positions.

References
----------
The CFSR paper (coarse-to-fine spike reconstruction), fine stage: patch search over the TFI
frames t +- 5i and averaging of the matches (Eq. 3-14 as read in ``docs/methods.md``, section
"CFSR: the fine stage", step 5, which also gives the settings CFSR uses); the temporal schedule
above is ours, not the paper's.
C. Barnes, E. Shechtman, A. Finkelstein, D. B. Goldman, "PatchMatch: a randomized
correspondence algorithm for structural image editing", ACM TOG 28(3), 2009.
"""

from __future__ import annotations

import numpy as np

from cfsr import _simd
from cfsr.methods.cfsr._patchmatch_kernels import (
    _EXTRA,
    _PREDICTIONS,
    _ROW_KEY,
    _SOURCES,
    BLOCK,
    _Blocks,
    _fuse_kernel,
    _nnf_independent_kernel,
    _nnf_temporal_kernel,
    _Pixels,
    _Plan,
    _Search,
)

__all__ = [
    "PATCH",
    "ITERS",
    "MAX_RADIUS",
    "NEAR_RADIUS",
    "NEAR_ITERS",
    "BAND",
    "BLOCK",
    "nnf_independent",
    "nnf_temporal",
    "nnf_multi",
    "fuse_matches",
    "patchmatch_fuse",
]


#: Default patch side (pixels): the paper's 6 x 6 patch (rows/columns -2..+3 of the pixel).
PATCH = 6


#: Default scans of a full search (alternating direction).
ITERS = 3


#: Default largest random-search radius of a full search (pixels); halved down to 1.
MAX_RADIUS = 16


#: Default radius and scans of a predicted target's local search (temporal schedule).
NEAR_RADIUS = 2


NEAR_ITERS = 1


#: Default band height (full-frame rows) of the temporal schedule's parallel work.
BAND = 16




def _margins(patch: int, extra: int) -> tuple[int, int, int]:
    """Rows/columns of padding ``(before, rows after, columns after)`` for :func:`_ssd`."""
    # (patch - 1) // 2 before: the 2-before/3-after 6 x 6 patch of the paper's default, and a
    # centred window for odd sizes (patch // 2 - 1 went negative for a 1 x 1 patch)
    lo = (patch - 1) // 2
    return lo, patch - 1 - lo, patch - 1 - lo + extra


def _fill_margins(out: np.ndarray, lo: int, hh: int, ww: int) -> None:
    """Edge-replicate the interior ``out[..., lo:lo + hh, lo:lo + ww]`` into the margins."""
    out[..., :lo, lo : lo + ww] = out[..., lo : lo + 1, lo : lo + ww]
    out[..., lo + hh :, lo : lo + ww] = out[..., lo + hh - 1 : lo + hh, lo : lo + ww]
    out[..., :, :lo] = out[..., :, lo : lo + 1]
    out[..., :, lo + ww :] = out[..., :, lo + ww - 1 : lo + ww]


def _pad(img: np.ndarray, patch: int, extra: int = 0) -> np.ndarray:
    """Edge-replicate padding of the last two axes for :func:`_ssd` (float32, contiguous).

    ``extra`` more columns on the right (edge values too) let the block search read 16 columns
    from any block start inside the frame. The same values as ``np.pad(..., mode="edge")``,
    written by slice assignments (several times faster on the target stack).
    """
    lo, bottom, right = _margins(patch, extra)
    hh, ww = img.shape[-2:]
    out = np.empty(img.shape[:-2] + (hh + lo + bottom, ww + lo + right), np.float32)
    out[..., lo : lo + hh, lo : lo + ww] = img
    _fill_margins(out, lo, hh, ww)
    return out


def padded_guides(n: int, height: int, width: int, patch: int = PATCH):
    """A stack of ``n`` guide images of ``height x width`` already laid out as the temporal
    search reads them: ``(buffer, interior)``, an uninitialised float32 buffer with the
    search's margins and the ``(n, height, width)`` view of its images. Write the guides
    (reference first, then the targets) into ``interior``, call :func:`finish_padding`, and
    pass ``padded=buffer`` to :func:`nnf_temporal` (or :func:`patchmatch_fuse`): the search
    then reads the buffer instead of copying the guides into a padded one."""
    lo, bottom, right = _margins(patch, _EXTRA)
    buf = np.empty((n, height + lo + bottom, width + lo + right), np.float32)
    return buf, buf[:, lo : lo + height, lo : lo + width]


def finish_padding(buf: np.ndarray, patch: int = PATCH) -> np.ndarray:
    """Fill the margins of a :func:`padded_guides` buffer from its images (edge values)."""
    lo, bottom, right = _margins(patch, _EXTRA)
    _fill_margins(buf, lo, buf.shape[-2] - lo - bottom, buf.shape[-1] - lo - right)
    return buf


def _temporal_plan(steps, iters: int, max_radius: int, near_radius: int, near_iters: int) -> _Plan:
    """Order, offset predictors, radii and scans of the targets from their signed steps.

    Targets run by increasing ``|step|`` (the ``t - s`` side first). Each gets up to three
    predictions, linear combinations of the NNFs of targets already done: the nearer target
    on the same side scaled by the ratio of the steps (linear motion), the mirror target
    ``t -+ s`` negated, and the quadratic through the nearest pair ``t -+ u`` (constant
    acceleration: curved paths such as rotation). A predicted target then needs only a
    local search (``near_radius``, ``near_iters`` scans); one without prediction gets the
    full search (zero-motion start, ``max_radius``, ``iters`` scans).
    """
    steps = [int(v) for v in steps]
    n = len(steps)
    src = np.full((n, _PREDICTIONS, _SOURCES), -1, np.int64)
    wt = np.zeros((n, _PREDICTIONS, _SOURCES), np.float64)
    radius = np.full(n, max_radius, np.int64)
    scans = np.full(n, iters, np.int64)
    order = sorted(range(n), key=lambda i: (abs(steps[i]), steps[i] > 0, i))
    done: list[int] = []
    for i in order:
        s = steps[i]
        preds: list[tuple[tuple[int, float], ...]] = []
        if s != 0:
            same = [k for k in done if steps[k] * s > 0 and abs(steps[k]) < abs(s)]
            if same:
                a = max(same, key=lambda k: abs(steps[k]))
                preds.append(((a, s / steps[a]),))
            mirror = [k for k in done if steps[k] == -s]
            if mirror:
                preds.append(((mirror[0], -1.0),))
            pos = {steps[k]: k for k in done if 0 < steps[k] < abs(s)}
            neg = {-steps[k]: k for k in done if 0 < -steps[k] < abs(s)}
            both = sorted(set(pos) & set(neg))
            if both:
                # off(v) = a v + b v^2 through off(+u) and off(-u)
                u = float(both[-1])
                lin, quad = s / (2 * u), s * s / (2 * u * u)
                preds.append(((pos[both[-1]], lin + quad), (neg[both[-1]], quad - lin)))
        for c, pred in enumerate(preds):
            for k, (t, f) in enumerate(pred):
                src[i, c, k] = t
                wt[i, c, k] = f
        if preds:
            radius[i] = min(max_radius, near_radius)
            scans[i] = near_iters
        done.append(i)
    return _Plan(np.array(order, np.int64), src, wt, radius, scans)


def _independent_plan(n: int, iters: int, max_radius: int) -> _Plan:
    """Every target on its own: no predictions, the full search (``max_radius``, ``iters``)."""
    return _Plan(
        np.arange(n, dtype=np.int64),
        np.full((n, _PREDICTIONS, _SOURCES), -1, np.int64),
        np.zeros((n, _PREDICTIONS, _SOURCES), np.float64),
        np.full(n, max_radius, np.int64),
        np.full(n, iters, np.int64),
    )


def _prepare(ref, targets, mask, patch: int, iters: int, max_radius: int, origin):
    """Checked float32 images, the masked pixels and the outputs of both searches."""
    ref = np.ascontiguousarray(ref, dtype=np.float32)
    targets = np.ascontiguousarray(targets, dtype=np.float32)
    found = _matching(ref.shape, targets.shape, mask, patch, iters, max_radius, origin)
    return (ref, targets, *found)


def _matching(ref_shape, targets_shape, mask, patch: int, iters: int, max_radius: int, origin):
    """The masked pixels and the (uninitialised) outputs for images of these shapes, settings
    checked."""
    if len(targets_shape) != 3 or tuple(targets_shape[1:]) != tuple(ref_shape):
        got, want = tuple(targets_shape), tuple(ref_shape)
        raise ValueError(f"targets {got} do not match reference {want}")
    if patch < 1 or iters < 0 or max_radius < 0:
        raise ValueError(f"bad PatchMatch settings patch={patch} iters={iters} r={max_radius}")
    ys, xs = np.nonzero(np.asarray(mask, dtype=bool))
    ys = ys.astype(np.int64)
    xs = xs.astype(np.int64)
    index = np.full(tuple(ref_shape), -1, np.int64)
    index[ys, xs] = np.arange(ys.size)
    # the random search of a pixel is keyed by its position in the full frame, so the same
    # pixel draws the same offsets whatever else is matched (crop or whole frame)
    keys = (ys + int(origin[0])) * np.int64(_ROW_KEY) + (xs + int(origin[1]))
    # uninitialised: both kernels set every pixel's start (offset 0, cost inf or its own) in
    # their threads, so the pages are first touched there and not zeroed twice
    off = np.empty((targets_shape[0], ys.size, 2), np.int32)
    cost = np.empty((targets_shape[0], ys.size), np.float32)
    return _Pixels(ys, xs, index, keys), off, cost


def _search(patch: int, seed: int) -> _Search:
    return _Search(int(patch), np.uint64(int(seed) % (1 << 64)), _simd.choice())


def nnf_independent(
    ref: np.ndarray,
    targets: np.ndarray,
    mask: np.ndarray,
    *,
    patch: int = PATCH,
    iters: int = ITERS,
    max_radius: int = MAX_RADIUS,
    seed: int = 0,
    origin: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest-neighbour fields from ``ref`` to each of ``targets``, each target on its own.

    Every target gets the full search from zero motion, pixel by pixel: ``iters`` alternating
    scans of propagation and random search at radii ``max_radius, max_radius / 2, ..., 1``,
    the SSD stopping early once above the pixel's best. The targets run in parallel.

    Parameters
    ----------
    ref : ndarray (H, W) float32
        Guide image of the reference frame.
    targets : ndarray (N, H, W) float32
        Guide images of the target frames.
    mask : ndarray (H, W) bool
        Pixels whose patches are matched.
    patch : int
        Patch side (pixels); the paper uses 6.
    iters : int
        PatchMatch scans (alternating direction) of a full search.
    max_radius : int
        Largest random-search radius (pixels) of a full search.
    seed : int
        Seed of the counter-based random search (any int; reduced modulo 2**64).
    origin : (int, int)
        Position of ``ref[0, 0]`` in the full frame: the random draws are keyed by full-frame
        positions (and the temporal schedule's blocks and bands are cut there), so a crop and
        the whole frame draw alike.

    Returns
    -------
    ys, xs : ndarray (M,) int64
        Coordinates of the matched pixels (row-major order).
    offsets : ndarray (N, M, 2) int32
        (dy, dx) from each pixel to its match in each target.
    cost : ndarray (N, M) float32
        SSD of each match (guide units squared, summed over the patch).
    """
    ref, targets, pixels, off, cost = _prepare(ref, targets, mask, patch, iters, max_radius, origin)
    if pixels.ys.size and targets.shape[0]:
        _nnf_independent_kernel(
            _pad(ref, patch),
            _pad(targets, patch),
            pixels,
            _independent_plan(targets.shape[0], iters, max_radius),
            _search(patch, seed),
            off,
            cost,
        )
    return pixels.ys, pixels.xs, off, cost


def nnf_temporal(
    ref: np.ndarray,
    targets: np.ndarray,
    mask: np.ndarray,
    offsets_steps,
    *,
    patch: int = PATCH,
    iters: int = ITERS,
    max_radius: int = MAX_RADIUS,
    near_radius: int = NEAR_RADIUS,
    near_iters: int = NEAR_ITERS,
    band: int = BAND,
    seed: int = 0,
    origin: tuple[int, int] = (0, 0),
    padded: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest-neighbour fields from ``ref`` to each of ``targets`` by the temporal schedule.

    ``offsets_steps`` gives each target's signed step from the reference. Targets run by
    increasing ``|step|``; one without an earlier target to predict from gets the full search
    (``iters``, ``max_radius``), every other starts from the offsets predicted by the nearer
    targets and gets a local search (``near_iters`` scans at radii ``near_radius .. 1``).
    Pixels are searched in blocks of :data:`BLOCK` full-frame columns of one row, and the
    work is split into bands of ``band`` full-frame rows that run in parallel (propagation
    stays inside a band). See the module docstring.

    Parameters
    ----------
    ref, targets, mask, patch, iters, max_radius, seed, origin
        As in :func:`nnf_independent`.
    offsets_steps : sequence of int, length N
        Each target's signed step from the reference frame.
    near_radius, near_iters : int
        Random-search radius (pixels) and scans of a predicted target's local search.
    band : int
        Height (full-frame rows) of the bands that run in parallel.
    padded : ndarray (N + 1, ...) float32, optional
        ``ref`` and ``targets`` already padded (:func:`padded_guides`, :func:`finish_padding`;
        ``ref`` and ``targets`` are then views of its images): read as they are, not copied.

    Returns
    -------
    ys, xs, offsets, cost
        As in :func:`nnf_independent`.
    """
    steps = [int(v) for v in offsets_steps]
    if len(steps) != np.shape(targets)[0]:
        raise ValueError(f"{len(steps)} offsets_steps for {np.shape(targets)[0]} targets")
    if padded is None:
        ref, targets, pixels, off, cost = _prepare(
            ref, targets, mask, patch, iters, max_radius, origin
        )
    else:  # the images are the padded buffer's: only their shapes are checked
        pixels, off, cost = _matching(
            np.shape(ref), np.shape(targets), mask, patch, iters, max_radius, origin
        )
        lo, bottom, right = _margins(patch, _EXTRA)
        n, hh, ww = np.shape(targets)
        want = (n + 1, hh + lo + bottom, ww + lo + right)
        if padded.shape != want or padded.dtype != np.float32 or not padded.flags.c_contiguous:
            raise ValueError(f"padded guides {padded.shape} {padded.dtype}, need {want} float32")
    ys, xs = pixels.ys, pixels.xs
    if ys.size and np.shape(targets)[0]:
        plan = _temporal_plan(steps, iters, max_radius, near_radius, near_iters)
        # blocks of masked pixels in one row and one BLOCK-column cell of the full frame, and
        # bands of ``band`` full-frame rows: a crop and the whole frame cut alike
        fy = ys + int(origin[0])
        cell = (xs + int(origin[1])) // BLOCK
        new = np.ones(ys.size, bool)
        new[1:] = (np.diff(fy) != 0) | (np.diff(cell) != 0)
        starts = np.append(np.nonzero(new)[0], ys.size).astype(np.int64)
        bfy = fy[starts[:-1]]
        bkeys = bfy * np.int64(_ROW_KEY) + cell[starts[:-1]]
        bid = bfy // max(1, int(band))
        cuts = np.nonzero(np.diff(bid))[0] + 1
        bands = np.concatenate([[0], cuts, [starts.size - 1]]).astype(np.int64)
        _nnf_temporal_kernel(
            _pad(ref, patch, _EXTRA) if padded is None else padded[0],
            _pad(targets, patch, _EXTRA) if padded is None else padded[1:],
            pixels,
            _Blocks(starts, bkeys, bands),
            plan,
            _search(patch, seed),
            off,
            cost,
        )
    return ys, xs, off, cost


# keywords of the temporal schedule alone (nnf_multi drops them for the independent one)
_TEMPORAL_ONLY = ("near_radius", "near_iters", "band", "padded")


def nnf_multi(
    ref: np.ndarray, targets: np.ndarray, mask: np.ndarray, *, offsets_steps=None, **search
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest-neighbour fields from ``ref`` to each of ``targets`` on the ``mask`` pixels.

    Picks the schedule: without ``offsets_steps``, :func:`nnf_independent` (every target its
    own full search; ``near_radius``, ``near_iters``, ``band`` and ``padded`` are accepted and
    not used);
    with them (each target's signed step from the reference), :func:`nnf_temporal`. The
    keywords ``search`` (``patch``, ``iters``, ``max_radius``, ``seed``, ``origin``, ...), their
    defaults and the result are theirs.
    """
    if offsets_steps is None:
        kept = {k: v for k, v in search.items() if k not in _TEMPORAL_ONLY}
        return nnf_independent(ref, targets, mask, **kept)
    return nnf_temporal(ref, targets, mask, offsets_steps, **search)


def fuse_matches(
    ref_raw: np.ndarray,
    raw: np.ndarray,
    matches,
    *,
    patch: int = PATCH,
    h: float = 0.0,
    wanted: np.ndarray | None = None,
) -> np.ndarray:
    """Average the reference value with the matched values of every target at the given pixels.

    ``matches`` is ``(ys, xs, offsets, cost)``, the result of :func:`nnf_multi`. Weights are
    ``exp(-SSD / (patch**2 * h**2))`` (non-local-means form); ``h <= 0`` gives the plain
    average of the paper. A target whose cost is infinite has no match for the pixel (every
    patch its search tried read NaN guides: CFSR leaves NaN where it computed none) and adds
    nothing. ``wanted`` (bool ``(M,)``): only these pixels are averaged, the others take
    ``ref_raw`` (CFSR matches pixels whose own value it does not use: they carry the search's
    propagation). Returns float32 ``(M,)`` in the units of ``raw``.
    """
    ys, xs, offsets, cost = matches
    out = np.empty(ys.size, np.float32)
    if ys.size == 0:
        return out
    ref_raw = np.ascontiguousarray(ref_raw, dtype=np.float32)
    if wanted is None:
        js = np.arange(ys.size, dtype=np.int64)
    else:
        wanted = np.asarray(wanted, dtype=bool)
        if wanted.shape != ys.shape:
            raise ValueError(f"wanted {wanted.shape} for {ys.size} matched pixels")
        js = np.flatnonzero(wanted).astype(np.int64)
        rest = ~wanted
        out[rest] = ref_raw[ys[rest], xs[rest]]
    scale = float(patch * patch * h * h) if h > 0 else 0.0
    return _fuse_kernel(
        ref_raw,
        np.ascontiguousarray(raw, dtype=np.float32),
        ys,
        xs,
        js,
        offsets,
        cost,
        scale,
        out,
    )


def patchmatch_fuse(
    ref_raw: np.ndarray,
    ref_guide: np.ndarray,
    raw: np.ndarray,
    guides: np.ndarray,
    mask: np.ndarray,
    *,
    patch: int = PATCH,
    h: float = 0.0,
    wanted: np.ndarray | None = None,
    **search,
) -> np.ndarray:
    """Refine ``ref_raw`` on ``mask`` by PatchMatch over the target frames.

    Matching uses the guides (:func:`nnf_multi` with ``patch`` and the keywords ``search``:
    ``offsets_steps`` picks the schedule); the averaged values are the raw rates
    (:func:`fuse_matches`, weight scale ``h``). Pixels outside ``mask`` keep ``ref_raw``, and so
    do those outside ``wanted`` (bool ``(H, W)``, default all): they are matched, and carry
    the propagation, but not averaged. Returns float32 ``(H, W)``.
    """
    out = np.array(ref_raw, dtype=np.float32, copy=True)
    if raw.shape[0] == 0 or not np.any(mask):
        return out
    matches = nnf_multi(ref_guide, guides, mask, patch=patch, **search)
    ys, xs = matches[:2]
    sel = None if wanted is None else np.asarray(wanted, dtype=bool)[ys, xs]
    out[ys, xs] = fuse_matches(ref_raw, raw, matches, patch=patch, h=h, wanted=sel)
    return out
