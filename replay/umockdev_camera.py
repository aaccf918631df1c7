"""The USB camera emulator for umockdev: the real libusb and the real pyusb talk to it.

umockdev's preload library (``umockdev-wrapper python ...``) redirects ``/sys``, ``/dev`` and
udev into a test bed; the emulated node ``/dev/bus/usb/001/002`` forwards every usbdevfs
``ioctl`` to :class:`UsbdevfsCamera`, which completes URBs in place (same address space) from
:class:`cfsr_live.replay.camera_model.CameraModel`. libusb enumerates it through sysfs/udev, parses
its descriptors, claims the interface and submits/reaps URBs exactly as with a real device.

Driven through ctypes only (``libumockdev.so.0``, ``libgobject-2.0.so.0``), no PyGObject.
Struct layouts and ioctl numbers are x86-64 (``<linux/usbdevice_fs.h>``). Adapted from the
project's emulation notes (``notes/usb-emulation.md``, Appendix A), which also list the gotchas
handled here (DISCARDURB's argument is the URB pointer; pace by blocking in REAP instead of
returning EAGAIN in a loop; catch every exception and complete with EIO).

Usage (the process must run under ``umockdev-wrapper``)::

    model = CameraModel(read_dat("x.dat"), paced=True)
    with EmulatedCamera(model) as cam:
        dev = usb.core.find(idVendor=cam.vid, idProduct=cam.pid)
"""

from __future__ import annotations

import ctypes
import errno
import os
import struct
import sys
import threading
import time
import traceback
from collections import deque
from ctypes import (
    CFUNCTYPE,
    POINTER,
    Structure,
    c_char_p,
    c_int,
    c_long,
    c_size_t,
    c_ubyte,
    c_ulong,
    c_void_p,
)

from cfsr_live.driver import protocol as P
from cfsr_live.replay.camera_model import CameraModel

__all__ = ["EmulatedCamera", "UsbdevfsCamera", "available", "preloaded", "STRINGS"]

# usbdevfs ioctl numbers (x86_64)
USBDEVFS_SETINTERFACE = 0x80085504
USBDEVFS_SETCONFIGURATION = 0x80045505
USBDEVFS_GETDRIVER = 0x41045508
USBDEVFS_SUBMITURB = 0x8038550A
USBDEVFS_DISCARDURB = 0x0000550B
USBDEVFS_REAPURB = 0x4008550C
USBDEVFS_REAPURBNDELAY = 0x4008550D
USBDEVFS_CLAIMINTERFACE = 0x8004550F
USBDEVFS_RELEASEINTERFACE = 0x80045510
USBDEVFS_IOCTL = 0xC0105512
USBDEVFS_RESET = 0x00005514
USBDEVFS_CLEAR_HALT = 0x80045515
USBDEVFS_GET_CAPABILITIES = 0x8004551A
USBDEVFS_DISCONNECT_CLAIM = 0x8108551B
CAP_ZERO_PACKET, CAP_BULK_CONTINUATION, CAP_NO_PACKET_SIZE_LIM = 0x01, 0x02, 0x04
CAP_BULK_SCATTER_GATHER, CAP_REAP_AFTER_DISCONNECT = 0x08, 0x10
URB_TYPE_CONTROL, URB_TYPE_BULK = 2, 3
URB_SIZE = 56  # sizeof(struct usbdevfs_urb) on x86_64; buffer at 16, status at 4, actual at 28

STRINGS = {1: "CFSR emulated", 2: "Spike Camera 400x250 (emulated)", 3: "EMU00001"}


def _descriptors(vid: int, pid: int) -> tuple[bytes, bytes]:
    dev = struct.pack("<BBHBBBBHHHBBBB", 18, 1, 0x0320, 0, 0, 0, 9, vid, pid, 0x0100, 1, 2, 3, 1)
    ep = struct.pack("<BBBBHB", 7, 5, P.EP_IN, 2, P.PACKET_BYTES, 0) + struct.pack(
        "<BBBBH", 6, 0x30, 15, 0, 0
    )
    intf = struct.pack("<BBBBBBBBB", 9, 4, 0, 0, 1, 0xFF, 0, 0, 0)
    body = intf + ep
    cfg = struct.pack("<BBHBBBBB", 9, 2, 9 + len(body), 1, 1, 0, 0x80, 112) + body
    return dev, cfg


