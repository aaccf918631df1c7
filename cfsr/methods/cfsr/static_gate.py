"""The static gate: a window whose spike counts did not change is output as its static estimate
(TFP, or the ``isi`` rate of :func:`span_isi_rate`) at once.

CFSR's coarse stage proves a pixel static by its distinct ISIs (Eq. 5) over the union of the K
history frames' distinction windows (~650 steps at the defaults; with the margins the history
scan reads ~860), 4-5 times the steps a TFP frame reads. When a whole window is static, that
proof, MOG and DAISI only confirm what the counts already say, and CFSR's output is the TFP
(Eq. 4). The gate reads two spans of ``window`` steps ending where the TFP span ends and passes
when no pixel's count differs between them by more than ``tol`` spikes: with constant
brightness an integrate-and-fire pixel fires ``floor`` or ``ceil`` of ``rate * window`` times
in any span of ``window`` steps, so a static scene passes at ``tol = 1``, while anything that
moves changes the counts of the pixels it crosses. What a passing window can still hide is a
change of the two spans' mean rates under ``(tol + 2) / window`` spikes per step (each count is
within one spike of its span's integral; 1.9 % of full scale at the defaults), or motion that
leaves both counts equal. Sensor noise that moves counts
by more than ``tol`` makes the gate fail, which costs only the gate's time: the window then
takes the whole pipeline.

The gate counts both spans in one pass and stops at the first chunk of pixels that changed,
after probing every 8th chunk first: a moving window pays ~0.1 ms for it instead of two
whole-frame counts (5-6 ms of a CFSR frame on the demo disk scene), a passing one about what
the two counts cost.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cfsr._jit import njit
from cfsr._packed import CHUNK, LANES, count_packed, stored_view, upright
from cfsr._words import PackedWindow
from cfsr.methods.cfsr.coarse import span_estimator
from cfsr.methods.cfsr.patchmatch_frames import pm_tiles
from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.tfp import RateRule, fill_sparse_stored, isi_span_stored

__all__ = [
    "active_tiles",
    "gated_rate",
    "span_counts",
    "span_isi_rate",
    "static_gate",
    "tile_gates",
]


class _Raster(NamedTuple):
    """Where a window's image pixels lie among its stored ones, by name: what the gate reads
    of the packed geometry ``src.geo`` (int64[5], :func:`cfsr._words.geometry`). Stored pixel
    ``q`` is an image pixel when ``q // stored_width < height`` and ``q % stored_width <
    width`` (head columns at the right of every stored row); the compiled gate takes it as
    it is."""

    stored_width: int  #: stored pixels per row, head columns included
    height: int  #: image rows
    width: int  #: image columns
    flipud: bool  #: rows stored bottom-up
    fliplr: bool  #: columns stored right to left

    @classmethod
    def of(cls, src: PackedWindow) -> _Raster:
        geo = src.geo  # [stored width, height, flipud, first column, column step]
        return cls(int(geo[0]), src.h, src.w, bool(geo[2]), int(geo[4]) < 0)


def _stored(src: PackedWindow, flat: np.ndarray) -> np.ndarray:
    """:func:`cfsr._packed.stored_view` of ``src``'s geometry."""
    return stored_view(flat, _Raster.of(src).stored_width, src.h, src.w)


def _upright(src: PackedWindow, stored: np.ndarray, dtype=np.int32) -> np.ndarray:
    """A :func:`_stored` view -> the upright image (a new ``dtype`` array)."""
    r = _Raster.of(src)
    return upright(stored, r.fliplr, r.flipud).astype(dtype)


def span_counts(src: PackedWindow, a: int, b: int) -> np.ndarray:
    """Spikes per pixel in steps ``[a, b)`` of ``src``, upright int32 ``(H, W)``, counted on
    the packed bytes (:func:`cfsr._packed.count_packed`, no unpacking)."""
    return _upright(src, _stored(src, count_packed(src.packed, a, b)))


