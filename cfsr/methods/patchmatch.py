"""PatchMatch temporal fusion for the fine reconstruction (CFSR paper, fine stage).

For every pixel of the fine dynamic region, the 6 x 6 patch around it in the reference frame
(TFI at t) is matched in each target frame (TFI at t +- 5i, i = 1..10); the matched centre values
of all targets and the reference are averaged. Patches of neighbouring pixels overlap, so this is
the "overlapping patches" form of the paper's patch search.

The nearest-neighbour field (NNF) per target is found with PatchMatch (Barnes et al., 2009):
zero-motion initialisation, then alternating forward/backward scans that try the offsets of the
already-visited left/up (right/down) neighbours (propagation) and random offsets around the
current best at radii ``max_radius, max_radius/2, ..., 1`` (random search). The sum of squared
differences (SSD) over the patch stops early once it exceeds the current best. Only the masked
pixels are visited; the NNFs of the targets are independent and run in parallel.

Randomness comes from a counter-based hash of (seed, target, the pixel's full-frame position,
iteration, radius), so the result does not depend on thread scheduling (the same window always
gives the same frame, which keeps the streaming and whole-array paths identical) nor on which
other pixels are matched (a crop and the whole frame draw alike).

Matching happens on a *guide* (a lightly smoothed TFI): matching the raw TFI locks onto its
quantisation noise. The averaged values are the raw TFI rates at the matched positions.

References
----------
C. Barnes, E. Shechtman, A. Finkelstein, D. B. Goldman, "PatchMatch: a randomized
correspondence algorithm for structural image editing", ACM TOG 28(3), 2009.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["nnf_multi", "fuse_matches", "patchmatch_fuse"]

_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)


@njit(cache=True, inline="always")
def _mix(z):  # pragma: no cover - numba
    """splitmix64 finaliser: a well-spread 64-bit hash of ``z`` (uint64)."""
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


@njit(cache=True, inline="always")
def _rand2(seed, a, b, c, r):  # pragma: no cover - numba
    """Two uniform integers in [-r, r] from the counter (seed, a, b, c)."""
    z = _mix(seed + _GOLD * np.uint64(a + 1))
    z = _mix(z + _GOLD * np.uint64(b + 1))
    z = _mix(z + _GOLD * np.uint64(c + 1))
    span = np.uint64(2 * r + 1)
    dy = np.int64(z % span) - r
    dx = np.int64((z >> np.uint64(32)) % span) - r
    return dy, dx


@njit(cache=True, inline="always")
def _clamp(v, lo, hi):  # pragma: no cover - numba
    return lo if v < lo else (hi if v > hi else v)


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def _ssd6(ref, tgt, y, x, ty, tx, limit):  # pragma: no cover - numba
    """:func:`_ssd` for the default 6 x 6 patch (constant bounds: the loops unroll)."""
    s = 0.0
    for dy in range(6):
        rr = ref[y + dy]
        qr = tgt[ty + dy]
        for dx in range(6):
            d = rr[x + dx] - qr[tx + dx]
            s += d * d
        if s > limit:
            return s
    return s


@njit(cache=True, inline="always")
def _cost(ref, tgt, y, x, ty, tx, patch, limit):  # pragma: no cover - numba
    if patch == 6:
        return _ssd6(ref, tgt, y, x, ty, tx, limit)
    return _ssd(ref, tgt, y, x, ty, tx, patch, limit)


def _pad(img: np.ndarray, patch: int) -> np.ndarray:
    """Edge-replicate padding of the last two axes for :func:`_ssd` (float32, contiguous)."""
    # (patch - 1) // 2 before: the 2-before/3-after 6 x 6 patch of the paper's default, and a
    # centred window for odd sizes (patch // 2 - 1 went negative for a 1 x 1 patch)
    lo = (patch - 1) // 2
    hi = patch - 1 - lo
    width = [(0, 0)] * (img.ndim - 2) + [(lo, hi), (lo, hi)]
    return np.ascontiguousarray(np.pad(img, width, mode="edge"), dtype=np.float32)


@njit(parallel=True, cache=True)
def _nnf_kernel(ref, targets, ys, xs, keys, index, patch, iters, max_r, seed, off, cost):
    # pragma: no cover - numba
    n_t = targets.shape[0]
    h = targets.shape[1] - patch + 1
    w = targets.shape[2] - patch + 1
    m = ys.shape[0]
    for i in prange(n_t):
        tgt = targets[i]
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
                    ry, rx = _rand2(seed, i, keys[j], it * 64 + r, r)
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


def nnf_multi(
    ref: np.ndarray,
    targets: np.ndarray,
    mask: np.ndarray,
    *,
    patch: int = 6,
    iters: int = 3,
    max_radius: int = 16,
    seed: int = 0,
    origin: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest-neighbour fields from ``ref`` to each of ``targets`` on the ``mask`` pixels.

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
        PatchMatch scans (alternating direction).
    max_radius : int
        Largest random-search radius (pixels).
    seed : int
        Seed of the counter-based random search (any int; reduced modulo 2**64).
    origin : (int, int)
        Position of ``ref[0, 0]`` in the full frame: each pixel's random draws are keyed by
        its full-frame position, so a crop and the whole frame draw alike.

    Returns
    -------
    ys, xs : ndarray (M,) int64
        Coordinates of the matched pixels (row-major order).
    offsets : ndarray (N, M, 2) int32
        (dy, dx) from each pixel to its match in each target.
    cost : ndarray (N, M) float32
        SSD of each match (guide units squared, summed over the patch).
    """
    ref = np.ascontiguousarray(ref, dtype=np.float32)
    targets = np.ascontiguousarray(targets, dtype=np.float32)
    if targets.ndim != 3 or targets.shape[1:] != ref.shape:
        raise ValueError(f"targets {targets.shape} do not match reference {ref.shape}")
    if patch < 1 or iters < 0 or max_radius < 0:
        raise ValueError(f"bad PatchMatch settings patch={patch} iters={iters} r={max_radius}")
    ys, xs = np.nonzero(np.asarray(mask, dtype=bool))
    ys = ys.astype(np.int64)
    xs = xs.astype(np.int64)
    index = np.full(ref.shape, -1, np.int64)
    index[ys, xs] = np.arange(ys.size)
    # the random search of a pixel is keyed by its position in the full frame, so the same
    # pixel draws the same offsets whatever else is matched (crop or whole frame)
    keys = (ys + int(origin[0])) * np.int64(1 << 20) + (xs + int(origin[1]))
    off = np.zeros((targets.shape[0], ys.size, 2), np.int32)
    cost = np.zeros((targets.shape[0], ys.size), np.float32)
    if ys.size and targets.shape[0]:
        s = np.uint64(int(seed) % (1 << 64))
        _nnf_kernel(
            _pad(ref, patch),
            _pad(targets, patch),
            ys,
            xs,
            keys,
            index,
            patch,
            iters,
            max_radius,
            s,
            off,
            cost,
        )
    return ys, xs, off, cost


