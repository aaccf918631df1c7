"""The USB spike camera as a :class:`~cfsr_live.driver.source.Source` (pyusb, imported lazily).

Reads whole protocol blocks (``docs/protocol.md``) with synchronous bulk transfers **in place**
into one preallocated ``array.array`` (``dev.read(ep, buffer)``, never ``dev.read(ep, size)``),
so the hot loop allocates nothing. Block sizes follow the kernel's rules: a multiple of the
1024-byte packet and at most 16 MiB per read (256 frames of 12,500 bytes + the header packet
= 3,201,024 bytes).

Recovery, all counted in :meth:`UsbCameraSource.counters`:

* lost data: from the 64-bit frame index in every header (``lost_frames``), whatever the cause
  (device FIFO overflow, a damaged block we discarded, the time the camera was unplugged);
* timeout (errno 110): counted, reading continues;
* stall (errno 32): the halt is cleared (no transfer is in flight: reads are synchronous);
* babble/overflow (errno 75), bad header CRC, short block: the stream may be misaligned, so
  the next read is scanned for a header on a packet boundary and re-aligned (``resyncs``);
* payload CRC mismatch: the block is dropped;
* unplug (errno 19 or 5): the device is released and re-opened with exponential backoff
  while :meth:`read_block` keeps returning ``None``; the service stays up.
"""

from __future__ import annotations

import array
import errno
import logging
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from cfsr.layout import Layout
from cfsr_live.driver import protocol as P
from cfsr_live.driver.source import (
    Block,
    BlockFlags,
    CameraControl,
    Source,
    SourceCounters,
    SourceDisconnected,
    SourceError,
    SourceInfo,
    SourceState,
)

__all__ = ["UsbCameraSource", "UsbCounters", "DISCONNECT_ERRNOS"]

log = logging.getLogger("cfsr.usb")

#: errors that mean the device went away (the real kernel gives either, timing-dependent)
DISCONNECT_ERRNOS = (errno.ENODEV, errno.EIO)
_LIBUSB_NO_DEVICE, _LIBUSB_IO = -4, -1


class _CameraControl(CameraControl):
    def __init__(self, src: UsbCameraSource) -> None:
        self._s = src

    def device_info(self) -> dict[str, Any]:
        d = self._s._dev_info
        return {} if d is None else dict(d.__dict__)

    def device_status(self) -> dict[str, Any]:
        return dict(self._s._status_cache)


@dataclass(frozen=True)
class UsbCounters(SourceCounters):
    """The camera's counters: frames (delivered, lost on the link) and the link's events,
    each a count since the source was made (the module's docstring says what each recovers
    from)."""

    lost_frames: int | None = 0  #: frames missing from the header indices (a camera has a link)
    blocks: int = 0  #: protocol blocks delivered
    timeouts: int = 0  #: bulk reads that timed out (errno 110)
    stalls: int = 0  #: halts cleared (errno 32)
    overflows: int = 0  #: babble/overflow reads (errno 75)
    short_blocks: int = 0  #: blocks shorter than their header says
    crc_errors: int = 0  #: blocks dropped for a payload CRC mismatch
    bad_headers: int = 0  #: reads whose header did not parse or check
    resyncs: int = 0  #: re-alignments on a header found in a read
    disconnects: int = 0  #: times the device went away (errno 19 / 5)
    reconnects: int = 0  #: sessions after the first
    connect_failures: int = 0  #: attempts to open the device that failed
    errors: int = 0  #: other USB errors
    sessions: int = 0  #: successful opens


