"""``.dat`` spike files (SpikeCV / Spike-Zoo layout), their JSON sidecar, and ``.npz`` arrays.

A ``.dat`` file has no header: packed frames back to back, LSB-first bits, rows stored upside
down. Files are memory-mapped, so opening a 10 GB recording costs nothing and frames are
unpacked only when asked for. Our writers always add ``NAME.dat.json`` beside the data.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from cfsr._bits import pack_frames
from cfsr.layout import STEP_RATE_HZ, Layout
from cfsr.spikes import SpikeRecording

__all__ = [
    "SpikeFileError",
    "read_dat",
    "write_dat",
    "read_npz",
    "read_spikes",
    "sidecar_path",
    "read_sidecar",
    "DatWriter",
]

SIDECAR_VERSION = 1


class SpikeFileError(ValueError):
    """A spike file or its sidecar cannot be used as asked; the message names file and problem."""


def sidecar_path(path: str | os.PathLike) -> Path:
    """``NAME.dat`` -> ``NAME.dat.json``."""
    p = Path(path)
    return p.with_name(p.name + ".json")


def read_sidecar(path: str | os.PathLike) -> dict[str, Any] | None:
    """Read the JSON sidecar of ``path`` if it exists; raise SpikeFileError if it is unreadable."""
    sp = sidecar_path(path)
    if not sp.exists():
        return None
    try:
        meta = json.loads(sp.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SpikeFileError(f"{sp}: unreadable sidecar ({exc})") from exc
    if not isinstance(meta, dict):
        raise SpikeFileError(f"{sp}: sidecar must hold a JSON object, found {type(meta).__name__}")
    return meta


def _software_version() -> str:
    try:
        from importlib.metadata import version

        return version("cfsr")
    except Exception:  # noqa: BLE001 - metadata missing in a source checkout is fine
        return "unknown"


def _sidecar_dict(
    layout: Layout, n_frames: int, rate_hz: float, meta: Mapping[str, Any] | None
) -> dict[str, Any]:
    out: dict[str, Any] = {
        "format": "spike-dat",
        "sidecar_version": SIDECAR_VERSION,
        "width": layout.width,
        "height": layout.height,
        "head_cols": layout.head_cols,
        "flipud": layout.flipud,
        "fliplr": layout.fliplr,
        "frame_bytes": layout.frame_bytes,
        "n_frames": n_frames,
        "rate_hz": rate_hz,
        "written_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "software": f"cfsr {_software_version()}",
    }
    if meta:
        out.update({k: v for k, v in meta.items() if k not in ("n_frames", "frame_bytes")})
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
    if not p.exists():
        raise SpikeFileError(f"{p}: no such file")
    if p.is_dir():
        raise SpikeFileError(f"{p}: is a directory, expected a .dat file")
    meta = read_sidecar(p) or {}
    try:
        layout = _layout_from(
            meta, width=width, height=height, head_cols=head_cols, flipud=flipud, fliplr=fliplr
        )
    except (TypeError, ValueError) as exc:
        raise SpikeFileError(f"{p}: wrong geometry ({exc})") from exc
    size = p.stat().st_size
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
    if "n_frames" in meta and int(meta["n_frames"]) != n and not tail:
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
        self._fh = open(self.path, "wb")  # noqa: SIM115 - closed in close()

    def write_packed(self, packed: np.ndarray) -> None:
        packed = np.ascontiguousarray(packed, dtype=np.uint8)
        if packed.ndim != 2 or packed.shape[1] != self.layout.frame_bytes:
            raise ValueError(
                f"packed block must be (n, {self.layout.frame_bytes}), got {packed.shape}"
            )
        self._fh.write(packed.tobytes())
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
        if self._fh.closed:
            return
        self._fh.close()
        side = _sidecar_dict(self.layout, self.n_frames, self.rate_hz, self.meta)
        sidecar_path(self.path).write_text(json.dumps(side, indent=2, default=_json_default))

    def __enter__(self) -> DatWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


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
                raise SpikeFileError(
                    f"{p}: cannot tell which array holds spikes; arrays: {names} (pass key=)"
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
