"""PatchMatch's compiled kernels (numba, cached): the private sibling of
:mod:`cfsr.methods.cfsr.patchmatch`, which plans the search, lays out the buffers and calls
them. The search, the schedule and the draws are described there.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cfsr import _simd
from cfsr._borrow import borrow, keep
from cfsr._jit import njit
from cfsr._simd import LANES, READ_COLS, Lanes, box6x8_update
from cfsr._splitmix import GOLDEN, mix64

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


@njit(hot=True)
def _nnf_independent_kernel(ref, targets, pixels, plan, search, off, cost):
    # pragma: no cover - numba
    """Independent full searches, one target after the other (see :func:`nnf_independent`)."""
    ys, xs, index, keys = borrow(pixels)
    scans, radius = borrow((plan.scans, plan.radius))
    ref, targets, offb, costb = borrow((ref, targets, off, cost))
    patch = search.patch
    seed = search.seed
    n_t = targets.shape[0]
    h = targets.shape[1] - patch + 1
    w = targets.shape[2] - patch + 1
    m = ys.shape[0]
    for i in range(n_t):
        tgt = targets[i]
        iters = scans[i]
        max_r = radius[i]
        for j in range(m):
            offb[i, j, 0] = 0
            offb[i, j, 1] = 0
            costb[i, j] = _cost(ref, tgt, ys[j], xs[j], ys[j], xs[j], patch, np.inf)
        for it in range(iters):
            fwd = it % 2 == 0
            d = -1 if fwd else 1
            for jj in range(m):
                j = jj if fwd else m - 1 - jj
                y = ys[j]
                x = xs[j]
                by = offb[i, j, 0]
                bx = offb[i, j, 1]
                best = costb[i, j]
                # propagation from the already-visited horizontal and vertical neighbours
                for k in range(2):
                    ny = y + d if k == 1 else y
                    nx = x + d if k == 0 else x
                    if ny < 0 or ny >= h or nx < 0 or nx >= w:
                        continue
                    nj = index[ny, nx]
                    if nj < 0:
                        continue
                    cy = offb[i, nj, 0]
                    cx = offb[i, nj, 1]
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
                offb[i, j, 0] = by
                offb[i, j, 1] = bx
                costb[i, j] = best
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
    ys, xs, index, _ = borrow(pixels)
    starts, bkeys, bands = borrow(blocks)
    order, src, wt, radius, scans = borrow(plan)
    ref, targets, offb, costb = borrow((ref, targets, off, cost))
    patch = search.patch
    seed = search.seed
    h = targets.shape[1] - patch + 1
    w = targets.shape[2] - (patch - 1) - _EXTRA
    # bands of rows are independent (propagation stays inside a band), so the result does not
    # depend on the order they run in, or on a crop; inside a band the targets run in
    # ``order`` because each is initialised from those before it
    for b in range(bands.shape[0] - 1):
        q0 = bands[b]
        q1 = bands[b + 1]
        j0 = starts[q0]
        j1 = starts[q1]
        cs_own = np.empty(BLOCK + patch, np.float32)
        cand_own = np.empty((_MAX_CANDIDATES, 2), np.int64)
        # the current block's bests by lane (column - first column of the block)
        lanes_own = Lanes(np.empty(BLOCK, np.float32), np.zeros(BLOCK, np.int32),
                          np.zeros(BLOCK, np.int32))
        cs, cand, lanes = borrow((cs_own, cand_own, lanes_own))
        bc, boy, box = lanes
        for o in range(order.shape[0]):
            i = order[o]
            tgt = targets[i]
            offi = offb[i]
            costi = costb[i]
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
                            nc = _predicted(offb, src[i], wt[i], p0, p1, cand)
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
        keep((cs_own, cand_own, lanes_own))
    return off, cost


@njit(hot=True)
def _fuse_kernel(ref_raw, raw, ys, xs, js, off, cost, scale, out):  # pragma: no cover - numba
    # the pixels ``js`` (ascending) in chunks; inside a chunk target by target (one frame at a
    # time in cache), each pixel still summing the reference and then the targets in order
    n_t, h, w = raw.shape
    ref_raw, raw, ys, xs, js, off, cost, outb = borrow((ref_raw, raw, ys, xs, js, off, cost, out))
    m = js.shape[0]
    chunk = _FUSE_CHUNK
    for ch in range((m + chunk - 1) // chunk):
        q0 = ch * chunk
        q1 = min(m, q0 + chunk)
        acc_own = np.empty(q1 - q0)
        wsum_own = np.ones(q1 - q0)
        acc, wsum = borrow((acc_own, wsum_own))
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
            outb[js[q]] = acc[q - q0] / wsum[q - q0]
        keep((acc_own, wsum_own))
    return out
