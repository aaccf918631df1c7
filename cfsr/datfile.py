"""``.dat`` spike files (SpikeCV / Spike-Zoo layout) and ``.npz`` arrays.

A ``.dat`` file has no header: packed frames back to back, LSB-first bits, rows stored upside
down. Files are memory-mapped, so opening a 10 GB recording costs nothing and frames are
unpacked only when asked for; a reader that must survive the file shrinking under it (the
replay device) reads through :class:`DatReader` instead. Our writers always add
``NAME.dat.json`` beside the data, and every sidecar value is checked on read
(:mod:`cfsr.sidecar`, whose names this module also gives) against bounds a real camera can
reach.
"""

from __future__ import annotations

import contextlib
import os
import stat
import warnings
import weakref
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cfsr import sidecar
from cfsr._bits import pack_frames
from cfsr.layout import STEP_RATE_HZ, Layout
from cfsr.sidecar import *  # noqa: F403 - the sidecar's public names, reachable from here
from cfsr.sidecar import (  # those this module uses itself
    MAX_FRAME_PIXELS,
    MAX_RATE_HZ,
    MAX_SIDE_PX,
    MIN_RATE_HZ,
    SIDECAR_RESERVE_BYTES,
    FileShrankError,
    SpikeFileError,
    _as_number,
    _overwrite,
    _sidecar_bytes,
    _sidecar_dict,
    _write_bytes_atomic,
    file_kind,
    read_sidecar,
    sidecar_path,
    validate_sidecar,
)
from cfsr.spikes import SpikeRecording

__all__ = [
    "read_dat",
    "write_dat",
    "read_npz",
    "read_spikes",
    "DatReader",
    "DatWriter",
    *sidecar.__all__,  # the sidecar's names, reachable from here as before
]


