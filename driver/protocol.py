"""Our USB wire protocol for spike cameras (specified in ``docs/protocol.md``).

Pure functions and constants only: the driver (:mod:`cfsr_live.driver.usb`) and the camera emulator
(:mod:`cfsr_live.replay.camera_model`) both use them, so they cannot disagree.

A stream is a sequence of fixed-size *blocks* on bulk IN endpoint 0x81. Each block is one
1024-byte header packet followed by ``frames_per_block`` packed frames (the ``.dat`` byte
layout), zero-padded to a whole number of 1024-byte packets::

    block_bytes = 1024 + ceil(frames_per_block * frame_bytes / 1024) * 1024   (<= 16 MiB)

Header (little-endian, first 64 bytes of the header packet, the rest zero)::

    0   4s  magic b"SPKB"
    4   u16 protocol version (1)
    6   u16 header bytes (1024)
    8   u64 index of the first frame (device frame counter since power-on)
    16  u32 frame count in this block (<= frames_per_block)
    20  u32 frames per block (as configured by START)
    24  u16 width     26 u16 height     28 u16 stored width     30 u16 layout flags
    32  u32 frame bytes
    36  u32 block flags (BF_*)
    40  u32 block bytes
    44  u32 CRC-32 of the payload (frame_count * frame_bytes bytes, zlib polynomial)
    48  u64 frames the device dropped so far (FIFO overflow), cumulative
    56  u32 block sequence number (mod 2^32)
    60  u32 CRC-32 of bytes 0..59

The payload CRC is the driver's largest cost per block (``service/benchmarks.py``): the
standard library's ``zlib.crc32`` runs at ~7 GB/s here (0.46 ms of a 3.2 MB block, two
thirds of the driver's time), the carry-less-multiply CRC of ISA-L or zlib-ng at ~39 GB/s.
:func:`payload_crc32` uses the first of ``isal``, ``zlib_ng`` and ``zlib`` that imports (same
polynomial, same values; :data:`CRC32_IMPL` names it).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import astuple, dataclass

__all__ = [
    "MAGIC",
    "VERSION",
    "HEADER_BYTES",
    "PACKET_BYTES",
    "MAX_TRANSFER_BYTES",
    "DEFAULT_VID",
    "DEFAULT_PID",
    "EP_IN",
    "REQ_GET_INFO",
    "REQ_START",
    "REQ_STOP",
    "REQ_GET_STATUS",
    "RT_VENDOR_IN",
    "RT_VENDOR_OUT",
    "BF_DEVICE_OVERFLOW",
    "BF_SESSION_START",
    "LF_FLIPUD",
    "LF_FLIPLR",
    "CRC32_IMPL",
    "BlockHeader",
    "DeviceInfo",
    "DeviceStatus",
    "block_bytes",
    "frame_alignment",
    "pack_header",
    "payload_crc32",
    "parse_header",
    "pack_info",
    "parse_info",
    "pack_status",
    "parse_status",
]

MAGIC = b"SPKB"
VERSION = 1
HEADER_BYTES = 1024
PACKET_BYTES = 1024  # SuperSpeed bulk wMaxPacketSize
MAX_TRANSFER_BYTES = 16 * 1024 * 1024  # usbfs_memory_mb default: one read must stay below
#: placeholder ids of the emulated camera (the real camera's ids are passed with --vid/--pid)
DEFAULT_VID, DEFAULT_PID = 0x1D6B, 0x5350
EP_IN = 0x81

# vendor control requests, recipient interface 0
RT_VENDOR_OUT = 0x41  # host-to-device | vendor | interface
RT_VENDOR_IN = 0xC1  # device-to-host | vendor | interface
REQ_GET_INFO = 0x01  # IN, 64 bytes: DeviceInfo
REQ_START = 0x02  # OUT, wValue = frames per block; flushes the FIFO, starts streaming
REQ_STOP = 0x03  # OUT
REQ_GET_STATUS = 0x04  # IN, 32 bytes: DeviceStatus

# block flags
BF_DEVICE_OVERFLOW = 0x1  # the FIFO overflowed before this block: frames were dropped
BF_SESSION_START = 0x2  # first block after START
# layout flags
LF_FLIPUD, LF_FLIPLR = 0x1, 0x2


def _fast_crc32():
    try:
        from isal.isal_zlib import crc32

        return crc32, "isal"
    except ImportError:
        pass
    try:
        from zlib_ng.zlib_ng import crc32

        return crc32, "zlib_ng"
    except ImportError:
        return zlib.crc32, "zlib"


#: CRC-32 (zlib polynomial) of a buffer, optionally continuing from ``value``: the fastest
#: implementation installed (module notes)
payload_crc32, CRC32_IMPL = _fast_crc32()

# Each message's dataclass lists its fields in wire order (``version`` last: it travels in the
# fixed part): pack_* and parse_* take them in that order, so the order is written once.
_HDR = struct.Struct("<4sHHQIIHHHHIIIIQI")
_HDR_CRC = struct.Struct("<I")
assert _HDR.size == 60
_INFO = struct.Struct("<4sHHHHHHIIIHBB16s8sI4x")
assert _INFO.size == 64
_STATUS = struct.Struct("<BBHIQQI4x")
assert _STATUS.size == 32


@dataclass(frozen=True)
class BlockHeader:
    """One block's header; fields in wire order after (magic, version, header bytes)."""

    first_index: int
    frame_count: int
    frames_per_block: int
    width: int
    height: int
    stored_width: int
    layout_flags: int
    frame_bytes: int
    flags: int
    block_bytes: int
    payload_crc: int
    device_dropped: int
    sequence: int
    version: int = VERSION