class UsbCameraSource(Source):
    """The USB camera.

    Parameters
    ----------
    vid, pid : int
        USB ids (defaults: the emulator's placeholder ids, ``cfsr_live.driver.protocol``).
    serial : str, optional
        Only open the camera with this serial number.
    frames_per_block : int
        Frames per block requested with START (a multiple of the packet alignment: 256 for
        400 x 250 frames).
    read_timeout_ms : int
        Timeout of one bulk read.
    backend : pyusb backend, optional
        For tests (``cfsr_live.replay.fake_usb.FakeUsbBackend``); default libusb.
    backoff : (float, float)
        First and largest delay between reconnection attempts, seconds.
    """

    def __init__(
        self,
        vid: int = P.DEFAULT_VID,
        pid: int = P.DEFAULT_PID,
        *,
        serial: str | None = None,
        frames_per_block: int = 256,
        read_timeout_ms: int = 1000,
        backend: Any = None,
        backoff: tuple[float, float] = (0.1, 2.0),
    ) -> None:
        super().__init__()
        self.vid, self.pid, self.serial = int(vid), int(pid), serial
        self.want_fpb = int(frames_per_block)
        self.read_timeout_ms = int(read_timeout_ms)
        self.backend = backend
        self.backoff = backoff
        self.info = SourceInfo(
            kind="usb",
            name=f"USB camera {self.vid:04x}:{self.pid:04x}",
            layout=Layout(),
            max_block_frames=self.want_fpb,
        )
        self._facilities = {CameraControl: _CameraControl(self)}
        self._usb = None
        self._dev = None
        self._ep = P.EP_IN
        self._dev_info: P.DeviceInfo | None = None
        self._buf: array.array | None = None
        self._view: np.ndarray | None = None
        self.block_bytes = 0
        self.fpb = 0
        self._expect: int | None = None
        self._resync = False
        self._next_attempt = 0.0
        self._delay = backoff[0]
        self._status_cache: dict[str, Any] = {"connected": False}
        self._status_at = 0.0
        self._opened = False
        self._c = UsbCounters()

    # -- lifecycle -----------------------------------------------------------------------------
    def open(self) -> None:
        try:
            import usb.core  # noqa: F401
        except ImportError as exc:
            raise SourceError(f"pyusb is not installed ({exc})") from exc
        self._opened = True
        self._expect = None
        try:
            self._connect()
        except SourceError as exc:
            # keep the service up: read_block retries with backoff
            self.last_error = str(exc)
            self._schedule_retry()

    def close(self) -> None:
        self._opened = False
        if self._dev is not None:
            try:
                self._ctrl_out(P.REQ_STOP, 0)
            except Exception:  # noqa: BLE001 - the device may be gone
                pass
        self._release()
        self.state = SourceState.CLOSED

    def counters(self) -> UsbCounters:
        return self._c

    def _count(self, **add: int) -> None:
        """Add ``add`` (field name -> frames or events) to the counters: a new frozen record,
        so a reader in another thread sees a block's figures together or not at all."""
        c = self._c
        self._c = replace(c, **{k: getattr(c, k) + n for k, n in add.items()})

    # -- connection ------------------------------------------------------------------------------
    def _find(self):
        import usb.core

        kw: dict[str, Any] = {"idVendor": self.vid, "idProduct": self.pid}
        if self.backend is not None:
            kw["backend"] = self.backend
        if self.serial is not None:
            want = self.serial
            kw["custom_match"] = lambda d: _serial_of(d) == want
        return usb.core.find(**kw)

    def _connect(self) -> None:
        import usb.core
        import usb.util

        self._usb = usb
        self.state = SourceState.OPENING
        try:
            try:
                dev = self._find()
            except usb.core.NoBackendError as exc:
                raise SourceError(
                    f"no libusb backend for pyusb ({exc}); install libusb-1.0-0"
                ) from exc
            if dev is None:
                raise SourceDisconnected(
                    f"no USB device {self.vid:04x}:{self.pid:04x}"
                    + (f" with serial {self.serial}" if self.serial else "")
                )
            try:
                if dev.is_kernel_driver_active(0):
                    dev.detach_kernel_driver(0)
            except (NotImplementedError, usb.core.USBError):
                pass
            dev.set_configuration()
            usb.util.claim_interface(dev, 0)
            self._dev = dev
            intf = dev.get_active_configuration()[(0, 0)]
            ep = usb.util.find_descriptor(
                intf,
                custom_match=lambda e: usb.util.endpoint_direction(e.bEndpointAddress)
                == usb.util.ENDPOINT_IN
                and usb.util.endpoint_type(e.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK,
            )
            if ep is None:
                raise SourceError("the device has no bulk IN endpoint")
            self._ep = ep.bEndpointAddress
            packet = int(ep.wMaxPacketSize)
            raw = dev.ctrl_transfer(P.RT_VENDOR_IN, P.REQ_GET_INFO, 0, 0, 64, 1000)
            info = P.parse_info(raw)
            if info.version != P.VERSION:
                raise SourceError(f"device speaks protocol {info.version}, we speak {P.VERSION}")
            layout = Layout(
                width=info.width,
                height=info.height,
                head_cols=info.stored_width - info.width,
                flipud=bool(info.layout_flags & P.LF_FLIPUD),
                fliplr=bool(info.layout_flags & P.LF_FLIPLR),
            )
            if layout.frame_bytes != info.frame_bytes:
                raise SourceError(
                    f"device reports {info.frame_bytes}-byte frames for {info.width} x "
                    f"{info.height}, expected {layout.frame_bytes}"
                )
            align = P.frame_alignment(info.frame_bytes, packet)
            fpb = max(align, self.want_fpb // align * align)
            bb = P.block_bytes(fpb, info.frame_bytes, packet)
            while bb > min(info.max_block_bytes, P.MAX_TRANSFER_BYTES) and fpb > align:
                fpb -= align
                bb = P.block_bytes(fpb, info.frame_bytes, packet)
            if bb != self.block_bytes:
                self._buf = array.array("B", bytes(bb))  # allocated once per block size
                self._view = np.frombuffer(self._buf, np.uint8)
            self.block_bytes, self.fpb = bb, fpb
            old = self.info
            self.info = SourceInfo(
                kind="usb",
                name=f"USB camera {self.vid:04x}:{self.pid:04x} ({info.serial})",
                layout=layout,
                rate_hz=float(info.rate_hz),
                max_block_frames=fpb,
                serial=info.serial,
                meta=dict(old.meta),
            )
            self._dev_info = info
            self._ctrl_out(P.REQ_START, fpb)
        except usb.core.USBError as exc:
            self._release()
            self._count(connect_failures=1)
            raise SourceDisconnected(f"cannot open the USB camera: {exc}") from exc
        except SourceError:
            self._release()
            self._count(connect_failures=1)
            raise
        self._count(sessions=1, reconnects=1 if self._c.sessions else 0)
        self._resync = False
        self._delay = self.backoff[0]
        self.state = SourceState.STREAMING
        self.last_error = None
        self._status_cache = {"connected": True}
        log.info("USB camera streaming: %d frames per block, %d bytes", fpb, bb)

    def _release(self) -> None:
        dev, self._dev = self._dev, None
        if dev is not None and self._usb is not None:
            try:
                self._usb.util.release_interface(dev, 0)
            except Exception:  # noqa: BLE001
                pass
            try:
                self._usb.util.dispose_resources(dev)
            except Exception:  # noqa: BLE001
                pass
        self._status_cache = {"connected": False}

    def _schedule_retry(self) -> None:
        self.state = SourceState.BACKOFF
        self._next_attempt = time.monotonic() + self._delay
        self._delay = min(self.backoff[1], self._delay * 2)

    def _disconnected(self, exc: Exception) -> None:
        self._count(disconnects=1)
        self.last_error = f"camera disconnected: {exc}"
        log.warning("%s; reconnecting", self.last_error)
        self._release()
        self.state = SourceState.DISCONNECTED
        self._delay = self.backoff[0]
        self._schedule_retry()

    def _ctrl_out(self, req: int, value: int) -> None:
        self._dev.ctrl_transfer(P.RT_VENDOR_OUT, req, value, 0, None, 1000)

    # -- reading ---------------------------------------------------------------------------
    def read_block(self, timeout: float = 0.5) -> Block | None:
        if not self._opened:
            return None
        if self._dev is None:
            wait = self._next_attempt - time.monotonic()
            if wait > 0:
                time.sleep(min(wait, max(0.0, timeout)))
                return None
            try:
                self._connect()
            except SourceError as exc:
                self.last_error = str(exc)
                self._schedule_retry()
                return None
        usb = self._usb
        ms = max(20, min(self.read_timeout_ms, int(timeout * 1000) or self.read_timeout_ms))
        self._poll_status()
        try:
            n = self._dev.read(self._ep, self._buf, ms)
        except usb.core.USBTimeoutError:
            self._count(timeouts=1)
            return None
        except usb.core.USBError as exc:
            return self._on_error(exc)
        return self._parse(n)

    def _on_error(self, exc) -> None:
        code = getattr(exc, "errno", None)
        be = getattr(exc, "backend_error_code", None)
        if code in DISCONNECT_ERRNOS or be in (_LIBUSB_NO_DEVICE, _LIBUSB_IO):
            self._disconnected(exc)
            return None
        if code == errno.EPIPE:
            self._count(stalls=1)
            try:
                self._dev.clear_halt(self._ep)
            except self._usb.core.USBError as e2:
                if getattr(e2, "errno", None) in DISCONNECT_ERRNOS:
                    self._disconnected(e2)
            return None
        if code == errno.EOVERFLOW:
            self._count(overflows=1)
            self._resync = True
            return None
        if code == errno.ENOMEM:
            raise SourceError(
                f"the kernel refused a {self.block_bytes}-byte read (usbfs memory limit): "
                "use fewer frames per block"
            )
        self._count(errors=1)
        self.last_error = str(exc)
        return None

    def _poll_status(self) -> None:
        now = time.monotonic()
        if now - self._status_at < 1.0 or self._dev is None:
            return
        self._status_at = now
        try:
            raw = self._dev.ctrl_transfer(P.RT_VENDOR_IN, P.REQ_GET_STATUS, 0, 0, 32, 200)
            st = P.parse_status(raw)
            self._status_cache = {"connected": True, **st.__dict__}
        except Exception as exc:  # noqa: BLE001 - informational only
            self._status_cache = {"connected": True, "error": str(exc)}

    def _read_exact(self, nbytes: int) -> int:
        """Read ``nbytes`` (a multiple of the packet) into a scratch buffer; returns count."""
        scratch = array.array("B", bytes(nbytes))
        got = self._dev.read(self._ep, scratch, self.read_timeout_ms)
        self._scratch = np.frombuffer(scratch, np.uint8)
        return got

    def _find_header(self, v: np.ndarray, n: int) -> int | None:
        for off in range(P.PACKET_BYTES, n - 63, P.PACKET_BYTES):
            if bytes(v[off : off + 4]) == P.MAGIC and P.parse_header(v[off : off + 64]):
                return off
        return None

    def _parse(self, n: int) -> Block | None:
        v = self._view
        hdr = P.parse_header(v[:64]) if n >= 64 else None
        if hdr is None or hdr.block_bytes != self.block_bytes:
            if not self._resync:
                self._count(bad_headers=1)
            self._resync = False
            off = self._find_header(v, n)
            if off is None:
                self._resync = True  # keep looking in the next read
                return None
            # the stream is misaligned by ``off`` bytes: complete the block and carry on
            self._count(resyncs=1)
            keep = n - off
            v[:keep] = v[off:n].copy()
            need = self.block_bytes - keep
            try:
                got = self._read_exact(need)
            except self._usb.core.USBError as exc:
                return self._on_error(exc)
            if got != need:
                self._resync = True
                return None
            v[keep : keep + need] = self._scratch[:need]
            n = self.block_bytes
            hdr = P.parse_header(v[:64])
            if hdr is None:
                return None
        self._resync = False
        lay = self.info.layout
        if hdr.frame_bytes != lay.frame_bytes or hdr.frame_count > hdr.frames_per_block:
            self._count(bad_headers=1)
            return None
        plen = hdr.frame_count * hdr.frame_bytes
        if n < P.HEADER_BYTES + plen:
            self._count(short_blocks=1)
            return None
        payload = v[P.HEADER_BYTES : P.HEADER_BYTES + plen]
        if P.payload_crc32(payload) != hdr.payload_crc:
            self._count(crc_errors=1)
            return None
        flags = BlockFlags.NONE
        lost = 0
        first = hdr.first_index
        if self._expect is not None:
            if first > self._expect:
                lost = first - self._expect
                flags |= BlockFlags.LOSS
                self._count(lost_frames=lost)
            elif first < self._expect:
                flags |= BlockFlags.DISCONTINUITY  # the device restarted its counter
        else:
            flags |= BlockFlags.DISCONTINUITY
        self._expect = first + hdr.frame_count
        self._count(blocks=1, frames_delivered=hdr.frame_count)
        return Block(
            index=first,
            data=payload.reshape(hdr.frame_count, hdr.frame_bytes),
            flags=flags,
            lost_before=lost,
        )


def _serial_of(dev) -> str | None:
    try:
        return dev.serial_number
    except Exception:  # noqa: BLE001
        return None