@njit(parallel=True, cache=True)
def _fuse_kernel(ref_raw, raw, ys, xs, off, cost, scale, out):  # pragma: no cover - numba
    n_t, h, w = raw.shape
    for j in prange(ys.shape[0]):
        y = ys[j]
        x = xs[j]
        acc = np.float64(ref_raw[y, x])
        wsum = 1.0
        for i in range(n_t):
            wt = 1.0 if scale <= 0.0 else np.exp(-cost[i, j] / scale)
            ty = _clamp(y + off[i, j, 0], 0, h - 1)
            tx = _clamp(x + off[i, j, 1], 0, w - 1)
            acc += wt * raw[i, ty, tx]
            wsum += wt
        out[j] = acc / wsum
    return out


def fuse_matches(
    ref_raw: np.ndarray,
    raw: np.ndarray,
    ys: np.ndarray,
    xs: np.ndarray,
    offsets: np.ndarray,
    cost: np.ndarray,
    *,
    patch: int = 6,
    h: float = 0.0,
) -> np.ndarray:
    """Average the reference value with the matched values of every target at the given pixels.

    Weights are ``exp(-SSD / (patch**2 * h**2))`` (non-local-means form); ``h <= 0`` gives the
    plain average of the paper. Returns float32 ``(M,)`` in the units of ``raw``.
    """
    out = np.empty(ys.size, np.float32)
    if ys.size == 0:
        return out
    scale = float(patch * patch * h * h) if h > 0 else 0.0
    return _fuse_kernel(
        np.ascontiguousarray(ref_raw, dtype=np.float32),
        np.ascontiguousarray(raw, dtype=np.float32),
        ys,
        xs,
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
    patch: int = 6,
    iters: int = 3,
    max_radius: int = 16,
    h: float = 0.0,
    seed: int = 0,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Refine ``ref_raw`` on ``mask`` by PatchMatch over the target frames.

    Matching uses the guides; the averaged values are the raw rates. Pixels outside ``mask``
    keep ``ref_raw``. ``origin``: see :func:`nnf_multi`. Returns float32 ``(H, W)``.
    """
    out = np.array(ref_raw, dtype=np.float32, copy=True)
    if raw.shape[0] == 0 or not np.any(mask):
        return out
    ys, xs, off, cost = nnf_multi(
        ref_guide,
        guides,
        mask,
        patch=patch,
        iters=iters,
        max_radius=max_radius,
        seed=seed,
        origin=origin,
    )
    out[ys, xs] = fuse_matches(ref_raw, raw, ys, xs, off, cost, patch=patch, h=h)
    return out