class DatReader:
    """Bounds-checked reads of whole packed frames from a ``.dat`` file, without a memory map.

    Touching a memory map past the end of a file that shrank after it was mapped kills the
    process with SIGBUS; a reader that must survive the file being truncated or rewritten
    under it (the replay device of a long-running service) reads through this instead. Each
    :meth:`read` is one ``preadv`` into a fresh array: a short read means the file no longer
    holds those frames and raises :class:`FileShrankError`.

    Parameters
    ----------
    path : path-like
        The ``.dat`` file (must be a regular file; it is opened without blocking).
    frame_bytes : int
        Bytes per packed frame.
    offset : int
        Byte offset of frame 0 in the file.
    """

    def __init__(self, path: str | os.PathLike, frame_bytes: int, *, offset: int = 0) -> None:
        self.path = Path(path)
        self.frame_bytes = int(frame_bytes)
        self.offset = int(offset)
        fd = os.open(self.path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            os.close(fd)
            raise SpikeFileError(f"{self.path}: is a {file_kind(st.st_mode)}, not a regular file")
        self._fd = fd
        # the descriptor is released even if close() is never called
        self._finalizer = weakref.finalize(self, os.close, fd)

    @property
    def closed(self) -> bool:
        return not self._finalizer.alive

    def close(self) -> None:
        self._finalizer()

    def size(self) -> int:
        """Current size of the file in bytes."""
        return os.fstat(self._fd).st_size

    def read(self, start: int, n: int) -> np.ndarray:
        """Frames ``start..start+n-1`` as a new ``(n, frame_bytes)`` uint8 array.

        Raises
        ------
        FileShrankError
            The file ends before the last requested byte; the message names the file, its
            size now and the bytes that were needed.
        """
        fb = self.frame_bytes
        out = np.empty((n, fb), np.uint8)
        want = n * fb
        pos = self.offset + start * fb
        view = memoryview(out.reshape(-1))
        got = 0
        while got < want:
            k = os.preadv(self._fd, [view[got:]], pos + got)
            if k == 0:
                break  # end of file
            got += k
        if got < want:
            raise FileShrankError(
                f"{self.path}: the file shrank while being read (it is now {self.size()} bytes; "
                f"frames {start}..{start + n - 1} need bytes {pos}..{pos + want - 1})"
            )
        return out



def _layout_from(meta: Mapping[str, Any] | None, **given: Any) -> Layout:
    """Explicit arguments win over the sidecar; the sidecar wins over defaults."""
    fields = {}
    for key in ("width", "height", "head_cols", "flipud", "fliplr"):
        if given.get(key) is not None:
            fields[key] = given[key]
        elif meta and key in meta:
            fields[key] = meta[key]
    return Layout(**fields)


def _regular_file(p: Path) -> os.stat_result:
    """``p``'s stat when it is a regular file, else SpikeFileError saying what it is."""
    try:
        st = p.stat()
    except FileNotFoundError:
        raise SpikeFileError(f"{p}: no such file") from None
    except OSError as exc:
        raise SpikeFileError(f"{p}: cannot read ({exc})") from exc
    if stat.S_ISDIR(st.st_mode):
        raise SpikeFileError(f"{p}: is a directory, expected a .dat file")
    if not stat.S_ISREG(st.st_mode):
        # a FIFO or device reports size 0 and would block or never end: say what it is
        raise SpikeFileError(
            f"{p}: is a {file_kind(st.st_mode)}, not a regular file; a .dat recording is a file"
        )
    return st


def read_dat(
    path: str | os.PathLike,
    width: int | None = None,
    height: int | None = None,
    *,
    head_cols: int | None = None,
    flipud: bool | None = None,
    fliplr: bool | None = None,
    allow_partial: bool = False,
    rate_hz: float | None = None,
) -> SpikeRecording:
    """Open a ``.dat`` spike recording, memory-mapped.

    Parameters
    ----------
    path : path-like
        The ``.dat`` file. A ``NAME.dat.json`` sidecar, if present, supplies geometry,
        orientation, rate and gain; explicit arguments override it.
    width, height : int, optional
        Image size in pixels without head columns (default 400 x 250).
    head_cols : int, optional
        Extra stored columns to drop (16 for the 416-wide raw variant).
    flipud, fliplr : bool, optional
        Orientation of the stored rows (default: stored upside down, not mirrored).
    allow_partial : bool
        If the size is not a multiple of the frame size, drop the incomplete tail and warn
        instead of raising. The number of dropped bytes is in ``meta["dropped_tail_bytes"]``.
    rate_hz : float, optional
        Steps per second (default from the sidecar, else 40,000).

    Returns
    -------
    SpikeRecording
        Frames are unpacked on demand: ``rec[a:b]`` is ``(b - a, H, W)`` uint8 0/1, upright.

    Raises
    ------
    SpikeFileError
        Missing or empty file, size not a multiple of the frame size, bad geometry, unreadable
        sidecar. The message names the file and the problem.
    """
    p = Path(path)
    st = _regular_file(p)
    meta = read_sidecar(p) or {}
    try:
        layout = _layout_from(
            meta, width=width, height=height, head_cols=head_cols, flipud=flipud, fliplr=fliplr
        )
    except (TypeError, ValueError) as exc:
        raise SpikeFileError(f"{p}: wrong geometry ({exc})") from exc
    if (
        layout.width > MAX_SIDE_PX
        or layout.height > MAX_SIDE_PX
        or layout.stored_width > MAX_SIDE_PX
        or layout.stored_width * layout.height > MAX_FRAME_PIXELS
    ):
        raise SpikeFileError(
            f"{p}: wrong geometry: stored frame {layout.stored_width} x {layout.height} pixels, "
            f"expected at most {MAX_SIDE_PX} pixels a side and {MAX_FRAME_PIXELS} a frame"
        )
    if rate_hz is not None and not (
        _as_number(rate_hz) is not None and MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ
    ):
        raise SpikeFileError(
            f"{p}: rate_hz = {rate_hz!r}, expected a number in [{MIN_RATE_HZ:g}, "
            f"{MAX_RATE_HZ:.0f}] steps/s"
        )
    size = st.st_size
    if size == 0:
        raise SpikeFileError(f"{p}: empty file (0 bytes), no spike frames")
    fb = layout.frame_bytes
    n, tail = divmod(size, fb)
    if tail:
        msg = (
            f"{p}: size {size} bytes is not a multiple of the frame size {fb} bytes "
            f"({layout.stored_width} x {layout.height} pixels); {n} whole frames and "
            f"{tail} bytes left over"
        )
        if not allow_partial or n == 0:
            hint = "" if n == 0 else "; pass allow_partial=True (--allow-partial) to drop the tail"
            raise SpikeFileError(msg + hint)
        warnings.warn(msg + "; dropping the partial tail", stacklevel=2)
        meta = {**meta, "dropped_tail_bytes": tail}
    if "n_frames" in meta and meta["n_frames"] != n and not tail:
        warnings.warn(
            f"{p}: sidecar says {meta['n_frames']} frames but the file holds {n}", stacklevel=2
        )
    data = np.memmap(p, dtype=np.uint8, mode="r", shape=(n, fb))
    rate = float(rate_hz if rate_hz is not None else meta.get("rate_hz", STEP_RATE_HZ))
    return SpikeRecording(data, layout, rate, dict(meta), str(p))


class DatWriter:
    """Append packed or unpacked frames to a ``.dat`` file; writes the sidecar on close.

    Used by ``write_dat``, the simulator and live recording, so every file we write gets the
    same sidecar. Use as a context manager.

    The file only ever holds whole frames: when a write fails part-way (``ENOSPC`` on a full
    disk, ``EFBIG``, an I/O error) the partial frame is cut off before the error is raised, and
    :attr:`n_frames` counts the frames that are really on disk.

    The sidecar exists before the first byte of spikes: opening writes a provisional one
    (geometry and rate, ``"complete": false``, no ``n_frames``) padded with blanks to
    :data:`SIDECAR_RESERVE_BYTES`, so its disk space is held from the start. :meth:`close`
    writes the final one to a temporary file renamed over it (a reader never sees half a
    sidecar); when the disk is full for that, it overwrites the reserved space in place. So a
    recording stays readable with its own geometry however the disk fills (before, another
    writer filling the disk lost the sidecar, and a 256 x 128 recording was read as 400 x 250).
    Opening fails, leaving no file, when not even the reserve fits. :meth:`discard` closes and
    removes both files (a recording that got no frame is not left behind as an empty file).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        layout: Layout,
        *,
        rate_hz: float = float(STEP_RATE_HZ),
        meta: Mapping[str, Any] | None = None,
    ) -> None:
        self.path = Path(path)
        self.layout = layout
        self.rate_hz = float(rate_hz)
        self.meta = dict(meta or {})
        self.n_frames = 0
        # never write a sidecar that read_sidecar would refuse; fail before the file exists
        validate_sidecar(_sidecar_dict(layout, 0, self.rate_hz, self.meta), sidecar_path(path))
        # unbuffered: each write reports how many bytes reached the file, so a failure can be
        # trimmed back to the last whole frame
        self._fh = open(self.path, "wb", buffering=0)  # noqa: SIM115 - closed in close()
        self._reserve_sidecar()

    # -- the sidecar's storage (FolderDatWriter keeps it in an open folder instead) ----------
    def _put_sidecar(self, data: bytes) -> None:
        """Replace the sidecar by ``data`` atomically (temporary file + rename)."""
        _write_bytes_atomic(sidecar_path(self.path), data)

    def _put_sidecar_in_place(self, data: bytes) -> None:
        """Overwrite the existing sidecar's bytes with ``data`` (no new disk space needed)."""
        with open(sidecar_path(self.path), "r+b", buffering=0) as fh:
            _overwrite(fh.fileno(), data)

    def _remove_files(self) -> None:
        """Remove the ``.dat`` and its sidecar."""
        for p in (self.path, sidecar_path(self.path)):
            p.unlink(missing_ok=True)

    # -- the sidecar's life ----------------------------------------------------------------------
    def _reserve_sidecar(self) -> None:
        """Write the provisional sidecar, padded to :data:`SIDECAR_RESERVE_BYTES`; on failure
        (no room even for that) remove the new ``.dat`` and raise."""
        side = _sidecar_dict(self.layout, 0, self.rate_hz, self.meta)
        del side["n_frames"]  # unknown until the end: read from the file's size meanwhile
        side["complete"] = False
        try:
            self._put_sidecar(_sidecar_bytes(side, SIDECAR_RESERVE_BYTES))
        except BaseException:
            self._fh.close()
            with contextlib.suppress(OSError):
                self._remove_files()
            raise

    def _write_final_sidecar(self) -> None:
        side = _sidecar_dict(self.layout, self.n_frames, self.rate_hz, self.meta)
        try:
            self._put_sidecar(_sidecar_bytes(side))
        except OSError as exc:
            # the disk is full (or nearly): the reserved sidecar's space is still ours
            data = _sidecar_bytes(side, SIDECAR_RESERVE_BYTES)
            if len(data) > SIDECAR_RESERVE_BYTES:  # a long drop map: keep its total only
                side["drop_map"] = f"{len(side.get('drop_map') or ())} entries, not kept"
                data = _sidecar_bytes(side, SIDECAR_RESERVE_BYTES)
            if len(data) > SIDECAR_RESERVE_BYTES:  # a calibration's gain: 'cfsr info' remakes it
                side.pop("defects", None)
                data = _sidecar_bytes(side, SIDECAR_RESERVE_BYTES)
            try:
                self._put_sidecar_in_place(data)
            except OSError:
                raise exc from None

    @property
    def bytes_written(self) -> int:
        return self.n_frames * self.layout.frame_bytes

    def write_packed(self, packed: np.ndarray) -> None:
        """Append ``(n, frame_bytes)`` stored frames; on ``OSError`` the file is trimmed to
        the frames fully written (counted in :attr:`n_frames`) and the error re-raised."""
        packed = np.ascontiguousarray(packed, dtype=np.uint8)
        fb = self.layout.frame_bytes
        if packed.ndim != 2 or packed.shape[1] != fb:
            raise ValueError(f"packed block must be (n, {fb}), got {packed.shape}")
        view = memoryview(packed).cast("B")
        done = 0
        try:
            while done < len(view):
                n = self._fh.write(view[done:])
                if not n:
                    raise OSError(28, "No space left on device (short write)", str(self.path))
                done += n
        except OSError:
            self.n_frames += done // fb
            try:
                os.ftruncate(self._fh.fileno(), self.bytes_written)
            except OSError:
                pass  # the write error is the one to report
            raise
        self.n_frames += packed.shape[0]

    def write_frames(self, frames: np.ndarray) -> None:
        frames = np.asarray(frames)
        lay = self.layout
        if frames.ndim != 3 or frames.shape[1:] != (lay.height, lay.width):
            raise ValueError(
                f"frames must be (n, {lay.height}, {lay.width}), got shape {frames.shape}"
            )
        if lay.head_cols:
            pad = np.zeros(frames.shape[:2] + (lay.head_cols,), np.uint8)
            if lay.fliplr:
                frames = np.concatenate([pad, frames], axis=2)
            else:
                frames = np.concatenate([frames, pad], axis=2)
        self.write_packed(pack_frames(frames, flipud=lay.flipud, fliplr=lay.fliplr))

    def close(self) -> None:
        """Close the file and write the sidecar atomically (temp file + rename)."""
        if self._fh.closed:
            return
        self._fh.close()
        self._write_final_sidecar()

    def discard(self) -> None:
        """Close and remove the ``.dat`` and its sidecar (a recording that holds nothing)."""
        if not self._fh.closed:
            self._fh.close()
        self._remove_files()

    def __enter__(self) -> DatWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()



def write_dat(
    path: str | os.PathLike,
    spikes: np.ndarray | SpikeRecording,
    *,
    layout: Layout | None = None,
    rate_hz: float | None = None,
    meta: Mapping[str, Any] | None = None,
    block: int = 4096,
) -> Path:
    """Write spikes to ``path`` in the ``.dat`` layout, plus the ``path.json`` sidecar.

    Parameters
    ----------
    spikes : ndarray (T, H, W) of 0/1, or SpikeRecording
        Upright frames. A recording is re-encoded in ``layout`` block by block.
    layout : Layout, optional
        Stored orientation/head columns; default: upside-down rows, no head columns, the
        array's geometry (SpikeCV ``SpikeToRaw`` / Spike-Zoo ``save_vidar_dat`` compatible).
    meta : mapping, optional
        Extra sidecar fields (``gain`` in spikes/step for display 255, provenance, ...).
    """
    if isinstance(spikes, SpikeRecording):
        src = spikes
        h, w = src.layout.height, src.layout.width
        base_meta = {**src.meta, **(meta or {})}
        rate = src.rate_hz if rate_hz is None else rate_hz
    else:
        arr = np.asarray(spikes)
        if arr.ndim != 3:
            raise ValueError(f"spikes must be (T, H, W), got shape {arr.shape}")
        h, w = arr.shape[1:]
        base_meta = dict(meta or {})
        rate = STEP_RATE_HZ if rate_hz is None else rate_hz
    if layout is not None:
        lay = layout
    elif isinstance(spikes, SpikeRecording):
        lay = spikes.layout
    else:
        lay = Layout(width=w, height=h)
    if (lay.height, lay.width) != (h, w):
        raise ValueError(f"layout is {lay.width} x {lay.height} but spikes are {w} x {h}")
    with DatWriter(path, lay, rate_hz=rate, meta=base_meta) as wr:
        if isinstance(spikes, SpikeRecording):
            if spikes.layout == lay:
                for _, blk in spikes.iter_blocks(block):
                    wr.write_packed(blk)
            else:
                for a in range(0, len(spikes), block):
                    wr.write_frames(spikes.frames(a, a + block))
        else:
            for a in range(0, arr.shape[0], block):
                wr.write_frames(arr[a : a + block])
    return Path(path)


def read_npz(path: str | os.PathLike, key: str | None = None) -> SpikeRecording:
    """Read decoded spikes from an ``.npz`` (e.g. Spike-Zoo's ``uhsr.npz``, key ``spk``).

    The array must be ``(T, H, W)`` of 0/1, upright. ``key`` defaults to ``spk`` or the only
    3-D array in the file.
    """
    p = Path(path)
    if not p.exists():
        raise SpikeFileError(f"{p}: no such file")
    try:
        with np.load(p, allow_pickle=False) as z:
            names = list(z.files)
            if key is None:
                cands = [k for k in names if z[k].ndim == 3]
                key = "spk" if "spk" in names else (cands[0] if len(cands) == 1 else None)
            if key is None or key not in names:
                # named for both callers: the function's argument and the CLI's option
                what = "cannot tell which array holds spikes" if key is None else (
                    f"no array {key!r}")
                raise SpikeFileError(
                    f"{p}: {what}; arrays: {names} (choose one: key= in Python, --key on "
                    "the command line)"
                )
            arr = z[key]
    except (OSError, ValueError) as exc:
        if isinstance(exc, SpikeFileError):
            raise
        raise SpikeFileError(f"{p}: not a readable .npz ({exc})") from exc
    if arr.ndim != 3 or arr.shape[0] == 0:
        raise SpikeFileError(f"{p}: array {key!r} has shape {arr.shape}, expected (T, H, W)")
    if arr.dtype != np.bool_ and arr.size and (arr.max() > 1 or arr.min() < 0):
        raise SpikeFileError(f"{p}: array {key!r} holds values outside 0/1")
    rec = SpikeRecording.from_array(arr.astype(np.uint8, copy=False))
    rec.path = str(p)
    rec.meta.update(read_sidecar(p) or {})
    return rec


def read_spikes(path: str | os.PathLike, **kwargs: Any) -> SpikeRecording:
    """Open ``.dat`` or ``.npz`` by extension."""
    p = Path(path)
    if p.suffix.lower() == ".npz":
        return read_npz(p, key=kwargs.pop("key", None))
    return read_dat(p, **kwargs)
