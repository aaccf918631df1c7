"""The PatchMatch stage's input frames: TFI and TFA guides at the PatchMatch steps, on tiles.

CFSR's fine reconstruction (:mod:`cfsr.methods.cfsr.pipeline`, paper Eq. 3 and the fine stage)
matches every fine-mask pixel in the TFI frames at ``t +- pm_step * i``; the matching reads
guides (TFA over ``pm_guide`` intervals, Gaussian-smoothed) and averages raw TFI rates. Both
are computed here, by one scan per pixel of the packed window (spike words,
:mod:`cfsr._words`), and only on the 8 x 8 tiles within :func:`match_reach` of a fine-mask
pixel (:func:`pm_tiles`); the other tiles hold NaN, which PatchMatch never matches.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import numpy as np
from numba import get_num_threads

from cfsr._isi import isi_from_times, search_range
from cfsr._jit import njit
from cfsr._words import (
    ROW_PAD,
    WORD_STEPS,
    PackedWindow,
    Words,
    n_words,
    popcount,
    prefix_counts,
    row_words,
    word_spikes,
)
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.tfa import grow_span

__all__ = ["TILE", "match_reach", "pm_tiles", "pm_frames", "isi_from_times"]

# spike words (:mod:`cfsr._words`): one bit per step, WORD_STEPS (64) steps per uint64 word;
# step s of the span is bit s & 63 of word s >> 6
_WORD_SHIFT = WORD_STEPS.bit_length() - 1
_WORD_MASK = WORD_STEPS - 1


@njit(helper=True)
def _rank(words, k, pre, q, mask):  # pragma: no cover - numba
    """Spikes of word row ``k`` before the step at bit ``mask`` (the bits below it set) of
    word ``q``, from the row's prefix counts ``pre``."""
    return pre[q] + np.int64(popcount(words[k, q] & mask))


class _Centers(NamedTuple):
    """The steps the frames are computed at and the rules' settings."""

    steps: np.ndarray  #: int64 (K,): ascending
    slot: np.ndarray  #: int64 (K,): frame written for each step
    max_isi: int  #: half-width of each step's search range
    guide: int  #: TFA intervals of the guide (0: no TFA frames)


class _Region(NamedTuple):
    """Where the frames are computed: crop rows, and per tile row the column runs."""

    y0: int  #: crop origin in the full frame
    x0: int
    tile: int  #: tile side (pixels)
    rows: np.ndarray  #: int64: crop rows with work
    runs_at: np.ndarray  #: int64 (tile rows + 1,): each tile row's first run in ``runs``
    runs: np.ndarray  #: int64 (R, 2): column runs ``[xa, xb)``, crop columns


