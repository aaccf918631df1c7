"""The PatchMatch stage's input frames: TFI and TFA guides at the PatchMatch steps, on tiles.

CFSR's fine reconstruction (:mod:`cfsr.methods.cfsr_fine`, paper Eq. 3 and the fine stage)
matches every fine-mask pixel in the TFI frames at ``t +- pm_step * i``; the matching reads
guides (TFA over ``pm_guide`` intervals, Gaussian-smoothed) and averages raw TFI rates. Both
are computed here, by one scan per pixel of the packed window (spike words,
:mod:`cfsr._words`), and only on the 16 x 16 tiles within the search margin of a fine-mask
pixel (:func:`pm_tiles`): tiles PatchMatch cannot read are skipped.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numba import njit, prange

from cfsr._words import PackedWindow, row_words, word_times
from cfsr.methods.tfa import grow_span

__all__ = ["TILE", "pm_tiles", "pm_frames", "isi_from_times"]


@njit(cache=True, inline="always")
def isi_from_times(tv, ns, ip, a, b):  # pragma: no cover - numba
    """TFI interval at a step c with search range ``[a, b)`` (the rule of ``tfi._isi_one``);
    ``ip`` indexes the last spike ``<= c`` (-1: none)."""
    i_n = ip + 1
    p_ok = ip >= 0 and tv[ip] >= a
    n_ok = i_n < ns and tv[i_n] < b
    if p_ok and n_ok:
        return tv[i_n] - tv[ip]
    if p_ok:
        bound = b - tv[ip]
        if ip >= 1 and tv[ip - 1] >= a:
            return max(bound, tv[ip] - tv[ip - 1])
        return bound
    if n_ok:
        bound = tv[i_n] - a + 1
        if i_n + 1 < ns and tv[i_n + 1] < b:
            return max(bound, tv[i_n + 1] - tv[i_n])
        return bound
    return b - a + 1


@njit(parallel=True, cache=True)
def _pm_kernel(packed, geo, lo, hi, y0, x0, centers, slot, m, thr, tile, runs_at, runs, raw, tfa):
    # pragma: no cover - numba
    """TFI rates (``1 / ISI``, float32) and TFA rates at ``centers`` (ascending; written to
    frame ``slot[k]``) on the crop at ``(y0, x0)``, only on the column runs
    ``runs[runs_at[i]:runs_at[i + 1]]`` of tile row ``i``."""
    n = packed.shape[0]
    kc = centers.shape[0]
    ch, cw = raw.shape[1:]
    nw = (hi - lo + 63) >> 6
    for yy in prange(ch):
        words = np.empty((cw + 80, nw), np.uint64)
        tv = np.empty(hi - lo + 1, np.int64)
        tr = yy // tile
        for ri in range(runs_at[tr], runs_at[tr + 1]):
            xa = runs[ri, 0]
            xb = runs[ri, 1]
            base, step = row_words(packed, geo, lo, hi, y0 + yy, x0 + xa, x0 + xb, words)
            for x in range(xa, xb):
                ns = word_times(words, base + step * (x - xa), nw, lo, tv)
                ip = -1  # last spike <= cc
                f0 = 0  # first spike >= c_lo
                f1 = 0  # first spike >= c_hi
                for kk in range(kc):
                    cc = centers[kk]
                    c_lo = max(0, cc - m)
                    c_hi = min(n, cc + m + 1)
                    while ip + 1 < ns and tv[ip + 1] <= cc:
                        ip += 1
                    sk = slot[kk]
                    raw[sk, yy, x] = np.float32(1.0 / isi_from_times(tv, ns, ip, c_lo, c_hi))
                    if thr <= 0:
                        continue
                    # TFA over thr intervals (the rule of tfa._adaptive_kernel, no refractory)
                    while f0 < ns and tv[f0] < c_lo:
                        f0 += 1
                    while f1 < ns and tv[f1] < c_hi:
                        f1 += 1
                    if f1 - f0 < 2:
                        tfa[sk, yy, x] = 1.0 / (c_hi - c_lo + 1)
                        continue
                    a, b = grow_span(tv, f0, f1, ip, cc, thr)
                    tfa[sk, yy, x] = (b - a) / (tv[b] - tv[a])


#: Side (pixels) of the tiles the fine stage skips or works on.
TILE = 16


def pm_tiles(fine: np.ndarray, margin: int, tile: int = TILE) -> np.ndarray:
    """Tiles (bool ``(ceil(H/tile), ceil(W/tile))``) that PatchMatch can read: those within
    ``margin`` pixels (rounded up to whole tiles) of a tile holding a fine-mask pixel.

    Every other tile is skipped by the fine stage: no TFI frames, no guides, no matching.
    """
    h, w = fine.shape
    th, tw = -(-h // tile), -(-w // tile)
    padded = np.zeros((th * tile, tw * tile), bool)
    padded[:h, :w] = fine
    occupied = padded.reshape(th, tile, tw, tile).any(axis=(1, 3))
    r = -(-int(margin) // tile)
    if r > 0 and occupied.any():
        import cv2

        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        occupied = cv2.dilate(occupied.astype(np.uint8), k) > 0
    return occupied


def _runs(tiles: np.ndarray, tile: int, x0: int, x1: int) -> tuple[np.ndarray, np.ndarray]:
    """Column runs ``[xa, xb)`` (relative to ``x0``) of needed tiles, per tile row."""
    at = [0]
    runs: list[tuple[int, int]] = []
    for row in tiles:
        c = 0
        while c < row.size:
            if row[c]:
                d = c
                while d < row.size and row[d]:
                    d += 1
                xa, xb = max(x0, c * tile), min(x1, d * tile)
                if xb > xa:
                    runs.append((xa - x0, xb - x0))
                c = d
            else:
                c += 1
        at.append(len(runs))
    return np.array(at, np.int64), np.array(runs, np.int64).reshape(-1, 2)


def pm_frames(
    src: PackedWindow,
    centers,
    box: tuple[int, int, int, int],
    p: Mapping[str, Any],
    tiles: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Raw TFI rates and matching guides at ``centers`` on ``box = (y0, y1, x0, x1)``.

    Guides: TFA over ``pm_guide`` intervals (or the TFI), Gaussian-smoothed. TFA adapts its
    integration to the pixel's own firing, so the guide is equally clean in bright and dark
    scenes (a fixed-window TFP guide is mostly 0 or 1/w in low light). The same numbers as
    ``tfi_rates`` and ``adaptive_rates`` on the crop. ``tiles`` (full-frame grid of
    :data:`TILE`-pixel tiles, see :func:`pm_tiles`): only the tiles marked are computed, the
    rest of the box holds rate 1 (never read by PatchMatch).
    """
    n = src.n
    y0, y1, x0, x1 = box
    if tiles is None:
        tiles = np.ones((-(-src.h // TILE), -(-src.w // TILE)), bool)
    # tile rows of the box, aligned on the crop's first row
    sub = np.zeros((-(-(y1 - y0) // TILE), tiles.shape[1]), bool)
    for i in range(sub.shape[0]):
        ya, yb = y0 + i * TILE, min(y1, y0 + (i + 1) * TILE)
        sub[i] = tiles[ya // TILE : (yb - 1) // TILE + 1].any(axis=0)
    runs_at, runs = _runs(sub, TILE, x0, x1)
    cs = np.asarray(centers, np.int64)
    order = np.argsort(cs, kind="stable")
    m = int(p["max_isi"])
    lo, hi = max(0, int(cs.min()) - m), min(n, int(cs.max()) + m + 1)
    thr = int(p["pm_guide"])
    raw = np.ones((cs.size, y1 - y0, x1 - x0), np.float32)
    tfa = np.ones(raw.shape if thr > 0 else (1, 1, 1), np.float32)
    _pm_kernel(
        src.packed,
        src.geo,
        lo,
        hi,
        y0,
        x0,
        cs[order],
        order,
        m,
        thr,
        TILE,
        runs_at,
        runs,
        raw,
        tfa,
    )
    g = raw.copy() if thr <= 0 else tfa
    if p["pm_sigma"] > 0:
        import cv2

        for k in range(g.shape[0]):
            g[k] = cv2.GaussianBlur(g[k], (0, 0), float(p["pm_sigma"]))
    return raw, g