def span_isi_rate(
    src: PackedWindow,
    a: int,
    b: int,
    *,
    mark: bool = False,
    center: int | None = None,
    max_isi: int = 200,
) -> np.ndarray:
    """The ``isi`` span rate (:func:`cfsr.methods.tfp.span_rate`) over steps ``[a, b)`` of
    ``src``, upright float32 ``(H, W)`` spikes per step in [0, 1], from the packed bytes: what
    a passing gate outputs when the static estimator is ``isi``. Pixels with fewer than two
    spikes in the span get -1 when ``mark``, or, given ``center``, the TFI at ``center``
    (``max_isi`` steps each side; :func:`cfsr.methods.tfp.static_rate`'s rule)."""
    flat = isi_span_stored(src.packed, a, b, mark=mark or center is not None)
    if center is not None:
        sw = _Raster.of(src).stored_width
        fill_sparse_stored(flat, src.packed, src.h, sw, src.w, int(center), int(max_isi))
    return _upright(src, _stored(src, flat), np.float32)


@njit
def _gate_kernel(packed, a, window, lanes, raster, tol, order, recent, failed, changes):
    # pragma: no cover - numba
    """Spikes of every stored pixel in ``[a + window, a + 2 * window)`` into ``recent`` and,
    against ``[a, a + window)``, ``failed[0] = 1`` once some image pixel's two counts differ
    by more than ``tol``; after that the remaining chunks are skipped. Chunks of 64 bytes
    (512 stored pixels, one cache line of every frame, SWAR lane counts as
    :func:`cfsr._packed.count_packed`) are taken in ``order`` (:func:`_probe_order`).
    ``raster``: :class:`_Raster` (stored pixel ``p`` is an image pixel when ``p // sw <
    height`` and ``p % sw < width``).
    A non-empty ``changes`` (uint8, one per stored pixel) takes every pixel's verdict
    (``|change| > tol``) and keeps the kernel going to the last chunk."""
    nb = packed.shape[1]
    sw = raster.stored_width
    height = raster.height
    width = raster.width
    every = changes.shape[0] > 0
    for i in range(order.shape[0]):
        if failed[0] and not every:
            continue
        b0 = order[i] * CHUNK
        m = min(nb, b0 + CHUNK) - b0
        old = np.zeros(CHUNK * 8, np.int64)
        new = np.zeros(CHUNK * 8, np.int64)
        acc_o = np.empty(CHUNK, np.uint64)
        acc_n = np.empty(CHUNK, np.uint64)
        done = 0
        while done < window:  # lanes hold up to 255 spikes: spilled every 255 frames
            step = min(window - done, 255)
            acc_o[:m] = 0
            acc_n[:m] = 0
            for tt in range(a + done, a + done + step):
                row_o = packed[tt]
                row_n = packed[tt + window]
                for j in range(m):
                    acc_o[j] += lanes[row_o[b0 + j]]
                    acc_n[j] += lanes[row_n[b0 + j]]
            for j in range(m):
                vo = acc_o[j]
                vn = acc_n[j]
                for k in range(8):
                    sh = np.uint64(8 * k)
                    old[j * 8 + k] += np.int64((vo >> sh) & np.uint64(0xFF))
                    new[j * 8 + k] += np.int64((vn >> sh) & np.uint64(0xFF))
            done += step
        p0 = b0 * 8
        changed = False
        for q in range(m * 8):
            recent[p0 + q] = new[q]
            moved = abs(new[q] - old[q]) > tol
            if every:
                changes[p0 + q] = moved
            if moved:
                pix = p0 + q
                changed |= pix // sw < height and pix % sw < width
        if changed:
            failed[0] = 1


def static_gate(src: PackedWindow, end: int, window: int, tol: int) -> np.ndarray | None:
    """The counts of steps ``[end - window, end)`` (upright int32 ``(H, W)``) when no pixel's
    count there differs by more than ``tol`` spikes from its count in the ``window`` steps
    before; None when some pixel's does, when ``tol < 0`` (gate off) or when the two spans do
    not fit in ``[0, end)``.

    Parameters
    ----------
    src : PackedWindow
        The window's packed frames.
    end : int
        First step after the spans (the end of the TFP span at t), window steps.
    window : int
        Length of each span, steps.
    tol : int
        Largest count change, spikes, still called static.
    """
    if tol < 0 or window < 1 or end - 2 * window < 0 or end > src.n:
        return None
    recent, failed, _ = _gate(src, end, window, tol, every=False)
    # head columns (right of every stored row) are not pixels: only the image's counts
    return None if failed else _upright(src, _stored(src, recent))