def frame_alignment(frame_bytes: int, packet: int = PACKET_BYTES) -> int:
    """Smallest number of frames whose bytes are a whole number of packets (256 for 12,500)."""
    from math import gcd

    return packet // gcd(frame_bytes, packet)


def block_bytes(frames_per_block: int, frame_bytes: int, packet: int = PACKET_BYTES) -> int:
    """Bytes of one block: header packet + payload padded to whole packets."""
    if frames_per_block < 1:
        raise ValueError(f"frames_per_block must be >= 1, got {frames_per_block}")
    payload = frames_per_block * frame_bytes
    n = HEADER_BYTES + -(-payload // packet) * packet
    if n > MAX_TRANSFER_BYTES:
        raise ValueError(
            f"{frames_per_block} frames of {frame_bytes} bytes make a {n}-byte block; one read "
            f"must stay <= {MAX_TRANSFER_BYTES} bytes (usbfs limit)"
        )
    return n


def pack_header(h: BlockHeader) -> bytes:
    """64 header bytes (the caller pads the packet to 1024 bytes with zeros)."""
    *head, sequence = astuple(h)[:-1]  # all but version
    body = _HDR.pack(MAGIC, VERSION, HEADER_BYTES, *head, sequence & 0xFFFFFFFF)
    return body + _HDR_CRC.pack(zlib.crc32(body))


def parse_header(buf) -> BlockHeader | None:
    """Parse 64 header bytes; None if the magic, version or header CRC is wrong."""
    mv = memoryview(buf)
    if len(mv) < 64 or bytes(mv[:4]) != MAGIC:
        return None
    body = mv[:60]
    (crc,) = _HDR_CRC.unpack_from(mv, 60)
    if zlib.crc32(body) != crc:
        return None
    f = _HDR.unpack_from(mv, 0)
    if f[1] != VERSION or f[2] != HEADER_BYTES:
        return None
    return BlockHeader(*f[3:], version=f[1])


@dataclass(frozen=True)
class DeviceInfo:
    """The GET_INFO reply; fields in wire order (a reserved word after ``ep_in``)."""

    width: int
    height: int
    stored_width: int
    layout_flags: int
    frame_bytes: int
    rate_hz: int
    max_block_bytes: int
    packet_bytes: int
    ep_in: int
    serial: str
    firmware: str
    default_frames_per_block: int
    version: int = VERSION


def pack_info(d: DeviceInfo) -> bytes:
    *numbers, serial, firmware, fpb = astuple(d)[:-1]  # all but version
    return _INFO.pack(
        b"SPKI", VERSION, 0, *numbers, 0, serial.encode()[:16], firmware.encode()[:8], fpb
    )


def parse_info(buf) -> DeviceInfo:
    b = bytes(buf)
    if len(b) < _INFO.size or b[:4] != b"SPKI":
        raise ValueError(f"not a device info reply ({len(b)} bytes, starts {b[:4]!r})")
    f = _INFO.unpack_from(b)
    serial, firmware = (s.rstrip(b"\0").decode(errors="replace") for s in f[13:15])
    return DeviceInfo(*f[3:12], serial, firmware, f[15], version=f[1])


@dataclass(frozen=True)
class DeviceStatus:
    """The GET_STATUS reply; fields in wire order (two reserved fields after ``streaming``)."""

    streaming: bool
    frames_per_block: int
    next_index: int
    dropped_total: int
    fifo_frames: int


def pack_status(s: DeviceStatus) -> bytes:
    streaming, *counts = astuple(s)
    return _STATUS.pack(int(streaming), 0, 0, *counts)


def parse_status(buf) -> DeviceStatus:
    b = bytes(buf)
    if len(b) < _STATUS.size:
        raise ValueError(f"status reply too short ({len(b)} bytes)")
    f = _STATUS.unpack_from(b)
    return DeviceStatus(bool(f[0]), *f[3:])
