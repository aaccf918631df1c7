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

from typing import NamedTuple

import numpy as np
from numba import prange

from cfsr import _simd
from cfsr._jit import njit
from cfsr._simd import LANES, READ_COLS, Lanes, box6x8_update
from cfsr._splitmix import GOLDEN, mix64

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
#: Block width (full-frame columns) of the temporal schedule: one vector lane per column.
BLOCK = LANES

# right-hand padding columns beyond the patch's for the block search (its vector kernel reads
# READ_COLS columns from a block start inside the frame)
_EXTRA = READ_COLS - _simd.PATCH
# the full-frame key of a pixel or block is row * _ROW_KEY + column (or 8-column cell)
_ROW_KEY = 1 << 20
# the draw of scan ``it`` at radius ``r`` is keyed ``it * _SCAN_KEY + r`` (radii below it)
_SCAN_KEY = 64
# room for a block's candidate offsets (at most 6 predictions, BLOCK + 1 neighbours or BLOCK
# distinct bests at a time)
_MAX_CANDIDATES = 64
# a target's offsets are predicted up to _PREDICTIONS ways, each from up to _SOURCES earlier
# targets (same side scaled, mirror negated; quadratic through a pair)
_PREDICTIONS = 3
_SOURCES = 2
# a predicted target's local search draws around this many of a block's distinct bests
_NEAR_SEEDS = 2
# no offset yet: a sentinel no prediction equals
_NO_OFFSET = -(1 << 40)
# pixels per parallel chunk of the fusion
_FUSE_CHUNK = 1024


class _Pixels(NamedTuple):
    """The masked pixels, row-major."""

    ys: np.ndarray  #: int64 (M,): rows
    xs: np.ndarray  #: int64 (M,): columns
    index: np.ndarray  #: int64 (H, W): each pixel's position in ys/xs, -1 if unmasked
    keys: np.ndarray  #: int64 (M,): full-frame keys (seed the independent search's draws)


class _Blocks(NamedTuple):
    """The temporal schedule's blocks (masked pixels of one row and one BLOCK-column cell of
    the full frame) and bands (blocks of ``band`` full-frame rows)."""

    start: np.ndarray  #: int64 (B + 1,): first pixel of each block, then M
    keys: np.ndarray  #: int64 (B,): full-frame keys (seed the block's draws)
    bands: np.ndarray  #: int64 (nbands + 1,): first block of each band, then B


class _Plan(NamedTuple):
    """Per target: order of search, predictors, random-search radius and scans."""

    order: np.ndarray  #: int64 (N,): targets in the order they are searched
    #: int64 (N, _PREDICTIONS, _SOURCES): the earlier targets each prediction combines (-1: none)
    src: np.ndarray
    wt: np.ndarray  #: float64 (N, _PREDICTIONS, _SOURCES): their weights
    radius: np.ndarray  #: int64 (N,): largest random-search radius
    scans: np.ndarray  #: int64 (N,): scans


class _Search(NamedTuple):
    """Settings shared by the kernels."""

    patch: int  #: patch side
    seed: np.uint64  #: seed of the counter-based draws
    #: the 6 x 6 block search's kernel (:func:`cfsr._simd.choice`): True, the LLVM intrinsic;
    #: None, its numba twin (another type: a kernel compiled and cached for each)
    simd: bool | None


@njit(helper=True)
def _rand2(seed, a, b, c, r):  # pragma: no cover - numba
    """Two uniform integers in [-r, r] from the counter (seed, a, b, c)."""
    z = mix64(seed + GOLDEN * np.uint64(a + 1))
    z = mix64(z + GOLDEN * np.uint64(b + 1))
    z = mix64(z + GOLDEN * np.uint64(c + 1))
    span = np.uint64(2 * r + 1)
    dy = np.int64(z % span) - r
    dx = np.int64((z >> np.uint64(32)) % span) - r
    return dy, dx


@njit(helper=True)
def _clamp(v, lo, hi):  # pragma: no cover - numba
    return lo if v < lo else (hi if v > hi else v)


@njit(helper=True)
def _ssd(ref, tgt, y, x, ty, tx, patch, limit):  # pragma: no cover - numba
    """SSD of the patch at (y, x) in ``ref`` and (ty, tx) in ``tgt``; stops above ``limit``.

    ``ref`` and ``tgt`` are edge-padded by :func:`_pad` (``(patch - 1) // 2`` rows/columns
    before, the rest after), so the patch rows/columns ``y - (patch - 1) // 2 .. y + patch // 2``
    of the unpadded image (6 x 6 for patch 6, centred for odd sizes, clamped at borders) are
    ``y .. y + patch - 1`` here:
    no per-pixel clamping in the inner loop, the same values and summation order.
    """
    s = 0.0
    for dy in range(patch):
        rr = ref[y + dy]
        qr = tgt[ty + dy]
        for dx in range(patch):
            d = rr[x + dx] - qr[tx + dx]
            s += d * d
        if s > limit:
            return s
    return s


