"""Bit (un)packing kernels for spike frames in the ``.dat`` byte layout.

A packed frame stores pixel ``p`` of the *stored* raster in byte ``p // 8`` at bit ``p % 8``
(LSB first), as SpikeCV and Spike-Zoo do. The stored raster is the upright image flipped
upside down (and optionally left-right), possibly with extra "head" columns on the right.
These kernels fuse the flips and the head-column removal into the unpack so that no
intermediate full-size copy is made.
"""

from __future__ import annotations

import numpy as np

from cfsr._jit import njit

__all__ = ["pack_frames", "unpack_frames", "unpack_layout"]


@njit
def _unpack_kernel(packed, out, stored_width, flipud, fliplr):  # pragma: no cover - numba
    n, height, width = out.shape
    for t in range(n):
        frame = packed[t]
        for r in range(height):
            rr = height - 1 - r if flipud else r
            base = r * stored_width
            for c in range(width):
                p = base + c
                cc = width - 1 - c if fliplr else c
                out[t, rr, cc] = (frame[p >> 3] >> (p & 7)) & 1
    return out


def unpack_frames(
    packed: np.ndarray,
    height: int,
    width: int,
    *,
    stored_width: int | None = None,
    flipud: bool = True,
    fliplr: bool = False,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Unpack ``(n, frame_bytes)`` packed frames into upright ``(n, height, width)`` uint8 0/1.

    ``stored_width`` is the number of pixels per stored row (``width`` plus any head columns,
    which are dropped). ``flipud``/``fliplr`` undo the flips the writer applied.
    """
    stored_width = width if stored_width is None else stored_width
    packed = np.ascontiguousarray(packed, dtype=np.uint8)
    if packed.ndim == 1:
        packed = packed.reshape(1, -1)
    n = packed.shape[0]
    need = (height * stored_width + 7) // 8
    if packed.shape[1] < need:
        raise ValueError(f"packed frames have {packed.shape[1]} bytes, need {need}")
    if out is None:
        out = np.empty((n, height, width), dtype=np.uint8)
    if n:
        _unpack_kernel(packed, out, stored_width, flipud, fliplr)
    return out


def unpack_layout(packed: np.ndarray, layout) -> np.ndarray:
    """:func:`unpack_frames` with the geometry and flips of ``layout`` (a
    :class:`cfsr.layout.Layout`): upright ``(n, height, width)`` uint8 0/1."""
    return unpack_frames(
        packed,
        layout.height,
        layout.width,
        stored_width=layout.stored_width,
        flipud=layout.flipud,
        fliplr=layout.fliplr,
    )


def pack_frames(frames: np.ndarray, *, flipud: bool = True, fliplr: bool = False) -> np.ndarray:
    """Pack upright ``(n, H, W)`` 0/1 frames into ``(n, ceil(H*W/8))`` bytes, ``.dat`` layout."""
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise ValueError(f"frames must be (n, H, W), got shape {frames.shape}")
    if flipud:
        frames = frames[:, ::-1, :]
    if fliplr:
        frames = frames[:, :, ::-1]
    flat = np.ascontiguousarray(frames != 0).reshape(frames.shape[0], -1)
    return np.packbits(flat, axis=1, bitorder="little")
