"""The JSON sidecar of a spike recording (``NAME.dat.json``): its bounds, its checks, how it is
read and how it is written.

Every sidecar value the library uses is checked on read (:func:`validate_sidecar`) against
bounds a real camera can reach, before anything is sized by it; a sidecar is written whole
(:func:`write_json_atomic`) or in space reserved for it (:data:`SIDECAR_RESERVE_BYTES`).
"""

from __future__ import annotations

import errno
import json
import math
import numbers
import os
import stat
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from cfsr.layout import Layout

__all__ = [
    "SIDECAR_VERSION",
    "SIDECAR_RESERVE_BYTES",
    "SpikeFileError",
    "FileShrankError",
    "sidecar_path",
    "read_sidecar",
    "validate_sidecar",
    "file_kind",
    "write_json_atomic",
    "MAX_SIDE_PX",
    "MAX_FRAME_PIXELS",
    "MIN_RATE_HZ",
    "MAX_RATE_HZ",
    "MIN_GAIN",
    "MAX_GAIN",
    "MAX_FRAMES",
    "MAX_SIDECAR_BYTES",
    "MAX_SIDECAR_DIGITS",
]

SIDECAR_VERSION = 1

# Bounds on sidecar values (and on the geometry and rate read_dat accepts): what a real spike
# camera can reach, not what JSON can hold. A value outside them is a damaged or hostile
# sidecar and is refused before anything (ring buffers, frame slots, durations) is sized by it.
#: Width and height in pixels, 1..65,535: the live WebSocket frame header stores the width in
#: 16 bits, so nothing wider can be shown. Head columns count towards the stored width.
MAX_SIDE_PX = 65_535
#: Pixels per stored frame (2**24 = 4096 x 4096, 2 MiB packed). Spike sensors built so far are
#: at most about 1000 x 1000; beyond this one 256-frame block would no longer fit in memory.
MAX_FRAME_PIXELS = 1 << 24
#: Steps per second, in [1, 1e7]: the sensor samples at 40,000; 10 MHz is beyond any made.
#: Below one step a second a replay would show no frame for minutes (at 1e-300, never) while
#: reporting itself as streaming.
MIN_RATE_HZ = 1.0
MAX_RATE_HZ = 1e7
#: Display gain in spikes/step (the firing rate shown as white), in [1e-6, 1]: no pixel can
#: fire more than once per step; below one spike per million steps (25 s) 1/gain overflows the
#: live frame header's float32 and every pixel shows as 0 or 255. The one owner of this bound:
#: the service's API takes it from here.
MIN_GAIN = 1e-6
MAX_GAIN = 1.0
#: Digits a sidecar number may have: more is no camera's value (and Python refuses to convert
#: over 4,300 digits with a message that names neither the file nor the key).
MAX_SIDECAR_DIGITS = 40
#: Frames a sidecar may claim: 2**40 steps (318 days at 40 kHz).
MAX_FRAMES = 1 << 40
#: A sidecar is a few hundred bytes of JSON; a larger one is refused, not read into memory.
MAX_SIDECAR_BYTES = 1 << 20


class SpikeFileError(ValueError):
    """A spike file or its sidecar cannot be used as asked; the message names file and problem."""


class FileShrankError(SpikeFileError):
    """A ``.dat`` file no longer holds frames it held when it was opened (truncated/rewritten)."""


def sidecar_path(path: str | os.PathLike) -> Path:
    """``NAME.dat`` -> ``NAME.dat.json``."""
    p = Path(path)
    return p.with_name(p.name + ".json")


def file_kind(mode: int) -> str:
    """What an ``st_mode`` is, in words ("regular file", "FIFO (named pipe)", ...)."""
    for test, name in (
        (stat.S_ISREG, "regular file"),
        (stat.S_ISDIR, "directory"),
        (stat.S_ISFIFO, "FIFO (named pipe)"),
        (stat.S_ISSOCK, "socket"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
    ):
        if test(mode):
            return name
    return "special file"


def _show(value: Any) -> str:
    """A sidecar value as it was written in JSON, on one short line, for error messages."""
    try:
        s = json.dumps(value)
    except (TypeError, ValueError):
        s = repr(value)
    return s if len(s) <= 40 else s[:37] + "..."


def _as_int(value: Any) -> int | None:
    """``value`` as an int if it is integral (JSON ``400`` or ``400.0``, a NumPy integer from
    a writer), else None."""
    if isinstance(value, bool | np.bool_):  # JSON true/false are not numbers
        return None
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real) and math.isfinite(value) and float(value).is_integer():
        return int(value)
    return None


