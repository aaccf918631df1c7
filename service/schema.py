"""The live frame schema: one owner for what the worker writes and every reader reads.

Three contracts cross process and network boundaries, and each is written here once:

* **The worker's counters** (:class:`WorkerCounters`): a typed record. The worker updates
  them in place in shared memory as the fields of :data:`COUNTER_DTYPE` (one float64 word
  each, meaningful on its own, read without a lock); the web process reads them back as a
  :class:`WorkerCounters`. A counter is named once, as a field; a misspelt name fails (a
  ``KeyError``/``ValueError`` from NumPy, an ``AttributeError`` from the record) instead of
  reading 0.
* **The mask names** (:func:`display_masks`): every mask a registered method declares
  (:attr:`cfsr.methods.registry.Method.masks`), in registration order. The frame slot stores
  them in its header when it is made, the worker publishes each under its name, and the
  WebSocket message carries one bit plane per name in that order (the viewer reads the names
  from ``GET /api/schema``).
* **The WebSocket frame message** (:data:`WS_HEADER`, :func:`encode_ws_message`,
  :func:`decode_ws_message`) and the method-name length shared with the slot
  (:data:`METHOD_NAME_BYTES`).

WebSocket message (binary, little-endian), version 2::

    offset size  field
    0      4     magic b"CFSR"
    4      2     version (2)
    6      2     header length in bytes (64)
    8      8     step index t of the frame (int64; 1 step = 25 us)
    16     4     frame number (uint32, counts published frames)
    20     2     width W
    22     2     height H
    24     1     mask flags: bit k set when mask k (GET /api/schema "masks") is present
    25     1     number of mask planes that follow the image (len of "masks")
    26     2     reserved
    28     4     gain (float32, spikes/step shown as 255)
    32     4     compute time (float32, ms)
    36     4     latency (float32, ms: newest spike used -> published)
    40     24    method name (ASCII, NUL padded)
    64     W*H   8-bit image, row-major, upright
    then         one plane per mask name, ceil(W*H/8) bytes each, bit p%8 of byte p//8
                 (LSB first); zeros where the mask is absent
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from cfsr import methods as registry  # read at call time (tests stand one in)

__all__ = [
    "COUNTER_DTYPE",
    "MASK_ALPHA",
    "MASK_STYLE",
    "MAX_MASKS",
    "SlotFrame",
    "MASK_NAME_BYTES",
    "METHOD_NAME_BYTES",
    "WS_HEADER",
    "WS_VERSION",
    "QUALITY_TIERS",
    "quality_code",
    "WorkerCounters",
    "counter_meanings",
    "decode_ws_message",
    "display_masks",
    "encode_ws_message",
    "mask_color",
    "schema_document",
]

#: bytes of the method name in the frame slot and in the WebSocket header (ASCII, NUL padded)
METHOD_NAME_BYTES = 24
#: the most masks a frame carries (one flag bit each in the WebSocket header)
MAX_MASKS = 8
#: the mask of the hot and dead pixels the worker corrects (cfsr.defects), after the methods'
DEFECTS_MASK = "defects"
#: the defect map's states, as the ``defects_state`` counter numbers them
DEFECT_STATES = ("off", "learning", "ready", "given")
#: bytes of one mask name in the frame slot's header
MASK_NAME_BYTES = 16


def _counter(meaning: str, kind: type = float) -> Any:
    return field(default=kind(0), metadata={"meaning": meaning})


@dataclass(frozen=True)
class WorkerCounters:
    """The worker's live counters, as the web process reads them (units in each meaning)."""

    heartbeat: float = _counter("time.monotonic() of the worker's last loop (s)")
    pid: int = _counter("process id of the worker", int)
    frames_out: int = _counter("frames published", int)
    steps_ingested: int = _counter("steps copied from the ring into the reconstructor", int)
    worker_skip_frames: int = _counter(
        "steps the display skipped because the reconstructor fell behind the ring (no spike "
        "data lost: the recorder reads the ring on its own)", int)
    ring_lost_frames: int = _counter(
        "steps overwritten in the ring before the worker read them: the display skipped "
        "them (no spike data lost: the recorder reads the ring on its own)", int)
    ring_overruns: int = _counter("times the ring's writer overran the worker", int)
    ring_torn: int = _counter("ring blocks read while being written, read again", int)
    gaps: int = _counter("breaks in the step sequence the worker saw", int)
    errors: int = _counter("frames that failed (the worker kept running)", int)
    compute_ms: float = _counter("reconstruction time per frame (ms, moving average)")
    latency_ms: float = _counter("arrival of the newest step used -> publish (ms, moving "
                                 "average)")
    config_version: int = _counter("version of the configuration the worker runs", int)
    started: float = _counter("time.monotonic() when the worker started (s)")
    first_frame_since: float = _counter(
        "time.monotonic() when the first frame under the current configuration began "
        "computing, 0 when none is pending (s; on a machine's first use it waits on numba)")
    workers: int = _counter("reconstruction processes in the worker's pool", int)
    threads: int = _counter("numba/OpenCV threads per process", int)
    shown_full: int = _counter("frames shown at CFSR's full quality tier (every frame of "
                               "other methods)", int)
    shown_fast: int = _counter("frames shown at CFSR's fast tier", int)
    dropped_late: int = _counter("frames computed but not shown: too late, or under a "
                                 "replaced configuration or source (no spike data lost)", int)
    dropped_order: int = _counter("frames computed but not shown: a newer step was shown "
                                  "first (no spike data lost)", int)
    fallback: int = _counter(
        "the rung of the ladder standing in for a first frame that compiles (0 none, 1 TFP, "
        "2 CSR)", int
    )
    fallback_frames: int = _counter("stand-in frames shown that way", int)
    shown_tier: int = _counter(
        "the tier that made the frame shown last (0 none, 1 full, 2 fast)", int)
    viewers: int = _counter("clients watching the frames, as the worker was last told (with "
                            "none it computes one frame a second)", int)
    pool_nice: int = _counter(
        "nice value the reconstruction pool's processes compute frames at (the least nice of "
        "them; raised above acquisition's once every kernel is cached and loaded)", int)
    defects_state: int = _counter(
        "the hot/dead pixel map (cfsr.defects): 0 correction off, 1 learning from the stream, "
        "2 ready, 3 given from outside", int)
    defects_hot: int = _counter("pixels the map calls hot (corrected before the method)", int)
    defects_dead: int = _counter("pixels the map calls dead (corrected before the method)", int)
    defects_confidence: float = _counter(
        "the map's confidence: steps counted over its warm-up of 2,000 (0..1)")
    defects_gain: int = _counter(
        "1 when a flat-field calibration's per-pixel gain is divided out of every output", int)

    @classmethod
    def from_record(cls, rec: np.void | np.ndarray) -> WorkerCounters:
        """The counters of one :data:`COUNTER_DTYPE` record (a copy)."""
        return cls(**{name: cast(rec[name]) for name, cast in _CASTS.items()})