class _IoctlData(Structure):  # struct _UMockdevIoctlData (umockdev.h)
    _fields_ = [
        ("g_class", c_void_p),
        ("ref_count", ctypes.c_uint),
        ("qdata", c_void_p),
        ("data", POINTER(c_ubyte)),
        ("data_len", c_int),
        ("client_addr", c_ulong),
        ("priv", c_void_p),
    ]


_HANDLE_IOCTL = CFUNCTYPE(c_int, c_void_p, c_void_p, c_void_p)
_libs: tuple[ctypes.CDLL, ctypes.CDLL] | None = None


def preloaded() -> bool:
    """True inside ``umockdev-wrapper`` (the preload must be there from process start)."""
    return "libumockdev-preload" in os.environ.get("LD_PRELOAD", "")


def available() -> tuple[bool, str]:
    """Whether this process can run the emulator, and why not."""
    if not preloaded():
        return False, "not running under umockdev-wrapper (LD_PRELOAD lacks libumockdev-preload)"
    try:
        _load()
    except OSError as exc:
        return False, f"cannot load libumockdev/libgobject: {exc}"
    return True, ""


def _load() -> tuple[ctypes.CDLL, ctypes.CDLL]:
    global _libs
    if _libs is not None:
        return _libs
    gobj = ctypes.CDLL("libgobject-2.0.so.0")
    um = ctypes.CDLL("libumockdev.so.0")
    um.umockdev_testbed_new.restype = c_void_p
    um.umockdev_ioctl_base_new.restype = c_void_p
    um.umockdev_testbed_attach_ioctl.argtypes = [c_void_p, c_char_p, c_void_p, c_void_p]
    um.umockdev_testbed_add_from_string.argtypes = [c_void_p, c_char_p, c_void_p]
    um.umockdev_ioctl_client_get_request.argtypes = [c_void_p]
    um.umockdev_ioctl_client_get_request.restype = c_ulong
    um.umockdev_ioctl_client_get_arg.argtypes = [c_void_p]
    um.umockdev_ioctl_client_get_arg.restype = POINTER(_IoctlData)
    um.umockdev_ioctl_client_complete.argtypes = [c_void_p, c_long, c_int]
    um.umockdev_ioctl_data_resolve.argtypes = [POINTER(_IoctlData), c_size_t, c_size_t, c_void_p]
    um.umockdev_ioctl_data_resolve.restype = POINTER(_IoctlData)
    um.umockdev_ioctl_data_set_ptr.argtypes = [POINTER(_IoctlData), c_size_t, POINTER(_IoctlData)]
    um.umockdev_ioctl_data_unref.argtypes = [POINTER(_IoctlData)]
    gobj.g_signal_connect_data.argtypes = [c_void_p, c_char_p, c_void_p, c_void_p, c_void_p,
                                           c_int]
    gobj.g_signal_connect_data.restype = c_ulong
    gobj.g_object_unref.argtypes = [c_void_p]
    _libs = (um, gobj)
    return _libs


