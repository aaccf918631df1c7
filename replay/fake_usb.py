"""A test-only pyusb backend (``usb.backend.IBackend``) serving the emulated camera.

``usb.core.find(backend=FakeUsbBackend(model))`` returns a genuine ``usb.core.Device``: pyusb's
own code runs (configuration, interface claim, descriptor parsing, ``dev.read`` into a
caller's ``array.array``); only the layer below pyusb (normally libusb) is emulated, by
:class:`cfsr_live.replay.camera_model.CameraModel`. Fast unit tests of the driver logic use it; the
umockdev tier (:mod:`cfsr_live.replay.umockdev_camera`) runs the real libusb instead. Importing this
module needs pyusb (it is test tooling; the driver itself imports pyusb lazily).

:class:`PreloadedUsbBackend` is the same device with its bulk stream built once in memory:
each read is one copy of a ready block plus a fresh 64-byte header, so a benchmark of it
measures the host side (pyusb, the driver, the ring), not the emulator
(``service/benchmarks.py``).
"""

from __future__ import annotations

import ctypes
import dataclasses
import errno
import time
from types import SimpleNamespace

import numpy as np
import usb.backend

from cfsr_live.driver import protocol as P
from cfsr_live.replay.camera_model import CameraModel

__all__ = ["FakeUsbBackend", "PreloadedUsbBackend", "STRINGS"]

STRINGS = {1: "CFSR emulated", 2: "Spike Camera 400x250 (emulated)", 3: "EMU00001"}


def _err(code: int, msg: str):
    import usb.core

    libusb_codes = {errno.ENODEV: -4, errno.EPIPE: -9, errno.EOVERFLOW: -8, errno.EIO: -1,
                    errno.ENOMEM: -11}
    return usb.core.USBError(msg, libusb_codes.get(code, -99), code)