#: how each counter reads back from its float64 word
_CASTS: dict[str, type] = {
    f.name: int if f.type in ("int", int) else float for f in fields(WorkerCounters)
}

#: the counters as stored in shared memory: one little-endian float64 word per field
COUNTER_DTYPE = np.dtype([(f.name, "<f8") for f in fields(WorkerCounters)])


def counter_meanings() -> dict[str, str]:
    """Each counter's name and meaning (for the API's schema document and the docs)."""
    return {f.name: f.metadata["meaning"] for f in fields(WorkerCounters)}


def display_masks() -> tuple[str, ...]:
    """The names of every mask a registered method declares, in registration order, each
    once, then the defect map's (:data:`DEFECTS_MASK`): ``("coarse", "fine", "motion",
    "defects")`` with the built-in methods."""
    out: list[str] = []
    for name in registry.methods():
        for m in registry.get_method(name).masks:
            if m not in out:
                out.append(m)
    if DEFECTS_MASK not in out:
        out.append(DEFECTS_MASK)
    if len(out) > MAX_MASKS:
        raise ValueError(f"methods declare {len(out)} masks; a frame carries {MAX_MASKS}")
    for m in out:
        if not m.isascii() or not 0 < len(m.encode()) < MASK_NAME_BYTES:
            raise ValueError(f"mask name {m!r}: 1-{MASK_NAME_BYTES - 1} ASCII characters")
    return tuple(out)


#: how the viewer and the PNG/MJPEG renderer show the built-in methods' masks: overlay colour
#: (RGB) and a one-line meaning; a mask of another method gets a colour of :data:`_PALETTE`
MASK_STYLE: dict[str, tuple[tuple[int, int, int], str]] = {
    "coarse": ((47, 123, 255), "pixels the coarse distinction calls dynamic (ISI statistics "
                               "at t)"),
    "fine": ((255, 140, 26), "moving objects found by the fine distinction (MOG + DAISI "
                             "edges)"),
    "motion": ((200, 80, 255), "pixels SNM's spiking neurons call moving"),
    "defects": ((255, 40, 40), "hot and dead pixels found in the stream; each took a "
                               "neighbour's spikes before the method ran"),
}
_PALETTE = ((70, 210, 140), (232, 185, 74), (255, 107, 107), (120, 200, 255))
#: opacity of a mask's colour over the image
MASK_ALPHA = 0.4


def mask_color(name: str) -> tuple[int, int, int]:
    """The overlay colour (RGB, 0..255) of mask ``name``."""
    if name in MASK_STYLE:
        return MASK_STYLE[name][0]
    return _PALETTE[sum(name.encode()) % len(_PALETTE)]