class UsbdevfsCamera:
    """usbdevfs ioctl handler: URB queue, control requests, bulk IN from the model."""

    def __init__(self, model: CameraModel, *, vid: int, pid: int,
                 caps: int = CAP_BULK_SCATTER_GATHER | CAP_NO_PACKET_SIZE_LIM
                 | CAP_REAP_AFTER_DISCONNECT) -> None:
        self.um, self.gobj = _load()
        self.model = model
        self.caps = caps
        self.dev_desc, self.cfg_desc = _descriptors(vid, pid)
        self.pending: deque = deque()
        self.discarded: deque = deque()
        self.pending_bytes = 0
        self.lock = threading.Lock()
        self.counts: dict[int, int] = {}
        self.errors: list[str] = []
        self.max_block_s = 0.02  # longest the handler blocks waiting for data
        #: ``threading`` ident of the thread umockdev calls the handler on (for CPU time)
        self.thread_ident: int | None = None
        self._cb = _HANDLE_IOCTL(self._handle)  # keep the callback alive

    # -- umockdev plumbing ------------------------------------------------------------------
    def _handle(self, handler, client, user):
        um = self.um
        self.thread_ident = threading.get_ident()
        try:
            req = um.umockdev_ioctl_client_get_request(client)
            self.counts[req] = self.counts.get(req, 0) + 1
            arg = um.umockdev_ioctl_client_get_arg(client)
            r = self._dispatch(req, arg)
            if r is None:
                return 0
            um.umockdev_ioctl_client_complete(client, r[0], r[1])
            return 1
        except Exception:  # noqa: BLE001 - never leave the client hanging
            self.errors.append(traceback.format_exc())
            traceback.print_exc(file=sys.stderr)
            um.umockdev_ioctl_client_complete(client, -1, errno.EIO)
            return 1

    def _u32(self, arg, value: int) -> None:
        um = self.um
        d = um.umockdev_ioctl_data_resolve(arg, 0, 4, None)
        ctypes.cast(d.contents.data, POINTER(ctypes.c_uint32))[0] = value
        um.umockdev_ioctl_data_unref(d)

    def _dispatch(self, req, arg):
        um, model = self.um, self.model
        gone = model.unplugged()
        if req == USBDEVFS_GET_CAPABILITIES:
            self._u32(arg, self.caps)
            return 0, 0
        if req == USBDEVFS_GETDRIVER:
            return -1, errno.ENODATA
        if req == USBDEVFS_RELEASEINTERFACE:
            return 0, 0
        if req in (USBDEVFS_CLAIMINTERFACE, USBDEVFS_DISCONNECT_CLAIM, USBDEVFS_SETCONFIGURATION,
                   USBDEVFS_SETINTERFACE, USBDEVFS_RESET, USBDEVFS_IOCTL):
            return (-1, errno.ENODEV) if gone else (0, 0)
        if req == USBDEVFS_CLEAR_HALT:
            if gone:
                return -1, errno.ENODEV
            model.clear_halt()
            return 0, 0
        if req == USBDEVFS_SUBMITURB:
            if gone:
                return -1, errno.ENODEV
            urb = um.umockdev_ioctl_data_resolve(arg, 0, URB_SIZE, None)  # owned reference
            raw = ctypes.string_at(urb.contents.data, URB_SIZE)
            typ, ep = raw[0], raw[1]
            buf_ptr, buf_len = struct.unpack_from("<Qi", raw, 16)
            with self.lock:
                if typ == URB_TYPE_BULK and self.pending_bytes + buf_len > P.MAX_TRANSFER_BYTES:
                    um.umockdev_ioctl_data_unref(urb)
                    return -1, errno.ENOMEM  # usbfs_memory_mb=16, as the real kernel
                if typ == URB_TYPE_BULK:
                    self.pending_bytes += buf_len
                self.pending.append((urb, typ, ep, buf_ptr, buf_len))
            return 0, 0
        if req in (USBDEVFS_REAPURB, USBDEVFS_REAPURBNDELAY):
            return self._reap(arg, gone)
        if req == USBDEVFS_DISCARDURB:
            addr = ctypes.cast(arg.contents.data, POINTER(ctypes.c_uint64))[0]
            with self.lock:
                for i, item in enumerate(self.pending):
                    if item[0].contents.client_addr == addr:
                        del self.pending[i]
                        if item[1] == URB_TYPE_BULK:
                            self.pending_bytes -= item[4]
                        self.discarded.append(item[0])
                        return 0, 0
            return -1, errno.EINVAL
        return None  # unknown: let umockdev pass it on

    def _finish(self, arg, urb, status: int, n: int) -> None:
        um = self.um
        base = ctypes.addressof(urb.contents.data.contents)
        view = (ctypes.c_char * URB_SIZE).from_address(base)
        struct.pack_into("<i", view, 4, status)
        struct.pack_into("<i", view, 28, n)
        p = um.umockdev_ioctl_data_resolve(arg, 0, 8, None)
        um.umockdev_ioctl_data_set_ptr(p, 0, urb)
        um.umockdev_ioctl_data_unref(p)
        um.umockdev_ioctl_data_unref(urb)

    def _reap(self, arg, gone: bool):
        with self.lock:
            if self.discarded:
                urb = self.discarded.popleft()
                self._finish(arg, urb, -errno.ENOENT, 0)
                return 0, 0
            if not self.pending:
                return -1, (errno.ENODEV if gone else errno.EAGAIN)
            urb, typ, ep, buf_ptr, buf_len = self.pending[0]
        if gone:
            status, n = -errno.ESHUTDOWN, 0
        elif typ == URB_TYPE_CONTROL:
            status, n = self._control(buf_ptr, buf_len)
        elif typ == URB_TYPE_BULK and ep == P.EP_IN:
            r = self.model.bulk_in(buf_ptr, buf_len)
            if r is None:
                # not due yet: block a little here (pacing), then let libusb poll again
                time.sleep(min(self.max_block_s, self.model.next_ready_in()))
                r = self.model.bulk_in(buf_ptr, buf_len)
                if r is None:
                    return -1, errno.EAGAIN
            status, n = r
        else:
            status, n = -errno.EPIPE, 0
        with self.lock:
            if self.pending and self.pending[0][0] is urb:
                self.pending.popleft()
                if typ == URB_TYPE_BULK:
                    self.pending_bytes -= buf_len
            else:  # discarded meanwhile
                return -1, errno.EAGAIN
        self._finish(arg, urb, status, n)
        return 0, 0

    def _control(self, buf_ptr: int, buf_len: int) -> tuple[int, int]:
        bm, breq, wvalue, windex, wlength = struct.unpack("<BBHHH", ctypes.string_at(buf_ptr, 8))
        m = self.model
        try:
            if bm == 0x80 and breq == 6:  # GET_DESCRIPTOR
                dt, idx = wvalue >> 8, wvalue & 0xFF
                if dt == 1:
                    resp = self.dev_desc
                elif dt == 2:
                    resp = self.cfg_desc
                elif dt == 3:
                    if idx == 0:
                        resp = bytes([4, 3, 9, 4])
                    else:
                        s = STRINGS.get(idx, "?").encode("utf-16-le")
                        resp = bytes([2 + len(s), 3]) + s
                else:
                    return -errno.EPIPE, 0
            elif bm == P.RT_VENDOR_IN:
                resp = m.control_in(breq, wvalue, windex, wlength)
            elif bm == P.RT_VENDOR_OUT:
                m.control_out(breq, wvalue, windex, ctypes.string_at(buf_ptr + 8, wlength))
                return 0, wlength
            elif bm & 0x80:
                resp = b""
            else:
                return 0, wlength
        except ValueError:
            return -errno.EPIPE, 0  # the device stalls requests it does not understand
        resp = resp[:wlength]
        ctypes.memmove(buf_ptr + 8, resp, len(resp))
        return 0, len(resp)


