"""Per-pixel spike words: packed frames turned pixel-major, 64 steps per ``uint64``.

Packed frames (``.dat`` layout) are frame-major: one frame's pixels are adjacent bits. Every
per-pixel rule of the paper (ISIs, distinct ISIs, TFI, DAISI) walks one pixel's spike times,
so kernels must transpose. Doing it bit by bit costs a few operations per pixel and step
(900 steps of 400 x 250 pixels is 90 million of them); doing it as bit-matrix transposes
of 64 x 64 bits costs about 0.3 operations per pixel-step, and a pixel's spikes then come
out of its words with one trailing-zero count each, skipping the steps without a spike.

Word ``q`` of a pixel holds steps ``lo + 64 q .. lo + 64 q + 63``, bit ``b`` = step
``lo + 64 q + b``; steps at or past ``hi`` read as 0.

The kernels here are building blocks (``inline="always"``) for the per-pixel scans of
:mod:`cfsr.methods`; they take the stored geometry ``geo`` of :func:`geometry`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros
from numba.extending import intrinsic

from cfsr._bits import pack_frames
from cfsr._isi import needs_after, needs_before, tfi_interval
from cfsr._jit import njit
from cfsr.layout import Layout

__all__ = [
    "PackedWindow",
    "Words",
    "Stored",
    "geometry",
    "leading_zeros",
    "popcount",
    "trailing_zeros",
    "transpose64",
    "row_words",
    "word_spikes",
    "word_times",
    "prefix_counts",
    "count_range",
    "prev_spike",
    "next_spike",
    "range_times",
    "ROW_PAD",
    "WORD_STEPS",
    "n_words",
    "row_or_stored",
    "isi_in_words",
    "count_between",
]


@intrinsic
def popcount(typingctx, x):  # pragma: no cover - compiled
    """Set bits of an integer (LLVM ``ctpop``: one instruction where the CPU has it)."""
    sig = x(x)

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return sig, codegen


def geometry(layout) -> np.ndarray:
    """``geo`` of a :class:`~cfsr.layout.Layout`: where image pixel ``(y, x)`` is stored.

    Stored bit of ``(y, x)`` = ``row(y) * geo[0] + geo[3] + geo[4] * x`` with
    ``row(y) = geo[1] - 1 - y`` when ``geo[2]`` (rows bottom-up) else ``y``.
    """
    return np.array(
        [
            layout.stored_width,
            layout.height,
            int(bool(layout.flipud)),
            layout.width - 1 if layout.fliplr else 0,
            -1 if layout.fliplr else 1,
        ],
        np.int64,
    )


@intrinsic
def _load_u64(typingctx, arr, row, col):  # pragma: no cover - compiled
    """Eight bytes ``arr[row, col:col + 8]`` as one little-endian uint64 (unaligned load).

    The caller keeps ``col + 8`` inside the row's allocation.
    """
    sig = types.uint64(arr, row, col)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        inds = [
            context.cast(builder, v, t, types.intp)
            for v, t in zip(args[1:], signature.args[1:], strict=True)
        ]
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, inds)
        p64 = builder.bitcast(ptr, ir.IntType(64).as_pointer())
        return builder.load(p64, align=1)

    return sig, codegen


class PackedWindow:
    """A window as packed frames (``.dat`` layout) with the geometry ``geo`` the word scans
    need (:func:`geometry`).

    The streaming path wraps the buffered bytes as they are (no unpacking: 900 steps of
    400 x 250 unpack in ~50 ms, more than a whole scan); :meth:`from_frames` packs upright
    0/1 frames.
    """

    def __init__(self, packed: np.ndarray, height: int, width: int, geo: np.ndarray):
        self.packed = np.ascontiguousarray(packed, dtype=np.uint8)
        self.n = self.packed.shape[0]
        self.h = int(height)
        self.w = int(width)
        self.geo = geo

    @classmethod
    def from_frames(cls, window: np.ndarray) -> PackedWindow:
        """Pack upright ``(n, H, W)`` frames (any ``H * W``: the last byte is padded)."""
        n, h, w = window.shape
        return cls(pack_frames(window), h, w, np.array([w, h, 1, 0, 1], np.int64))

    @classmethod
    def from_packed(cls, packed: np.ndarray, layout: Layout) -> PackedWindow:
        return cls(packed, layout.height, layout.width, geometry(layout))


@njit(helper=True)
def transpose64(a):  # pragma: no cover - numba
    """Transpose the 64 x 64 bit matrix ``a`` (64 uint64) in place: bit ``j`` of ``a[r]``
    goes to bit ``r`` of ``a[j]`` (Warren, *Hacker's Delight*, 7-3: six rounds of block swaps).
    """
    j = 32
    m = np.uint64(0x00000000FFFFFFFF)
    while j != 0:
        # the pairs (k, k + j) of one round: blocks of 2j words, j contiguous pairs each (a
        # loop the compiler can vectorise)
        sj = np.uint64(j)
        for b in range(0, 64, 2 * j):
            for k in range(b, b + j):
                t = ((a[k] >> sj) ^ a[k + j]) & m
                a[k + j] ^= t
                a[k] ^= t << sj
        j >>= 1
        m ^= m << np.uint64(j)


#: Steps per spike word: one bit each in a uint64.
WORD_STEPS = 64


@njit(helper=True)
def n_words(lo, hi):  # pragma: no cover - numba
    """Words (:data:`WORD_STEPS` steps each) a pixel needs for steps ``[lo, hi)``."""
    return (hi - lo + WORD_STEPS - 1) // WORD_STEPS


#: Extra word rows per image row that :func:`row_words` may write beyond the row's pixels (a
#: stored row's head columns and the 64-pixel alignment of its bytes): a row's word buffer
#: is ``(pixels + ROW_PAD, words)``.
ROW_PAD = 80


@njit(helper=True)
def row_words(packed, geo, lo, hi, y, x0, x1, words):  # pragma: no cover - numba
    """Words of image pixels ``x0 .. x1-1`` of row ``y`` over steps ``[lo, hi)``.

    ``words`` must hold at least ``8 * (bytes covering the pixels) + 64`` rows of
    :func:`n_words` words. Returns ``(base, step)``: pixel ``x``'s words are
    ``words[base + step * (x - x0)]``.

    Blocks of 64 steps x 64 stored pixels (8 bytes of each frame, one unaligned load) are
    transposed in registers-sized rounds: about 0.3 operations per pixel-step.
    """
    sw, height, flipud, xo, xs = geo[0], geo[1], geo[2], geo[3], geo[4]
    yy = np.int64(y)
    row = (height - 1 - yy) if flipud else yy
    qa = row * sw + xo + xs * np.int64(x0)  # stored bit of x0
    qb = row * sw + xo + xs * np.int64(x1 - 1)  # stored bit of x1 - 1
    b0 = min(qa, qb) >> 3
    nbytes = (max(qa, qb) >> 3) - b0 + 1
    fb = packed.shape[1]
    nw = n_words(lo, hi)
    a = np.empty(64, np.uint64)
    for q in range(nw):
        t0 = lo + 64 * q
        nt = min(64, hi - t0)
        for g in range(0, nbytes, 8):
            col = b0 + g
            if col + 8 <= fb:
                for r in range(nt):
                    a[r] = _load_u64(packed, t0 + r, col)
            else:  # the frame's last bytes: no load past its end
                for r in range(nt):
                    v = np.uint64(0)
                    for i in range(fb - col):
                        v |= np.uint64(packed[t0 + r, col + i]) << np.uint64(8 * i)
                    a[r] = v
            for r in range(nt, 64):
                a[r] = 0
            transpose64(a)
            for j in range(min(64, 8 * (nbytes - g))):
                words[8 * g + j, q] = a[j]
    return qa - 8 * b0, xs


class Words(NamedTuple):
    """The packed window and the steps ``[lo, hi)`` whose spike words a scan reads (a
    kernel argument group)."""

    packed: np.ndarray  #: uint8 (n, frame bytes)
    geo: np.ndarray  #: int64 (5,): :func:`geometry`
    lo: int
    hi: int


class Stored(NamedTuple):
    """Spike words a whole-frame scan kept for a later one: pixel ``x`` of row ``y`` at
    ``store[y, bases[y, 0] + bases[y, 1] * x]`` (:func:`row_or_stored`); empty arrays make
    the later scan gather them itself."""

    store: np.ndarray  #: uint64 (H, W + ROW_PAD, words) or (0, 0, 0)
    bases: np.ndarray  #: int64 (H, 2) or (0, 2)


@njit(helper=True)
def row_or_stored(packed, geo, lo, hi, y, w, store, bases):  # pragma: no cover - numba
    """Words of image row ``y`` over ``[lo, hi)`` as ``(words, base, step)`` (see
    :func:`row_words`): ``store[y]`` when ``store`` holds one row per image row (the words a
    previous whole-frame scan left, ``bases[y]`` their placement), otherwise gathered here."""
    if store.shape[0] > y and bases.shape[0] > y:
        return store[y], bases[y, 0], bases[y, 1]
    words = np.empty((w + ROW_PAD, n_words(lo, hi)), np.uint64)
    base, step = row_words(packed, geo, lo, hi, y, 0, w, words)
    return words, base, step


@njit(helper=True)
def word_spikes(w, base, times, i):  # pragma: no cover - numba
    """Steps of the set bits of word ``w`` (bit ``b`` = step ``base + b``) into
    ``times[i:]``, ascending; returns the index after the last one written."""
    one = np.uint64(1)
    while w:
        times[i] = base + np.int64(trailing_zeros(w))
        i += 1
        w &= w - one
    return i


@njit(helper=True)
def word_times(words, k, nw, lo, times):  # pragma: no cover - numba
    """Spike steps of word row ``k`` into ``times`` (ascending); returns how many."""
    ns = 0
    for q in range(nw):
        ns = word_spikes(words[k, q], lo + 64 * q, times, ns)
    return ns


@njit(helper=True)
def _window(words, k, lo, q, a, b):  # pragma: no cover - numba
    """Word ``q`` of row ``k`` with the steps outside ``[a, b)`` cleared."""
    one = np.uint64(1)
    w = words[k, q]
    base = lo + 64 * q
    if a - base >= 64 or b <= base:
        return np.uint64(0)
    if base < a:
        w &= ~((one << np.uint64(a - base)) - one)
    if base + 64 > b:
        w &= (one << np.uint64(b - base)) - one
    return w


@njit(helper=True)
def prefix_counts(words, k, nw, prefix):  # pragma: no cover - numba
    """``prefix[q]`` = spikes of row ``k`` in its words ``0 .. q-1`` (for :func:`count_range`)."""
    c = 0
    for q in range(nw):
        prefix[q] = c
        c += np.int64(popcount(words[k, q]))
    prefix[nw] = c


@njit(helper=True)
def _before(words, k, lo, prefix, t):  # pragma: no cover - numba
    """Spikes of row ``k`` in ``[lo, t)``."""
    q = (t - lo) >> 6
    off = (t - lo) & 63
    if off == 0:
        return prefix[q]
    mask = np.uint64(0xFFFFFFFFFFFFFFFF) >> np.uint64(64 - off)
    return prefix[q] + np.int64(popcount(words[k, q] & mask))


@njit(helper=True)
def count_range(words, k, lo, prefix, a, b):  # pragma: no cover - numba
    """Spikes of row ``k`` in steps ``[a, b)`` (``lo <= a <= b <= lo + 64 * nw``), from the
    row's :func:`prefix_counts` and at most two masked popcounts."""
    if b <= a:
        return 0
    return _before(words, k, lo, prefix, b) - _before(words, k, lo, prefix, a)


@njit(helper=True)
def prev_spike(words, k, lo, t, a):  # pragma: no cover - numba
    """Last spike step of row ``k`` in ``[a, t]`` (-1: none); ``lo <= a``."""
    if t < a:
        return np.int64(-1)
    q = (t - lo) >> 6
    qa = (a - lo) >> 6
    w = words[k, q] & (np.uint64(0xFFFFFFFFFFFFFFFF) >> np.uint64(63 - ((t - lo) & 63)))
    while True:
        if w:
            s = lo + 64 * q + 63 - np.int64(leading_zeros(w))
            return s if s >= a else np.int64(-1)
        q -= 1
        if q < qa:
            return np.int64(-1)
        w = words[k, q]


@njit(helper=True)
def next_spike(words, k, lo, t, b):  # pragma: no cover - numba
    """First spike step of row ``k`` in ``[t, b)`` (-1: none); ``b`` within the words."""
    if b <= t:
        return np.int64(-1)
    q = (t - lo) >> 6
    qb = (b - 1 - lo) >> 6
    w = words[k, q] & (np.uint64(0xFFFFFFFFFFFFFFFF) << np.uint64((t - lo) & 63))
    while True:
        if w:
            s = lo + 64 * q + np.int64(trailing_zeros(w))
            return s if s < b else np.int64(-1)
        q += 1
        if q > qb:
            return np.int64(-1)
        w = words[k, q]


@njit(helper=True)
def range_times(words, k, lo, a, b, times):  # pragma: no cover - numba
    """Spike steps of row ``k`` in ``[a, b)`` into ``times`` (ascending); returns how many."""
    ns = 0
    if b <= a:
        return ns
    for q in range((a - lo) >> 6, ((b - 1 - lo) >> 6) + 1):
        ns = word_spikes(_window(words, k, lo, q, a, b), lo + 64 * q, times, ns)
    return ns


@njit(helper=True)
def isi_in_words(words, r, lo, c, a, b):  # pragma: no cover - numba
    """The TFI interval (Eq. 3, :func:`cfsr._isi.tfi_interval`) of word row ``r`` at step
    ``c``, spikes searched in ``[a, b)``, by bit scans (no spike list)."""
    p = prev_spike(words, r, lo, c, a)
    n = next_spike(words, r, lo, c + 1, b)
    pp = prev_spike(words, r, lo, p - 1, a) if needs_before(p, n) else -1
    nn = next_spike(words, r, lo, n + 1, b) if needs_after(p, n) else -1
    return tfi_interval(p, n, pp, nn, a, b)


@njit(helper=True)
def count_between(words, k, lo, a, b):  # pragma: no cover - numba
    """Spikes of row ``k`` in steps ``[a, b)``: masked popcounts of the words covering the
    span only (:func:`count_range` without a whole-row prefix, for a few short spans)."""
    c = 0
    if b <= a:
        return c
    for q in range((a - lo) >> 6, ((b - 1 - lo) >> 6) + 1):
        c += np.int64(popcount(_window(words, k, lo, q, a, b)))
    return c