class FakeUsbBackend(usb.backend.IBackend):
    """Duck-typed pyusb backend; see the module notes."""

    def __init__(self, model: CameraModel) -> None:
        import usb.util

        self.model = model
        self.claimed: set[int] = set()
        self.config = 0
        self.reads = 0
        sp = usb.util.SPEED_SUPER
        self._dev = SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0320, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=9, idVendor=P.DEFAULT_VID,
            idProduct=P.DEFAULT_PID, bcdDevice=0x0100, iManufacturer=1, iProduct=2,
            iSerialNumber=3, bNumConfigurations=1, address=2, bus=1, port_number=1,
            port_numbers=(1,), speed=sp,
        )
        self._cfg = SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=9 + 9 + 7 + 6, bNumInterfaces=1,
            bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80, bMaxPower=112,
            extra_descriptors=[],
        )
        self._intf = SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
            bNumEndpoints=1, bInterfaceClass=0xFF, bInterfaceSubClass=0, bInterfaceProtocol=0,
            iInterface=0, extra_descriptors=[],
        )
        self._ep = SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=P.EP_IN, bmAttributes=2,
            wMaxPacketSize=P.PACKET_BYTES, bInterval=0, bRefresh=0, bSynchAddress=0,
            extra_descriptors=[6, 0x30, 15, 0, 0, 0],
        )

    def _check(self) -> None:
        if self.model.unplugged():
            raise _err(errno.ENODEV, "No such device (it may have been disconnected)")

    # enumeration and descriptors
    def enumerate_devices(self):
        yield "fake-spike-camera"

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        return self._dev

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(config)
        return self._cfg

    def get_interface_descriptor(self, dev, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError((intf, alt, config))
        return self._intf

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if ep != 0:
            raise IndexError(ep)
        return self._ep

    # handles
    def open_device(self, dev):
        return SimpleNamespace(dev=dev)

    def close_device(self, dev_handle):
        pass

    def set_configuration(self, dev_handle, config_value):
        self._check()
        self.config = config_value

    def get_configuration(self, dev_handle):
        self._check()
        return self.config

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        self._check()

    def claim_interface(self, dev_handle, intf):
        self._check()
        self.claimed.add(intf)

    def release_interface(self, dev_handle, intf):
        self.claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def detach_kernel_driver(self, dev_handle, intf):
        pass

    def attach_kernel_driver(self, dev_handle, intf):
        pass

    def clear_halt(self, dev_handle, ep):
        self._check()
        self.model.clear_halt()

    def reset_device(self, dev_handle):
        self._check()

    # transfers
    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        import usb.core

        self._check()
        if ep != P.EP_IN or intf not in self.claimed:
            raise _err(errno.EPIPE, "Pipe error")
        addr, count = buff.buffer_info()
        n = count * buff.itemsize
        if n > P.MAX_TRANSFER_BYTES:
            raise _err(errno.ENOMEM, "Insufficient memory")
        deadline = time.monotonic() + (timeout or 1000) / 1000.0
        self.reads += 1
        while True:
            r = self.model.bulk_in(addr, n)
            if r is not None:
                status, got = r
                if status == 0:
                    return got
                if status in (-errno.ESHUTDOWN, -errno.ENODEV):
                    raise _err(errno.ENODEV, "No such device (it may have been disconnected)")
                if status == -errno.EPIPE:
                    raise _err(errno.EPIPE, "Pipe error")
                if status == -errno.EOVERFLOW:
                    raise _err(errno.EOVERFLOW, "Overflow")
                raise _err(errno.EIO, "Input/Output Error")  # -EPROTO and the rest, as libusb
            left = deadline - time.monotonic()
            if left <= 0:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            time.sleep(max(0.0, min(left, self.model.next_ready_in(), 0.005)))
            self._check()

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        raise _err(errno.EPIPE, "Pipe error")

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        self._check()
        m = self.model
        if bmRequestType == 0x80 and bRequest == 6 and (wValue >> 8) == 3:
            idx = wValue & 0xFF
            if idx == 0:
                payload = bytes([4, 3, 0x09, 0x04])
            else:
                s = STRINGS[idx].encode("utf-16-le")
                payload = bytes([2 + len(s), 3]) + s
            return self._copy_in(data, payload)
        if bmRequestType == P.RT_VENDOR_IN:
            try:
                payload = m.control_in(bRequest, wValue, wIndex, len(data) * data.itemsize)
            except ValueError as exc:
                raise _err(errno.EPIPE, f"Pipe error ({exc})") from None
            return self._copy_in(data, payload)
        if bmRequestType == P.RT_VENDOR_OUT:
            try:
                m.control_out(bRequest, wValue, wIndex, bytes(data))
            except ValueError as exc:
                raise _err(errno.EPIPE, f"Pipe error ({exc})") from None
            return len(data) * data.itemsize
        if bmRequestType & 0x80:
            return 0
        return len(data) * data.itemsize

    @staticmethod
    def _copy_in(data, payload: bytes) -> int:
        n = min(len(payload), len(data) * data.itemsize)
        addr, _ = data.buffer_info()
        ctypes.memmove(addr, payload, n)
        return n


class PreloadedUsbBackend(FakeUsbBackend):
    """:class:`FakeUsbBackend` whose bulk stream is ``blocks`` blocks built once, in memory.

    Control requests go to the model as in :class:`FakeUsbBackend`. After ``START``, the
    first read builds ``blocks`` consecutive blocks with the model (unpaced); from then on a
    read of one block copies the next of them into the caller's buffer (one ``memmove``, what
    the kernel's copy to user memory costs on a real host) and writes a fresh header into it
    (the device's frame counter keeps counting; payloads repeat every ``blocks`` blocks). The
    copy's time is summed in :attr:`copy_s` so a benchmark can tell it apart.

    Only whole-block reads are served and faults are not emulated: it exists to measure the
    host side with no emulator in the loop.
    """

    def __init__(self, model: CameraModel, *, blocks: int = 16) -> None:
        super().__init__(model)
        if blocks < 1:
            raise ValueError(f"blocks must be >= 1, got {blocks}")
        self.n_blocks = int(blocks)
        self._stream: np.ndarray | None = None
        self._headers: list[P.BlockHeader] = []
        self._first = 0  # device index of the first block built
        self.served = 0  # blocks served since the stream was built
        self.copy_s = 0.0

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        r = super().ctrl_transfer(dev_handle, bmRequestType, bRequest, wValue, wIndex, data,
                                  timeout)
        if bmRequestType == P.RT_VENDOR_OUT and bRequest in (P.REQ_START, P.REQ_STOP):
            self._stream = None  # START fixes the block size: build again at the next read
        return r

    def _build(self) -> None:
        m = self.model
        bb = m.block_bytes
        stream = np.empty((self.n_blocks, bb), np.uint8)
        headers = []
        self._first = m.next_index
        for k in range(self.n_blocks):
            r = m.bulk_in(stream[k].ctypes.data, bb)
            if r != (0, bb):
                raise RuntimeError(f"the model did not deliver a whole block ({r})")
            h = P.parse_header(stream[k, :64])
            assert h is not None
            headers.append(h)
        self._stream, self._headers, self.served = stream, headers, 0

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        if ep != P.EP_IN or intf not in self.claimed:
            raise _err(errno.EPIPE, "Pipe error")
        if self._stream is None:
            if not self.model.streaming:
                return super().bulk_read(dev_handle, ep, intf, buff, timeout)
            self._build()
        stream = self._stream
        addr, count = buff.buffer_info()
        n = count * buff.itemsize
        bb = stream.shape[1]
        if n != bb:
            raise _err(errno.EIO, f"the preloaded stream serves {bb}-byte reads, not {n}")
        k = self.served % self.n_blocks
        t0 = time.perf_counter()
        ctypes.memmove(addr, stream[k].ctypes.data, bb)
        self.copy_s += time.perf_counter() - t0
        if self.served >= self.n_blocks:  # a later lap: the device's counter moved on
            h = self._headers[k]
            lap = self.served // self.n_blocks
            hdr = P.pack_header(dataclasses.replace(
                h, first_index=h.first_index + lap * self.n_blocks * h.frame_count,
                sequence=h.sequence + lap * self.n_blocks, flags=0))
            ctypes.memmove(addr, hdr, len(hdr))
        self.served += 1
        self.reads += 1
        return bb