@njit(helper=True)
def _cost(ref, tgt, y, x, ty, tx, patch, limit):  # pragma: no cover - numba
    """:func:`_ssd`; the default 6 x 6 patch passes a constant (inlined, its loops unroll)."""
    if patch == _simd.PATCH:
        return _ssd(ref, tgt, y, x, ty, tx, _simd.PATCH, limit)
    return _ssd(ref, tgt, y, x, ty, tx, patch, limit)


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


@njit(hot=True)
def _nnf_independent_kernel(ref, targets, pixels, plan, search, off, cost):
    # pragma: no cover - numba
    """Independent full searches, one target per thread (see :func:`nnf_independent`)."""
    ys, xs, index, keys = pixels
    patch = search.patch
    seed = search.seed
    n_t = targets.shape[0]
    h = targets.shape[1] - patch + 1
    w = targets.shape[2] - patch + 1
    m = ys.shape[0]
    for i in prange(n_t):
        tgt = targets[i]
        iters = plan.scans[i]
        max_r = plan.radius[i]
        for j in range(m):
            off[i, j, 0] = 0
            off[i, j, 1] = 0
            cost[i, j] = _cost(ref, tgt, ys[j], xs[j], ys[j], xs[j], patch, np.inf)
        for it in range(iters):
            fwd = it % 2 == 0
            d = -1 if fwd else 1
            for jj in range(m):
                j = jj if fwd else m - 1 - jj
                y = ys[j]
                x = xs[j]
                by = off[i, j, 0]
                bx = off[i, j, 1]
                best = cost[i, j]
                # propagation from the already-visited horizontal and vertical neighbours
                for k in range(2):
                    ny = y + d if k == 1 else y
                    nx = x + d if k == 0 else x
                    if ny < 0 or ny >= h or nx < 0 or nx >= w:
                        continue
                    nj = index[ny, nx]
                    if nj < 0:
                        continue
                    cy = off[i, nj, 0]
                    cx = off[i, nj, 1]
                    if cy == by and cx == bx:
                        continue
                    ty = _clamp(y + cy, 0, h - 1)
                    tx = _clamp(x + cx, 0, w - 1)
                    c = _cost(ref, tgt, y, x, ty, tx, patch, best)
                    if c < best:
                        best = c
                        by = ty - y
                        bx = tx - x
                # random search around the current best at halving radii
                r = max_r
                while r >= 1:
                    ry, rx = _rand2(seed, i, keys[j], it * _SCAN_KEY + r, r)
                    ty = _clamp(y + by + ry, 0, h - 1)
                    tx = _clamp(x + bx + rx, 0, w - 1)
                    if ty - y != by or tx - x != bx:
                        c = _cost(ref, tgt, y, x, ty, tx, patch, best)
                        if c < best:
                            best = c
                            by = ty - y
                            bx = tx - x
                    r //= 2
                off[i, j, 0] = by
                off[i, j, 1] = bx
                cost[i, j] = best
    return off, cost


@njit(helper=True)
def _add_cand(cand, nc, cy, cx):  # pragma: no cover - numba
    """Append (cy, cx) to the first ``nc`` rows of ``cand`` unless already there."""
    for k in range(nc):
        if cand[k, 0] == cy and cand[k, 1] == cx:
            return nc
    cand[nc, 0] = cy
    cand[nc, 1] = cx
    return nc + 1