def _gate(src: PackedWindow, end: int, window: int, tol: int, *, every: bool):
    """:func:`_gate_kernel` on ``src``: ``(recent counts, failed, changes)`` per stored pixel;
    ``every`` visits every chunk in memory order and fills ``changes`` (else chunks in
    :func:`_probe_order`, stopping at the first changed one, and ``changes`` empty)."""
    nb = src.packed.shape[1]
    nchunks = (nb + CHUNK - 1) // CHUNK
    recent = np.zeros(nb * 8, np.int64)
    failed = np.zeros(1, np.int64)
    changes = np.zeros(nb * 8 if every else 0, np.uint8)
    _gate_kernel(
        np.ascontiguousarray(src.packed, dtype=np.uint8),
        end - 2 * window,
        window,
        LANES,
        _Raster.of(src),
        int(tol),
        np.arange(nchunks, dtype=np.int64) if every else _probe_order(nchunks),
        recent,
        failed,
        changes,
    )
    return recent, bool(failed[0]), changes


def active_tiles(
    src: PackedWindow, end: int, window: int, tol: int, tile: int, margin: int = 1
) -> np.ndarray | None:
    """The static gate per tile: pixels of the ``tile`` x ``tile`` tiles (image grid from the
    top-left corner) within ``margin`` tiles of one holding a pixel whose counts over the two
    spans of :func:`static_gate` differ by more than ``tol`` spikes, bool ``(H, W)``; None when
    the two spans do not fit in ``[0, end)`` or ``tol < 0`` (every pixel is then active).

    A tile outside this mask passes the gate's test on its own and next to tiles that pass it
    too, which is what the whole-frame gate asks of every pixel before it outputs a window as
    static (module notes: what a passing count test can still hide)."""
    if tol < 0 or window < 1 or tile < 1 or end - 2 * window < 0 or end > src.n:
        return None
    _, _, changes = _gate(src, end, window, tol, every=True)
    moved = _upright(src, _stored(src, changes), np.bool_)
    h, w = moved.shape
    near = pm_tiles(moved, margin * tile, tile)  # the tiles within margin of a changed one
    # C-contiguous (one kernel specialisation for every frame width)
    return np.ascontiguousarray(np.repeat(np.repeat(near, tile, axis=0), tile, axis=1)[:h, :w])


def _probe_order(n: int, every: int = 8) -> np.ndarray:
    """``0 .. n-1`` with every ``every``-th chunk first (a probe spread over the frame that a
    mover almost always touches), then the others in memory order (what a passing gate reads
    fastest)."""
    probe = np.arange(0, n, every, dtype=np.int64)
    rest = np.setdiff1d(np.arange(n, dtype=np.int64), probe)
    return np.concatenate([probe, rest])


def gated_rate(
    src: PackedWindow, gate: np.ndarray, pa: int, pb: int, center: int, s: CfsrSettings
) -> np.ndarray:
    """The output of a window the static gate passes (``gate``: its counts over the last
    span): the static estimate over ``[pa, pb)``, spikes per step in [0, 1]. Such a window
    has no mover for the steady check to catch, so the isi rule applies as is."""
    if span_estimator(s) == RateRule.ISI:  # below two spikes: the TFI at t
        tfp = span_isi_rate(src, pa, pb, center=center, max_isi=s.max_isi)
    else:
        counts = gate if pb - pa == s.static_window else span_counts(src, pa, pb)
        tfp = counts / np.float32(max(1, pb - pa))
    return np.clip(tfp, 0.0, 1.0).astype(np.float32)


def tile_gates(
    src: PackedWindow, pb: int, s: CfsrSettings
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(active, slow_cand)``: the pixels of the tiles the static gate per tile does not
    pass (None: all), for the adaptive stages and for the slow-motion windows.

    The slow-motion windows look only where the gate per tile finds a change (its tiles are
    still: their rate is a long window's already) whatever ``adaptive`` and the gate
    settings, so that every pipeline gives a still window the same output."""
    tile, tol, adaptive = s.static_tile, s.static_tol, s.adaptive

    def tiles(tol: int, tile: int) -> np.ndarray | None:
        a = active_tiles(src, pb, s.static_window, tol, tile)
        return None if a is not None and a.all() else a

    active = tiles(tol, tile) if adaptive and tile > 0 else None
    if adaptive and tile > 0 and tol >= 0:
        return active, active
    return active, tiles(tol if tol >= 0 else 1, tile or 16)  # tol -1: the default's