class EmulatedCamera:
    """A umockdev test bed holding one emulated camera; use as a context manager."""

    def __init__(self, model: CameraModel, *, vid: int = P.DEFAULT_VID,
                 pid: int = P.DEFAULT_PID, busnum: int = 1, devnum: int = 2) -> None:
        ok, why = available()
        if not ok:
            raise RuntimeError(why)
        self.model = model
        self.vid, self.pid = vid, pid
        self.busnum, self.devnum = busnum, devnum
        self.handler = UsbdevfsCamera(model, vid=vid, pid=pid)
        self._tb = None
        self._ioctl = None

    def start(self) -> EmulatedCamera:
        um, gobj = _load()
        tb = um.umockdev_testbed_new()
        ioctl = um.umockdev_ioctl_base_new()
        gobj.g_signal_connect_data(ioctl, b"handle-ioctl",
                                   ctypes.cast(self.handler._cb, c_void_p), None, None, 0)
        node = f"/dev/bus/usb/{self.busnum:03d}/{self.devnum:03d}"
        if not um.umockdev_testbed_attach_ioctl(tb, node.encode(), ioctl, None):
            raise RuntimeError(f"umockdev could not attach an ioctl handler to {node}")
        b, d = self.busnum, self.devnum
        desc = (
            f"P: /devices/pci0000:00/0000:00:14.0/usb{b}/{b}-1\n"
            f"N: bus/usb/{b:03d}/{d:03d}\n"
            "E: SUBSYSTEM=usb\nE: DEVTYPE=usb_device\nE: DRIVER=usb\n"
            f"E: BUSNUM={b:03d}\nE: DEVNUM={d:03d}\nE: DEVNAME={node}\n"
            f"A: busnum={b}\\n\nA: devnum={d}\\n\nA: bConfigurationValue=1\\n\n"
            "A: speed=5000\\n\n"
            f"H: descriptors={(self.handler.dev_desc + self.handler.cfg_desc).hex()}\n"
        )
        if not um.umockdev_testbed_add_from_string(tb, desc.encode(), None):
            raise RuntimeError("umockdev could not add the emulated device")
        self._tb, self._ioctl = tb, ioctl
        return self

    def stop(self) -> None:
        if self._tb is not None:
            _, gobj = _load()
            gobj.g_object_unref(self._tb)
            self._tb = None

    def __enter__(self) -> EmulatedCamera:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