@njit(helper=True)
def _eval_block(ref, tgt, y, xb, xl, cy, cx, lanes, cs, search):  # pragma: no cover - numba
    """Try offset (cy, cx) for the block at columns ``xb .. xl`` of row ``y`` (at most
    ``BLOCK`` apart).

    The block's pixels keep their bests in lane ``x - xb`` of ``lanes`` (SSD and offset);
    lanes of unmasked columns are updated too and never read. Inside the frame the block
    shares its rows: the squared differences of the ``patch`` rows are summed per column once
    (``BLOCK + patch - 1`` columns, scratch ``cs``), and each lane's SSD is the sum of its
    ``patch`` columns. Where the offset leaves the frame for some pixel, each lane is clamped
    and evaluated on its own, as in the scalar search.
    """
    patch = search.patch
    h = tgt.shape[0] - patch + 1
    w = tgt.shape[1] - (patch - 1) - _EXTRA
    ty = y + cy
    if ty >= 0 and ty < h and xb + cx >= 0 and xl + cx < w:
        if patch == _simd.PATCH:
            stride = ref.shape[1]
            rb = y * stride + xb
            tb = ty * stride + xb + cx
            box6x8_update(search.simd, ref, tgt, rb, tb, stride, cy, cx, lanes, cs)
        else:
            # ``lanes`` is unpacked only off the hot path: unpacking it on every call costs
            # reference counting that made the whole search 1.5x slower
            bc, boy, box = lanes
            nw = xl - xb + patch
            for c in range(nw):
                cs[c] = 0.0
            for r in range(patch):
                rr = ref[y + r]
                qr = tgt[ty + r]
                for c in range(nw):
                    d = rr[xb + c] - qr[xb + cx + c]
                    cs[c] += d * d
            for o in range(xl - xb + 1):
                s = np.float32(0.0)
                for c in range(patch):
                    s += cs[o + c]
                if s < bc[o]:
                    bc[o] = s
                    boy[o] = cy
                    box[o] = cx
    else:
        bc, boy, box = lanes
        qy = _clamp(y + cy, 0, h - 1)
        for o in range(xl - xb + 1):
            x = xb + o
            qx = _clamp(x + cx, 0, w - 1)
            s = _cost(ref, tgt, y, x, qy, qx, patch, bc[o])
            if s < bc[o]:
                bc[o] = s
                boy[o] = qy - y
                box[o] = qx - x


@njit(helper=True)
def _predicted(off, src, wt, p0, p1, cand):  # pragma: no cover - numba
    """Write into ``cand`` the offsets one target's predictions (``src``, ``wt``: its rows of
    :class:`_Plan`) give the block's two end pixels ``p0`` and ``p1 - 1``; how many.

    Motion is smooth across BLOCK columns, so the ends bracket the pixels between them, and
    propagation and the local search cover the rest (every pixel's own prediction: 1.4x the
    work for the same PSNR within 0.04 dB on disk/fan/car); ends whose sources match predict
    alike.
    """
    nc = 0
    last = max(1, p1 - p0 - 1)
    for c in range(src.shape[0]):
        s0 = src[c, 0]
        if s0 < 0:
            break
        s1 = src[c, 1]
        w0 = wt[c, 0]
        w1 = wt[c, 1]
        ay = np.int64(_NO_OFFSET)
        ax = ay
        by = ay
        bx = ay
        for k in range(p0, p1, last):
            ky = np.int64(off[s0, k, 0])
            kx = np.int64(off[s0, k, 1])
            ly = np.int64(0)
            lx = np.int64(0)
            if s1 >= 0:
                ly = np.int64(off[s1, k, 0])
                lx = np.int64(off[s1, k, 1])
            if ky == ay and kx == ax and ly == by and lx == bx:
                continue
            ay = ky
            ax = kx
            by = ly
            bx = lx
            py = w0 * ky + w1 * ly
            px = w0 * kx + w1 * lx
            cy = np.int64(np.floor(py + 0.5))
            cx = np.int64(np.floor(px + 0.5))
            nc = _add_cand(cand, nc, cy, cx)
    return nc


@njit(helper=True)
def _block_bests(cand, xs, p0, p1, boy, box):  # pragma: no cover - numba
    """Write into ``cand`` the distinct best offsets (lanes ``boy``, ``box``) of the block's
    pixels ``p0 .. p1-1``; how many."""
    xb = xs[p0]
    nb = 0
    for k in range(p0, p1):
        o = xs[k] - xb
        nb = _add_cand(cand, nb, boy[o], box[o])
    return nb