def _as_number(value: Any) -> float | None:
    """``value`` as a float if it is a finite real number (not a bool), else None."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        return None
    v = float(value)
    return v if math.isfinite(v) else None


class _LongNumber:
    """A JSON number written with more than :data:`MAX_SIDECAR_DIGITS` digits, kept as its
    length only (never converted: that costs time quadratic in the digits)."""

    def __init__(self, text: str) -> None:
        self.digits = len(text)

    def __repr__(self) -> str:
        return f"<a number of {self.digits} digits>"


def _parse_number(text: str) -> Any:
    if len(text) > MAX_SIDECAR_DIGITS:
        return _LongNumber(text)
    return float(text) if any(c in text for c in ".eE") else int(text)


def _long_number_at(value: Any, path: str = "") -> tuple[str, _LongNumber] | None:
    """The key path and value of the first :class:`_LongNumber` inside ``value`` (None if
    there is none)."""
    if isinstance(value, _LongNumber):
        return path, value
    items = value.items() if isinstance(value, Mapping) else (
        enumerate(value) if isinstance(value, list) else ())
    for k, v in items:
        if (found := _long_number_at(v, f"{path}.{k}" if path else str(k))) is not None:
            return found
    return None


def validate_sidecar(meta: Mapping[str, Any], where: str | os.PathLike) -> dict[str, Any]:
    """Check every sidecar value the library uses against what a real camera can reach.

    Parameters
    ----------
    meta : mapping
        The parsed sidecar.
    where : path-like
        The sidecar, named in error messages.

    Returns
    -------
    dict
        A copy with integral values as ``int`` and rates as ``float``. Keys the library does not
        interpret (provenance, scene description, ...) pass through unchanged.

    Raises
    ------
    SpikeFileError
        One line naming ``where``, the key, the value and the allowed range. Bounds:
        ``width``, ``height`` 1..:data:`MAX_SIDE_PX` pixels, ``head_cols`` >= 0 with the stored
        row at most :data:`MAX_SIDE_PX` and the frame at most :data:`MAX_FRAME_PIXELS`;
        ``flipud``/``fliplr`` booleans; ``frame_bytes`` equal to the geometry's; ``n_frames``
        0..:data:`MAX_FRAMES`; ``rate_hz`` in [:data:`MIN_RATE_HZ`, :data:`MAX_RATE_HZ`]
        steps/s; ``gain`` null or in [:data:`MIN_GAIN`, :data:`MAX_GAIN`] spikes/step.
    """
    out = dict(meta)

    def bad(key: str, expected: str, *, geometry: bool = False) -> SpikeFileError:
        what = "wrong geometry" if geometry else "bad sidecar value"
        return SpikeFileError(f"{where}: {what}: {key} = {_show(meta[key])}, expected {expected}")

    if (long := _long_number_at(meta)) is not None:
        raise SpikeFileError(f"{where}: bad sidecar value: {long[0]} = {long[1]!r}, expected "
                             f"a number of at most {MAX_SIDECAR_DIGITS} digits")

    for key, lo in (("width", 1), ("height", 1), ("head_cols", 0)):
        if key in meta:
            v = _as_int(meta[key])
            if v is None or not lo <= v <= MAX_SIDE_PX:
                raise bad(key, f"an integer in [{lo}, {MAX_SIDE_PX}] pixels", geometry=True)
            out[key] = v
    for key in ("flipud", "fliplr"):
        if key in meta and not isinstance(meta[key], bool):
            raise bad(key, "true or false", geometry=True)
    default = Layout()
    sw = out.get("width", default.width) + out.get("head_cols", default.head_cols)
    h = out.get("height", default.height)
    if sw > MAX_SIDE_PX or sw * h > MAX_FRAME_PIXELS:
        raise SpikeFileError(
            f"{where}: wrong geometry: stored frame {sw} x {h} pixels (width + head_cols x "
            f"height), expected at most {MAX_SIDE_PX} pixels a row and {MAX_FRAME_PIXELS} a frame"
        )
    if "frame_bytes" in meta:
        v = _as_int(meta["frame_bytes"])
        if v is None or v * 8 != sw * h:
            raise bad("frame_bytes", f"{sw} x {h} / 8 = {sw * h / 8:.12g} bytes (its geometry)",
                      geometry=True)
        out["frame_bytes"] = v
    for key, hi in (("n_frames", MAX_FRAMES), ("dropped_tail_bytes", MAX_FRAME_PIXELS // 8)):
        if key in meta:
            v = _as_int(meta[key])
            if v is None or not 0 <= v <= hi:
                raise bad(key, f"an integer in [0, {hi}]")
            out[key] = v
    if "sidecar_version" in meta:
        v = _as_int(meta["sidecar_version"])
        if v is None or v < 1:
            raise bad("sidecar_version", "an integer >= 1")
    if "rate_hz" in meta:
        v = _as_number(meta["rate_hz"])
        if v is None or not MIN_RATE_HZ <= v <= MAX_RATE_HZ:
            raise bad("rate_hz", f"a number in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:.0f}] steps/s")
        out["rate_hz"] = v
    if meta.get("gain") is not None:
        v = _as_number(meta["gain"])
        if v is None or not MIN_GAIN <= v <= MAX_GAIN:
            raise bad("gain", f"null or a number in [{MIN_GAIN:g}, {MAX_GAIN:g}] spikes/step")
        out["gain"] = v
    if meta.get("defects") is not None:
        # deferred: a cycle (cfsr.defects.defect_map reads and writes sidecars through this module)
        from cfsr.defects.defect_map import DefectMap

        try:  # checked here once; cfsr.defects.map_of builds it again from the checked value
            DefectMap.from_dict(meta["defects"], (h, out.get("width", default.width)),
                                where=f"{where}: defects")
        except ValueError as exc:
            raise SpikeFileError(str(exc)) from None
    return out


def read_sidecar(path: str | os.PathLike) -> dict[str, Any] | None:
    """Read and validate the JSON sidecar of ``path``; None if there is none.

    The sidecar is opened without blocking and read only if it is a regular file of at most
    :data:`MAX_SIDECAR_BYTES` (a FIFO named like a sidecar must not hang a folder scan). Every
    value is checked by :func:`validate_sidecar`.

    Raises
    ------
    SpikeFileError
        Unreadable, not a regular file, too large, not a JSON object, or a value out of bounds.
    """
    sp = sidecar_path(path)
    try:
        fd = os.open(sp, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise SpikeFileError(f"{sp}: unreadable sidecar ({exc})") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise SpikeFileError(
                f"{sp}: sidecar is a {file_kind(st.st_mode)}, not a regular file"
            )
        if st.st_size > MAX_SIDECAR_BYTES:
            raise SpikeFileError(
                f"{sp}: sidecar is {st.st_size} bytes, more than the {MAX_SIDECAR_BYTES} "
                "a sidecar may hold"
            )
        try:
            raw = b""
            while len(raw) <= MAX_SIDECAR_BYTES:  # a read may return less than asked
                chunk = os.read(fd, MAX_SIDECAR_BYTES + 1 - len(raw))
                if not chunk:
                    break
                raw += chunk
            meta = json.loads(raw.decode("utf-8"), parse_int=_parse_number,
                              parse_float=_parse_number)
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            why = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
            raise SpikeFileError(f"{sp}: unreadable sidecar ({why})") from exc
    finally:
        os.close(fd)
    if not isinstance(meta, dict):
        raise SpikeFileError(f"{sp}: sidecar must hold a JSON object, found {type(meta).__name__}")
    return validate_sidecar(meta, sp)


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


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as JSON to ``path`` through a temporary file in the same folder and a
    rename: ``path`` is either its old content or the whole new one, never a partial file."""
    _write_bytes_atomic(Path(path), json.dumps(obj, indent=2, default=_json_default).encode())


def _write_bytes_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb", buffering=0) as fh:
            _overwrite(fh.fileno(), data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _overwrite(fd: int, data: bytes) -> None:
    """Write all of ``data`` at the start of ``fd`` and cut the file there (short writes are
    retried; one that writes nothing is ENOSPC)."""
    view = memoryview(data)
    done = 0
    while done < len(view):
        n = os.pwrite(fd, view[done:], done)
        if not n:
            raise OSError(errno.ENOSPC, "No space left on device (short write)")
        done += n
    os.ftruncate(fd, len(data))


#: bytes a sidecar holds on disk from the moment its ``.dat`` is created (a few hundred are
#: used; the rest is blanks, which JSON ignores), so the final one fits on a full disk
SIDECAR_RESERVE_BYTES = 16 * 1024


def _sidecar_bytes(side: Mapping[str, Any], pad_to: int = 0) -> bytes:
    """``side`` as indented JSON text, padded with blanks (then a newline) to ``pad_to``."""
    text = json.dumps(side, indent=2, default=_json_default).encode()
    return text + b" " * max(0, pad_to - len(text) - 1) + b"\n"


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
