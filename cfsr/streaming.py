"""The streaming reconstructor: blocks of packed frames in, reconstructed frames out.

One implementation serves the offline CLI (fed from a file) and the live worker (fed from the
ring buffer). It keeps the most recent packed frames in a mirrored ring (every frame is
written twice, ``capacity`` apart, so any window is one contiguous slice) and unpacks only the
window a requested output needs.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from cfsr._bits import unpack_layout
from cfsr.config import MethodConfig
from cfsr.defects import DefectCorrector
from cfsr.layout import Layout
from cfsr.methods.registry import Method, Output

__all__ = ["StreamingReconstructor"]


class StreamingReconstructor:
    """Reconstruct frames from a stream of packed spike blocks.

    Parameters
    ----------
    method : str or MethodConfig
        Registered method name (see :func:`cfsr.methods`), or a validated
        :class:`~cfsr.config.MethodConfig` (then ``params`` and ``preset`` stay unset).
    layout : Layout
        Geometry/orientation of the packed frames pushed in.
    params : mapping, optional
        Method parameters (validated; unknown names are an error).
    preset : str, optional
        Named preset applied before ``params``.
    slack : int
        Extra frames kept beyond the method's window, so a pushed block never evicts a frame
        still needed (steps).
    defects : DefectCorrector, optional
        Hot/dead pixel correction (:class:`cfsr.defects.DefectCorrector`): it learns its map
        from every pushed block and corrects a buffered step in place when it is first read,
        so every method reads corrected spikes. None (default): the spikes as pushed.

    Notes
    -----
    Step indices are absolute int64 (1 step = 25 us). A block whose first step is not the one
    expected means data were lost: the history is discarded and ``gaps`` counts it, because a
    window spanning the hole would give wrong intervals.
    """

    def __init__(
        self,
        method: str | MethodConfig,
        layout: Layout,
        *,
        params: Mapping[str, Any] | None = None,
        preset: str | None = None,
        slack: int = 4096,
        defects: DefectCorrector | None = None,
    ) -> None:
        self.layout = layout
        self.slack = int(slack)
        self.defects = defects
        self.gaps = 0
        self._buf: np.ndarray | None = None
        self._capacity = 0  # frames the mirrored ring holds (its rows / 2)
        self._first = 0  # absolute step of the oldest buffered frame
        self._next = 0  # absolute step expected next
        self._count = 0  # buffered frames
        # state a recurrent method carries between outputs of this stream (Method.recurrent);
        # emptied whenever the stream or the method changes
        self.memo: dict[str, Any] = {}
        self.set_method(method, params=params, preset=preset)

    # -- configuration -------------------------------------------------------------------
    def set_method(
        self,
        method: str | MethodConfig,
        *,
        params: Mapping[str, Any] | None = None,
        preset: str | None = None,
    ) -> None:
        """Switch method/parameters at run time, all or nothing.

        The new state is built completely first (parameters validated, the history buffer
        of the new window's size allocated and filled with the buffered frames that still
        fit); only then does it replace the running one. Whatever fails on the way (a
        ValueError naming a parameter, a MemoryError for the buffer) leaves the reconstructor
        exactly as it was, still reconstructing. The buffer follows the window both ways, so
        the memory of a large window is given back when a smaller one replaces it.

        A :class:`~cfsr.config.MethodConfig` was validated when it was made (perhaps in
        another process) and is not validated again; only its window is checked against the
        method's limit here, because this is where a buffer of that size would be allocated.
        """
        if isinstance(method, MethodConfig):
            if params is not None or preset is not None:
                raise TypeError("pass params/preset inside the MethodConfig, not beside it")
            cfg = method
        else:
            cfg = MethodConfig(method, params, preset)
        m: Method = cfg.spec
        p = dict(cfg.params)
        before, after = cfg.window
        if before + after > m.max_span:
            raise ValueError(
                f"method {m.name!r} with {dict(cfg.params)}: a window of {before} steps "
                f"before t and {after} after exceeds the {m.max_span} steps a history "
                "buffer may hold"
            )
        cap = before + after + 1 + self.slack
        buf, keep = self._buf, self._count
        if buf is None or cap != self._capacity:
            buf = np.zeros((2 * cap, self.layout.frame_bytes), np.uint8)  # may raise
            keep = min(self._count, cap)  # the newest frames that fit
            if keep:
                a = self._next - keep
                _write_mirrored(buf, cap, self.packed(a, self._next), a)
        # commit: plain assignments from here on, nothing can fail half-way
        self.config = cfg
        self.method, self.params = m, p
        self.before, self.after = before, after
        self.memo = {}
        if buf is not self._buf:
            self._buf, self._capacity = buf, cap
            self._count = keep
            self._first = self._next - keep

    @property
    def buffer_nbytes(self) -> int:
        """Bytes of the history buffer (a mirrored ring: twice the frames it holds)."""
        return 0 if self._buf is None else int(self._buf.nbytes)

    # -- input ---------------------------------------------------------------------------
    @property
    def first_step(self) -> int:
        """Oldest buffered step."""
        return self._first

    @property
    def next_step(self) -> int:
        """One past the newest buffered step."""
        return self._next

    def reset(self, start: int = 0) -> None:
        """Forget the buffered frames (and any recurrent state); the next step is ``start``."""
        self._count = 0
        self.memo = {}
        self._first = self._next = int(start)

    def push(self, packed: np.ndarray, start: int | None = None) -> None:
        """Append packed frames ``(n, frame_bytes)`` whose first frame is step ``start``."""
        packed = np.asarray(packed, dtype=np.uint8)
        if packed.ndim == 1:
            packed = packed.reshape(-1, self.layout.frame_bytes)
        if packed.ndim != 2 or packed.shape[1] != self.layout.frame_bytes:
            raise ValueError(
                f"packed block must be (n, {self.layout.frame_bytes}), got {packed.shape}"
            )
        start = self._next if start is None else int(start)
        if self._count and start != self._next:
            self.gaps += 1
            self.reset(start)
        elif not self._count:
            self._first = self._next = start
        self._append(packed, start)

    def _append(self, packed: np.ndarray, start: int) -> None:
        cap = self._capacity
        buf = self._buf
        assert buf is not None
        if len(packed) > cap:
            skip = len(packed) - cap
            packed = packed[skip:]
            start += skip
            self._count = 0
            self._first = start
        n = len(packed)
        _write_mirrored(buf, cap, packed, start)
        if self.defects is not None:
            self.defects.arrived(packed, start)
        self._next = start + n
        self._count = min(cap, self._count + n)
        self._first = self._next - self._count

    # -- output --------------------------------------------------------------------------
    def packed(self, a: int, b: int) -> np.ndarray:
        """Buffered packed frames of steps ``[a, b)`` as one contiguous view."""
        if a < self._first or b > self._next or a > b:
            raise ValueError(f"steps [{a}, {b}) not buffered (have [{self._first}, {self._next}))")
        cap = self._capacity
        i = a % cap
        assert self._buf is not None
        if self.defects is not None:  # before any method reads them
            self.defects.before_read(self._buf, cap, a, b)
        return self._buf[i : i + (b - a)]

    def can_compute(self, t: int, *, final: bool = False) -> bool:
        """True when step ``t`` and its full window (or the stream end, if ``final``) are here."""
        if t < self._first or t >= self._next:
            return False
        return final or t + self.after < self._next

    def compute(self, t: int, *, final: bool = False) -> Output:
        """Reconstruct step ``t`` from the buffered window.

        The window is ``[t - before, t + after]`` clipped to what the stream holds. Pass
        ``final=True`` at the end of a stream to accept a window clipped at the end; clipping at
        the start happens only when ``t`` is within ``before`` steps of the stream's first step.
        """
        if not self.can_compute(t, final=final):
            raise ValueError(
                f"step {t} cannot be computed yet (buffered [{self._first}, {self._next}), "
                f"needs {self.after} steps after)"
            )
        a = max(self._first, t - self.before)
        b = min(self._next, t + self.after + 1)
        out = self.method.run_window(self, a, b, t, self.params, self.memo)
        return out if self.defects is None else self.defects.flatten(out, self.method)

    def frames(self, a: int, b: int) -> np.ndarray:
        """Buffered frames of steps ``[a, b)`` unpacked to upright ``(b - a, H, W)`` uint8."""
        return unpack_layout(self.packed(a, b), self.layout)

    def latest_step(self) -> int | None:
        """Newest step whose full window has arrived, or None."""
        t = self._next - 1 - self.after
        return t if t >= self._first else None

    def latest(self) -> tuple[int, Output] | None:
        """Reconstruct the newest computable step (for live display)."""
        t = self.latest_step()
        return None if t is None else (t, self.compute(t))

    def run(
        self, blocks: Iterable[tuple[int, np.ndarray]], times: Iterable[int]
    ) -> Iterator[tuple[int, Output]]:
        """Feed ``(start_step, packed_block)`` pairs; yield ``(t, Output)`` for sorted ``times``.

        Each output is produced as soon as its window has arrived; the rest at stream end.
        """
        pending = sorted(set(int(t) for t in times))
        k = 0
        for start, blk in blocks:
            self.push(blk, start)
            while k < len(pending) and self.can_compute(pending[k]):
                yield pending[k], self.compute(pending[k])
                k += 1
            while k < len(pending) and pending[k] < self._first:
                raise ValueError(f"step {pending[k]} was evicted before it could be computed")
        for t in pending[k:]:
            if not self.can_compute(t, final=True):
                raise ValueError(f"step {t} is outside the stream [{self._first}, {self._next})")
            yield t, self.compute(t, final=True)


def _write_mirrored(buf: np.ndarray, cap: int, packed: np.ndarray, start: int) -> None:
    """Write frames ``packed`` (at most ``cap``), the first being step ``start``, into the
    mirrored ring ``buf`` of ``cap`` frames: step s lives at rows ``s % cap`` and
    ``s % cap + cap``, so any ``cap`` consecutive steps are one contiguous slice."""
    n = len(packed)
    i0 = start % cap
    k = min(n, cap - i0)
    buf[i0 : i0 + k] = packed[:k]
    buf[i0 + cap : i0 + cap + k] = packed[:k]
    if n > k:
        buf[: n - k] = packed[k:]
        buf[cap : cap + n - k] = packed[k:]