# -- the WebSocket frame message ----------------------------------------------------------------
WS_MAGIC = b"CFSR"
WS_VERSION = 3
WS_HEADER = struct.Struct(f"<4sHHqIHHBBBxfff{METHOD_NAME_BYTES}s")
#: the ``quality`` byte of the header: the tier that made the frame (index into this tuple;
#: "" for a frame of a method without tiers)
QUALITY_TIERS: tuple[str, ...] = ("", "full", "fast")
assert WS_HEADER.size == 64

#: byte offsets of the header's fields, as the viewer reads them (``GET /api/schema``)
WS_OFFSETS = {
    "magic": 0, "version": 4, "header_bytes": 6, "step": 8, "frame_no": 16, "width": 20,
    "height": 22, "mask_flags": 24, "mask_planes": 25, "quality": 26, "gain": 28, "compute_ms": 32,
    "latency_ms": 36, "method": 40,
}


@dataclass
class SlotFrame:
    """One frame as the slot holds it and the hub sends it (``seq``: its sequence number in
    the slot; ``image``: 8-bit display, ``(H, W)``; ``masks``: bool ``(H, W)`` by name)."""

    seq: int
    step: int
    frame_no: int
    width: int
    height: int
    method: str
    gain: float
    t_publish: float
    t_arrival: float
    compute_ms: float
    latency_ms: float
    image: np.ndarray
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    #: the tier that made the frame (:data:`QUALITY_TIERS`; "" for a method without tiers)
    quality: str = ""


def encode_ws_message(f: SlotFrame, mask_names: tuple[str, ...]) -> bytes:
    """One frame as the binary WebSocket message above: the image, then one bit plane per
    name of ``mask_names`` (the slot's, :func:`display_masks`)."""
    n = f.width * f.height
    flags = 0
    parts = []
    for k, name in enumerate(mask_names):
        m = f.masks.get(name)
        if m is not None:
            flags |= 1 << k
            parts.append(np.packbits(m.reshape(-1) != 0, bitorder="little").tobytes())
        else:
            parts.append(bytes((n + 7) // 8))
    head = WS_HEADER.pack(
        WS_MAGIC, WS_VERSION, WS_HEADER.size, f.step, f.frame_no & 0xFFFFFFFF, f.width,
        f.height, flags, len(mask_names), quality_code(f.quality), f.gain, f.compute_ms,
        f.latency_ms,
        f.method.encode("ascii", "replace")[:METHOD_NAME_BYTES],
    )
    return b"".join([head, f.image.tobytes(), *parts])


def quality_code(tier: str | None) -> int:
    """The header's byte for ``tier`` (0 for none or an unknown one)."""
    return QUALITY_TIERS.index(tier) if tier in QUALITY_TIERS else 0


def decode_ws_message(msg: bytes, mask_names: tuple[str, ...]) -> dict[str, Any]:
    """Inverse of :func:`encode_ws_message` (tests and Python clients; ``mask_names`` as
    ``GET /api/schema`` gives them)."""
    (magic, ver, hlen, step, frame_no, w, h, flags, planes, quality, gain, comp, lat,
     name) = WS_HEADER.unpack_from(msg)
    if magic != WS_MAGIC:
        raise ValueError(f"not a CFSR frame message (magic {magic!r})")
    if planes != len(mask_names):
        raise ValueError(f"the message has {planes} mask planes, the schema names "
                         f"{len(mask_names)}")
    n = w * h
    img = np.frombuffer(msg, np.uint8, n, hlen).reshape(h, w)
    nb = (n + 7) // 8
    masks = {}
    for k, nm in enumerate(mask_names):
        if flags & (1 << k):
            raw = np.frombuffer(msg, np.uint8, nb, hlen + n + k * nb)
            masks[nm] = np.unpackbits(raw, bitorder="little")[:n].reshape(h, w).astype(bool)
    return {
        "version": ver, "step": step, "frame_no": frame_no, "width": w, "height": h,
        "gain": gain, "compute_ms": comp, "latency_ms": lat,
        "quality": QUALITY_TIERS[quality] if quality < len(QUALITY_TIERS) else "",
        "method": name.rstrip(b"\0").decode(), "image": img, "masks": masks,
    }


def schema_document(mask_names: tuple[str, ...]) -> dict[str, Any]:
    """What ``GET /api/schema`` returns: the frame message's layout, the mask names in
    plane order with their overlay colours, the heat colour map and the counters."""
    # deferred: a cycle (render imports this module's mask colours)
    from cfsr_live.service.render import HEAT_LUT

    return {
        "ws_version": WS_VERSION,
        "ws_header_bytes": WS_HEADER.size,
        "ws_offsets": WS_OFFSETS,
        "method_name_bytes": METHOD_NAME_BYTES,
        "quality_tiers": list(QUALITY_TIERS),
        "masks": [{"name": m, "color": list(mask_color(m)),
                   "meaning": MASK_STYLE.get(m, ((0, 0, 0), ""))[1]} for m in mask_names],
        "mask_alpha": MASK_ALPHA,
        "heat_lut": HEAT_LUT.reshape(-1).tolist(),
        "counters": counter_meanings(),
    }