@njit
def _pm_kernel(span, centers_, region, raw, tfa):
    # pragma: no cover - numba
    """TFI rates (``1 / ISI``, float32) and TFA rates at ``centers`` (ascending; written to
    frame ``slot[k]``) on the crop at ``(y0, x0)``, only on the crop rows ``rows`` and, in
    each, on the column runs ``runs[runs_at[i]:runs_at[i + 1]]`` of its tile row ``i``; the
    rest of those rows takes NaN (the other rows are the caller's)
    (``span``, ``centers_`` and ``region``: :class:`~cfsr._words.Words`, :class:`_Centers`,
    :class:`_Region`; ``m`` is ``max_isi``, ``thr`` the guide's intervals).

    Per pixel, the spike indices each center needs (last spike ``<= c``, first spikes
    ``>= c - m`` and ``>= c + m + 1``) are ranks: prefix popcounts of its spike words. Only
    the spike times a center can read are extracted (indices ``thr + 1`` below the first
    center's interval to ``thr + 1`` above the last one's). A pixel with ``thr - 1`` more
    spikes (at least 0) on each side of every center's interval, all inside every center's
    range (most pixels of a lit scene), takes both rates without branches: the ISI is the
    interval's, the TFA span :func:`grow_span`'s merge; the others follow the rules as
    written (:func:`isi_from_times`, :func:`grow_span`).
    """
    packed, geo, lo, hi = span
    centers, slot, m, thr = centers_
    y0, x0, tile, rows, runs_at, runs = region
    n = packed.shape[0]
    kc = centers.shape[0]
    cw = raw.shape[2]
    nw = n_words(lo, hi)
    side = max(thr - 1, 0)  # spikes a fast pixel needs beyond each center's interval
    one = np.uint64(1)
    qs, ms = _center_ranks(centers, m, n, lo)
    q_ip = qs[:, 0].copy()
    m_ip = ms[:, 0].copy()
    uthr = np.uint64(max(thr, 0))
    rec, rec_t = _rate_tables(hi - lo, thr)
    for ir in range(rows.shape[0]):
        yy = rows[ir]
        words = np.empty((cw + ROW_PAD, nw + 1), np.uint64)
        words[:, nw] = 0  # the step hi may fall on word nw
        tv = np.empty(hi - lo + 1, np.int64)
        pre = np.empty(nw + 2, np.int64)
        b_raw = np.empty((kc, cw), np.float32)  # the row's rates, center-major
        ips = np.empty(kc, np.uint64)
        b_tfa = np.empty((kc, cw), np.float32)
        tr = yy // tile
        for ri in range(runs_at[tr], runs_at[tr + 1]):
            xa = runs[ri, 0]
            xb = runs[ri, 1]
            base, step = row_words(packed, geo, lo, hi, y0 + yy, x0 + xa, x0 + xb, words)
            for x in range(xa, xb):
                k = base + step * (x - xa)
                prefix_counts(words, k, nw + 1, pre)
                ns = pre[nw + 1]
                ip_a = _rank(words, k, pre, qs[0, 0], ms[0, 0]) - 1
                ip_b = _rank(words, k, pre, qs[kc - 1, 0], ms[kc - 1, 0]) - 1
                # spikes read: indices ip - thr - 1 .. ip + thr + 2 of the first and last
                # centers' ip; extract the words holding them
                r0 = max(0, ip_a - thr - 1)
                r1 = min(ns, ip_b + thr + 3)
                q = 0
                while q < nw and pre[q + 1] <= r0:
                    q += 1
                i = pre[q]
                while i < r1:
                    i = word_spikes(words[k, q], lo + WORD_STEPS * q, tv, i)
                    q += 1
                f0_b = _rank(words, k, pre, qs[kc - 1, 1], ms[kc - 1, 1])
                f1_a = _rank(words, k, pre, qs[0, 2], ms[0, 2])
                if ip_a - side >= f0_b and ip_b + 1 + side < f1_a:
                    # every center's interval and TFA span lie inside its range: ISI and
                    # grow_span's merge without branches, rates from the tables (unsigned
                    # indices: no negative-index wrap)
                    for kk in range(kc):
                        ip = np.uint64(_rank(words, k, pre, q_ip[kk], m_ip[kk]) - 1)
                        ips[kk] = ip
                        b_raw[kk, x] = rec[tv[ip + one] - tv[ip]]
                    if thr > 0:
                        for kk in range(kc):
                            cc = centers[kk]
                            ip = ips[kk]
                            g = np.uint64(0)
                            for j in range(1, thr):
                                uj = np.uint64(j)
                                g += np.uint64(cc - tv[ip - uj] <= tv[ip + one + uthr - uj] - cc)
                            b_tfa[kk, x] = rec_t[tv[ip + uthr - g] - tv[ip - g]]
                    continue
                for kk in range(kc):
                    cc = centers[kk]
                    ip = _rank(words, k, pre, qs[kk, 0], ms[kk, 0]) - 1  # last spike <= cc
                    f0 = _rank(words, k, pre, qs[kk, 1], ms[kk, 1])  # first spike >= c_lo
                    f1 = _rank(words, k, pre, qs[kk, 2], ms[kk, 2])  # first spike >= c_hi
                    c_lo, c_hi = search_range(cc, m, n)
                    b_raw[kk, x] = np.float32(1.0 / isi_from_times(tv, ns, ip, c_lo, c_hi))
                    if thr <= 0:
                        continue
                    # TFA over thr intervals (the rule of tfa._adaptive_kernel, no refractory)
                    if f1 - f0 < 2:
                        b_tfa[kk, x] = 1.0 / (c_hi - c_lo + 1)
                        continue
                    a, b = grow_span(tv, f0, f1, ip, cc, thr)
                    b_tfa[kk, x] = (b - a) / (tv[b] - tv[a])
            _store_run(raw, tfa, slot, yy, xa, xb, b_raw, b_tfa, thr > 0)
        _fill_outside_runs(raw, tfa, yy, runs[runs_at[tr] : runs_at[tr + 1]], thr > 0)