@njit(hot=True)
def _nnf_temporal_kernel(ref, targets, pixels, blocks, plan, search, off, cost):
    # pragma: no cover - numba
    """The temporal schedule by bands of blocks (see :func:`nnf_temporal`)."""
    ys, xs, index, _ = pixels
    starts, bkeys, bands = blocks
    order, src, wt, radius, scans = plan
    patch = search.patch
    seed = search.seed
    h = targets.shape[1] - patch + 1
    w = targets.shape[2] - (patch - 1) - _EXTRA
    # bands of rows are independent (propagation stays inside a band), so they run in parallel
    # with a result that does not depend on the number of threads; inside a band the targets
    # run in ``order`` because each is initialised from those before it
    for b in prange(bands.shape[0] - 1):
        q0 = bands[b]
        q1 = bands[b + 1]
        j0 = starts[q0]
        j1 = starts[q1]
        cs = np.empty(BLOCK + patch, np.float32)
        cand = np.empty((_MAX_CANDIDATES, 2), np.int64)
        # the current block's bests by lane (column - first column of the block)
        bc = np.empty(BLOCK, np.float32)
        boy = np.zeros(BLOCK, np.int32)
        box = np.zeros(BLOCK, np.int32)
        lanes = Lanes(bc, boy, box)
        for o in range(order.shape[0]):
            i = order[o]
            tgt = targets[i]
            offi = off[i]
            costi = cost[i]
            for j in range(j0, j1):  # the outputs come uninitialised (_matching)
                costi[j] = np.inf
                offi[j, 0] = 0
                offi[j, 1] = 0
            predicted = src[i, 0, 0] >= 0
            max_r = radius[i]
            for it in range(scans[i]):
                fwd = it % 2 == 0
                d = -1 if fwd else 1
                for qq in range(q0, q1):
                    q = qq if fwd else q0 + q1 - 1 - qq
                    p0 = starts[q]
                    p1 = starts[q + 1]
                    y = ys[p0]
                    xb = xs[p0]
                    xl = xs[p1 - 1]
                    for k in range(BLOCK):
                        bc[k] = np.inf
                    for k in range(p0, p1):
                        o = xs[k] - xb
                        bc[o] = costi[k]
                        boy[o] = offi[k, 0]
                        box[o] = offi[k, 1]
                    nc = 0
                    if it == 0:
                        if predicted:
                            nc = _predicted(off, src[i], wt[i], p0, p1, cand)
                        else:
                            nc = _add_cand(cand, nc, 0, 0)
                    # propagation: the offsets of the already-visited neighbours in the band
                    # (the row above/below the block, the pixel before/after it)
                    ny = y + d
                    if ny >= 0 and ny < h:
                        for k in range(p0, p1):
                            nj = index[ny, xs[k]]
                            if nj >= j0 and nj < j1:
                                nc = _add_cand(cand, nc, offi[nj, 0], offi[nj, 1])
                    nx = xs[p0] - 1 if fwd else xs[p1 - 1] + 1
                    if nx >= 0 and nx < w:
                        nj = index[y, nx]
                        if nj >= j0 and nj < j1:
                            nc = _add_cand(cand, nc, offi[nj, 0], offi[nj, 1])
                    for c in range(nc):
                        _eval_block(ref, tgt, y, xb, xl, cand[c, 0], cand[c, 1], lanes, cs, search)
                    # random search at halving radii around the block's distinct bests: in the
                    # full search around each current best (re-collected at every radius); in
                    # a predicted target's local search around the first two distinct bests
                    # before the search (the draws then do not wait on each other's results)
                    nb = _block_bests(cand, xs, p0, p1, boy, box)
                    if predicted:
                        nb = min(nb, _NEAR_SEEDS)
                    r = max_r
                    while r >= 1:
                        for u in range(nb):
                            ry, rx = _rand2(seed, i, bkeys[q] * BLOCK + u, it * _SCAN_KEY + r, r)
                            cy = cand[u, 0] + ry
                            cx = cand[u, 1] + rx
                            _eval_block(ref, tgt, y, xb, xl, cy, cx, lanes, cs, search)
                        r //= 2
                        if not predicted:
                            nb = _block_bests(cand, xs, p0, p1, boy, box)
                    for k in range(p0, p1):
                        o = xs[k] - xb
                        costi[k] = bc[o]
                        offi[k, 0] = boy[o]
                        offi[k, 1] = box[o]
    return off, cost


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


@njit(hot=True)
def _fuse_kernel(ref_raw, raw, ys, xs, js, off, cost, scale, out):  # pragma: no cover - numba
    # the pixels ``js`` (ascending) in chunks in parallel; inside a chunk target by target (one
    # frame at a time in cache), each pixel still summing the reference and then the targets
    # in order
    n_t, h, w = raw.shape
    m = js.shape[0]
    chunk = _FUSE_CHUNK
    for ch in prange((m + chunk - 1) // chunk):
        q0 = ch * chunk
        q1 = min(m, q0 + chunk)
        acc = np.empty(q1 - q0)
        wsum = np.ones(q1 - q0)
        for q in range(q0, q1):
            acc[q - q0] = ref_raw[ys[js[q]], xs[js[q]]]
        for i in range(n_t):
            for q in range(q0, q1):
                j = js[q]
                if not cost[i, j] < np.inf:
                    continue  # no match: every candidate read NaN guides (fuse_matches)
                y = ys[j]
                x = xs[j]
                wt = 1.0 if scale <= 0.0 else np.exp(-cost[i, j] / scale)
                ty = _clamp(y + off[i, j, 0], 0, h - 1)
                tx = _clamp(x + off[i, j, 1], 0, w - 1)
                acc[q - q0] += wt * raw[i, ty, tx]
                wsum[q - q0] += wt
        for q in range(q0, q1):
            out[js[q]] = acc[q - q0] / wsum[q - q0]
    return out


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