@njit
def _center_ranks(centers, m, n, lo):  # pragma: no cover - numba
    """Per center ``c`` of ``centers``: the word index ``qs`` and the bit mask ``ms`` below
    the steps ``c + 1``, ``c_lo`` and ``c_hi`` of its search range (``max_isi`` = ``m`` in
    a window of ``n`` steps whose words start at step ``lo``): a rank there is the count of
    spikes before that step."""
    kc = centers.shape[0]
    qs = np.empty((kc, 3), np.int64)
    ms = np.empty((kc, 3), np.uint64)
    one = np.uint64(1)
    for kk in range(kc):
        cc = centers[kk]
        c_lo, c_hi = search_range(cc, m, n)
        for j, t in enumerate((cc + 1, c_lo, c_hi)):
            qs[kk, j] = (t - lo) >> _WORD_SHIFT
            ms[kk, j] = (one << np.uint64((t - lo) & _WORD_MASK)) - one
    return qs, ms


@njit
def _rate_tables(span, thr):  # pragma: no cover - numba
    """Rates (spikes per step) of one interval, and of ``thr`` intervals, ``d`` steps long
    for ``d`` in ``0..span`` (0 at ``d = 0``): the float32 of the float64 division, as the
    per-pixel rules write them, so the table path gives the same numbers."""
    rec = np.empty(span + 1, np.float32)
    rec_t = np.empty(span + 1, np.float32)
    rec[0] = rec_t[0] = 0.0
    for d in range(1, span + 1):
        rec[d] = np.float32(1.0 / d)
        rec_t[d] = thr / d
    return rec, rec_t


@njit
def _store_run(raw, tfa, slot, yy, xa, xb, b_raw, b_tfa, with_tfa):  # pragma: no cover - numba
    """The run ``[xa, xb)`` of row ``yy`` into the frames: one contiguous copy per center
    (center ``kk``'s rates from row ``kk`` of ``b_raw``/``b_tfa`` into frame ``slot[kk]``)."""
    for kk in range(slot.shape[0]):
        raw[slot[kk], yy, xa:xb] = b_raw[kk, xa:xb]
        if with_tfa:
            tfa[slot[kk], yy, xa:xb] = b_tfa[kk, xa:xb]


@njit
def _fill_outside_runs(raw, tfa, yy, runs, with_tfa):  # pragma: no cover - numba
    """NaN in every frame's row ``yy`` outside the column ``runs`` (ascending ``[xa, xb)``
    pairs of that row): the frames are not pre-filled, so each value is written once."""
    fill = np.float32(np.nan)
    cw = raw.shape[2]
    gap = 0
    for ri in range(runs.shape[0] + 1):
        end = runs[ri, 0] if ri < runs.shape[0] else cw
        if end > gap:
            for kk in range(raw.shape[0]):
                raw[kk, yy, gap:end] = fill
                if with_tfa:
                    tfa[kk, yy, gap:end] = fill
        if ri < runs.shape[0]:
            gap = runs[ri, 1]


#: Side (pixels) of the tiles the fine stage skips or works on. 8 rather than 16: the tiles
#: within :func:`match_reach` of the fine mask then cover 0.65-0.76x the pixels on disk, fan
#: and car (docs/methods.md, "Guides where matches can land").
TILE = 8


def match_reach(patch: int, sigma: float) -> int:
    """Pixels around a pixel whose TFA its own patch reads in the guides: the patch's far
    side (rows and columns ``-(patch - 1) // 2 .. patch // 2``, as
    :mod:`cfsr.methods.cfsr.patchmatch` lays it out) plus the radius of the guide's Gaussian
    (OpenCV's kernel for float images reaches ``round(4 sigma)`` pixels; ``ceil`` here)."""
    blur = int(np.ceil(4.0 * sigma)) if sigma > 0 else 0
    return patch - 1 - (patch - 1) // 2 + blur


def pm_tiles(fine: np.ndarray, margin: int, tile: int = TILE) -> np.ndarray:
    """Tiles (bool ``(ceil(H/tile), ceil(W/tile))``) within ``margin`` pixels (rounded up to
    whole tiles) of a tile holding a fine-mask pixel.

    The fine stage computes frames and guides on these tiles only (margin
    :func:`match_reach`: every fine pixel's own patch reads computed guides).
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
    s: CfsrSettings,
    tiles: np.ndarray | None = None,
    guide_out: np.ndarray | None = None,
    bank: dict[str, Any] | None = None,
    shift: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Raw TFI rates and matching guides at ``centers`` on ``box = (y0, y1, x0, x1)``.

    Guides: TFA over ``pm_guide`` intervals (or the TFI), Gaussian-smoothed. TFA adapts its
    integration to the pixel's own firing, so the guide is equally clean in bright and dark
    scenes (a fixed-window TFP guide is mostly 0 or 1/w in low light). The same numbers as
    ``tfi_rates`` and ``adaptive_rates`` on the crop. ``tiles`` (full-frame grid of
    :data:`TILE`-pixel tiles, see :func:`pm_tiles`): only the tiles marked are computed, the
    rest of the box holds NaN in the rates and in the guides (the blur spreads it up to its
    radius into the tiles): a patch that reads a NaN has a NaN SSD, which no comparison of
    :mod:`cfsr.methods.cfsr.patchmatch` prefers, so every match, and every rate the fusion
    averages, lies in computed guides. ``guide_out`` (float32
    ``(len(centers), y1 - y0, x1 - x0)``, may be a strided view such as the images of
    :func:`cfsr.methods.cfsr.patchmatch.padded_guides`): the guides are written there and it is
    returned as the guides.

    ``bank`` (a dict kept from one call to the next: CFSR's dense output, whose outputs put
    their frames on one grid of steps): the frames of the previous call at the same absolute
    steps (``shift`` + window index) are taken from it when that call computed every tile
    this one computes (the same numbers: a pixel's TFI and TFA depend on its own spikes
    only), only the others are computed, and the bank is left holding this call's frames
    (before the blur, which runs on every frame as without a bank).
    """
    y0, y1, x0, x1 = box
    if tiles is None:
        tiles = np.ones((-(-src.h // TILE), -(-src.w // TILE)), bool)
    cs = np.asarray(centers, np.int64)
    thr = s.pm_guide
    raw = np.empty((cs.size, y1 - y0, x1 - x0), np.float32)
    tfa = np.empty(raw.shape if thr > 0 else (1, 1, 1), np.float32)
    todo = np.arange(cs.size)
    if bank and "raw" in bank:
        taken, missing = _from_bank(
            bank, cs + shift, box, tiles, raw, tfa, thr > 0, (src.h, src.w),
            (shift, shift + src.n, s.max_isi),
        )
        todo = np.flatnonzero(~taken)
        if taken.any() and missing.any():  # the taken frames' tiles the bank lacks
            _merge(src, cs, np.flatnonzero(taken), box, s, missing, raw, tfa)
    if todo.size == cs.size:
        _computed(src, cs, box, s, tiles, raw, tfa)
    elif todo.size:
        r = np.empty((todo.size,) + raw.shape[1:], np.float32)
        f = np.empty(r.shape if thr > 0 else (1, 1, 1), np.float32)
        _computed(src, cs[todo], box, s, tiles, r, f)
        raw[todo] = r
        if thr > 0:
            tfa[todo] = f
    if bank is not None:
        bank.update(box=tuple(int(v) for v in box), tiles=tiles.copy(), times=cs + shift,
                    raw=raw, tfa=tfa if thr > 0 else None, window=(shift, shift + src.n))
    g = raw if thr <= 0 else tfa
    if s.pm_sigma <= 0:
        if guide_out is not None:
            np.copyto(guide_out, g)
            return raw, guide_out
        return raw, g.copy() if thr <= 0 or bank is not None else g
    import cv2

    out = np.empty_like(g) if guide_out is None else guide_out
    sigma = s.pm_sigma

    def blur(ks: range) -> None:
        for k in ks:
            cv2.GaussianBlur(g[k], (0, 0), sigma, dst=out[k])

    # OpenCV blurs an image this small on one core: the frames are split over threads instead
    # (it releases the GIL; as many as numba's, so NUMBA_NUM_THREADS limits both), same numbers
    parts = max(1, min(get_num_threads(), g.shape[0]))
    jobs = [_blur_pool().submit(blur, range(i, g.shape[0], parts)) for i in range(1, parts)]
    blur(range(0, g.shape[0], parts))
    for j in jobs:
        j.result()
    return raw, out


def _computed_mask(
    box: tuple[int, int, int, int], tiles: np.ndarray
) -> np.ndarray:
    """The crop pixels :func:`pm_frames` computes (the others hold NaN): the columns of the
    marked tiles of each tile row, rows aligned on the crop's first row."""
    y0, y1, x0, x1 = box
    sub = _tile_rows(box, tiles)
    cols = np.repeat(sub, TILE, axis=1)[:, x0:x1]
    return np.repeat(cols, TILE, axis=0)[: y1 - y0]


def _tile_rows(box: tuple[int, int, int, int], tiles: np.ndarray) -> np.ndarray:
    """The tiles of each tile row of the box, aligned on the crop's first row."""
    y0, y1 = box[0], box[1]
    sub = np.zeros((-(-(y1 - y0) // TILE), tiles.shape[1]), bool)
    for i in range(sub.shape[0]):
        ya, yb = y0 + i * TILE, min(y1, y0 + (i + 1) * TILE)
        sub[i] = tiles[ya // TILE : (yb - 1) // TILE + 1].any(axis=0)
    return sub


def _from_bank(
    bank: dict[str, Any],
    times: np.ndarray,
    box: tuple[int, int, int, int],
    tiles: np.ndarray,
    raw: np.ndarray,
    tfa: np.ndarray,
    guided: bool,
    size: tuple[int, int],
    window: tuple[int, int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Fill ``raw`` (and ``tfa`` when ``guided``) with the bank's frames at ``times``
    (absolute steps) where it computed them, NaN elsewhere: ``(taken, missing)``, which
    frames it filled and the tiles of ``tiles`` the bank lacks (their pixels still to
    compute in the taken frames). ``window``: this call's window ``(lo, hi)`` (absolute
    steps) and ``max_isi``: a frame is taken only where both windows clip its search range
    alike (Eq. 3's spikes within ``max_isi`` steps, inside the window)."""
    by0, by1, bx0, bx1 = bank["box"]
    y0, y1, x0, x1 = box
    h, w = size
    # the bank's tiles that lie whole inside its box (tiles end at the frame's edge)
    ends_y = np.minimum(h, (np.arange(tiles.shape[0]) + 1) * TILE)
    ends_x = np.minimum(w, (np.arange(tiles.shape[1]) + 1) * TILE)
    in_y = (np.arange(tiles.shape[0]) * TILE >= by0) & (ends_y <= by1)
    in_x = (np.arange(tiles.shape[1]) * TILE >= bx0) & (ends_x <= bx1)
    cov = bank["tiles"] & in_y[:, None] & in_x[None, :]
    missing = tiles & ~cov
    taken = np.zeros(times.size, bool)
    at = {int(t): k for k, t in enumerate(bank["times"].tolist())}
    if not (tiles & cov).any():
        return taken, missing
    keep = _computed_mask(box, tiles & cov)
    # the crop rows and columns both boxes hold
    a, b, c, d = max(y0, by0), min(y1, by1), max(x0, bx0), min(x1, bx1)
    here = (slice(a - y0, b - y0), slice(c - x0, d - x0))
    there = (slice(a - by0, b - by0), slice(c - bx0, d - bx0))
    nan = np.float32(np.nan)
    lo, hi, m = window
    b_lo, b_hi = bank["window"]
    for i, t in enumerate(times.tolist()):
        k = at.get(int(t))
        if k is None or max(lo, t - m) != max(b_lo, t - m) or min(hi, t + m + 1) != min(
            b_hi, t + m + 1
        ):
            continue
        pairs = ((raw, bank["raw"]), (tfa, bank["tfa"])) if guided else ((raw, bank["raw"]),)
        for out, src in pairs:
            out[i] = nan
            out[i][here] = np.where(keep[here], src[k][there], nan)
        taken[i] = True
    return taken, missing


def _merge(
    src: PackedWindow,
    cs: np.ndarray,
    which: np.ndarray,
    box: tuple[int, int, int, int],
    s: CfsrSettings,
    missing: np.ndarray,
    raw: np.ndarray,
    tfa: np.ndarray,
) -> None:
    """Compute frames ``which`` on the ``missing`` tiles and write them there."""
    r = np.empty((which.size,) + raw.shape[1:], np.float32)
    f = np.empty(r.shape if tfa.shape[0] == raw.shape[0] else (1, 1, 1), np.float32)
    _computed(src, cs[which], box, s, missing, r, f)
    put = _computed_mask(box, missing)
    for j, i in enumerate(which.tolist()):
        raw[i][put] = r[j][put]
        if f.shape[0] == r.shape[0]:
            tfa[i][put] = f[j][put]


def _computed(
    src: PackedWindow,
    cs: np.ndarray,
    box: tuple[int, int, int, int],
    s: CfsrSettings,
    tiles: np.ndarray,
    raw: np.ndarray,
    tfa: np.ndarray,
) -> None:
    """Raw TFI rates (and TFA, ``pm_guide > 0``) at window indices ``cs`` on the box's tiles
    into ``raw`` and ``tfa``; NaN on the crop rows without work and outside the runs."""
    n = src.n
    y0, y1, x0, x1 = box
    sub = _tile_rows(box, tiles)
    runs_at, runs = _runs(sub, TILE, x0, x1)
    order = np.argsort(cs, kind="stable")
    m = s.max_isi
    lo, hi = max(0, int(cs.min()) - m), min(n, int(cs.max()) + m + 1)
    thr = s.pm_guide
    # the crop rows with work
    rows = np.flatnonzero(np.diff(runs_at)[np.arange(y1 - y0) // TILE] > 0).astype(np.int64)
    _pm_kernel(
        Words(src.packed, src.geo, lo, hi),
        _Centers(cs[order], order, m, thr),
        _Region(y0, x0, TILE, rows, runs_at, runs),
        raw,
        tfa,
    )
    idle = np.ones(y1 - y0, bool)
    idle[rows] = False
    raw[:, idle] = np.nan
    if thr > 0:
        tfa[:, idle] = np.nan


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _blur_pool() -> ThreadPoolExecutor:
    """Helper threads for the guides' Gaussian blur (created on first use)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(
                max_workers=max(1, (os.cpu_count() or 1) - 1), thread_name_prefix="cfsr-blur"
            )
        return _POOL


def _forget_pool() -> None:
    # a forked child inherits the pool object but not its threads: jobs would never run
    global _POOL, _POOL_LOCK
    _POOL = None
    _POOL_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)
