"""USB driver logic against the fake pyusb backend (Tier 0: pyusb's own code runs, the layer
below it is :class:`cfsr_live.replay.camera_model.CameraModel`). The same scenarios run against the
real libusb under umockdev in ``tests/usb/umock_cases.py``."""

from __future__ import annotations

import numpy as np
import pytest
from livehelpers import wait_until

pytest.importorskip("usb.core")

from cfsr_live.driver import protocol as P  # noqa: E402
from cfsr_live.driver.source import BlockFlags, CameraControl, ReplayControl, SourceState  # noqa: E402
from cfsr_live.driver.usb import UsbCameraSource  # noqa: E402
from cfsr_live.replay.camera_model import CameraModel  # noqa: E402
from cfsr_live.replay.fake_usb import FakeUsbBackend, PreloadedUsbBackend  # noqa: E402
from cfsr_live.replay.pattern import pattern_recording  # noqa: E402


@pytest.fixture(scope="module")
def rec():
    return pattern_recording(700, height=50, width=64)  # 400-byte frames, 16-frame alignment


def _open(rec, fpb=64, **kw):
    model = CameraModel(rec, **kw)
    src = UsbCameraSource(frames_per_block=fpb, backend=FakeUsbBackend(model),
                          read_timeout_ms=300, backoff=(0.02, 0.1))
    src.open()
    return model, src


def _check_block(rec, blk):
    n = rec.n_frames
    want = rec.packed_frames[(blk.index + np.arange(blk.n_frames)) % n]
    assert np.array_equal(blk.data, want), f"block at {blk.index} is not byte-exact"


def _read(src, k, rec=None, timeout=5.0):
    out = []

    def got_all() -> bool:
        b = src.read_block(0.3)  # waits for data itself: no pause between polls
        if b is not None:
            if rec is not None:
                _check_block(rec, b)
            out.append(b)
        return len(out) >= k

    wait_until(got_all, timeout, lambda: f"{k} blocks (got {len(out)}; counters "
               f"{src.counters()})", interval=0)
    return out


def test_protocol_sizes():
    assert P.frame_alignment(12500) == 256
    assert P.block_bytes(256, 12500) == 3_201_024 == 3126 * 1024
    with pytest.raises(ValueError, match="16777216"):
        P.block_bytes(1400, 12500)
    h = P.BlockHeader(2**40 + 5, 256, 256, 400, 250, 400, 1, 12500, 0, 3_201_024, 7, 3, 9)
    raw = P.pack_header(h)
    assert P.parse_header(raw) == h
    bad = bytearray(raw)
    bad[9] ^= 1
    assert P.parse_header(bytes(bad)) is None


def test_payload_crc_is_zlibs_crc32():
    import zlib

    data = np.random.default_rng(1).integers(0, 256, 3 * 12500 + 7, dtype=np.uint8)
    assert P.CRC32_IMPL in ("isal", "zlib_ng", "zlib")
    assert P.payload_crc32(data) == zlib.crc32(data)
    assert P.payload_crc32(data[5:], 123) == zlib.crc32(data[5:], 123)
    assert P.payload_crc32(b"") == 0


def test_enumerate_configure_and_byte_exact(rec):
    model, src = _open(rec)
    assert src.state == SourceState.STREAMING
    assert src.info.kind == "usb" and src.info.layout.frame_bytes == 400
    assert src.fpb == 64 and src.block_bytes == P.block_bytes(64, 400)
    assert src.get_facility(ReplayControl) is None  # a camera cannot seek
    cam = src.get_facility(CameraControl)
    assert cam.device_info()["serial"] == "EMU00001"
    blocks = _read(src, 20, rec)
    assert [b.index for b in blocks] == list(range(0, 20 * 64, 64))
    assert blocks[0].flags & BlockFlags.DISCONTINUITY
    assert src.counters().lost_frames == 0
    assert model.events[0] == "start 64"
    src.close()
    assert model.events[-1] == "stop"


@pytest.mark.parametrize("fault", ["stall", "overflow", "short", "corrupt", "corrupt_header",
                                   "timeout"])
def test_fault_recovery_and_loss_count(rec, fault):
    model, src = _open(rec)
    _read(src, 3, rec)
    model.inject(fault, seconds=0.4)
    blocks = _read(src, 6, rec)
    c = src.counters()
    assert c.lost_frames == model.expected_loss
    expected = {"stall": 64, "overflow": 64, "short": 64, "corrupt": 64, "corrupt_header": 64,
                "timeout": 0}[fault]
    assert c.lost_frames == expected, c
    key = {"stall": "stalls", "overflow": "overflows", "short": "short_blocks",
           "corrupt": "crc_errors", "corrupt_header": "bad_headers", "timeout": "timeouts"}[fault]
    assert getattr(c, key) >= 1, c
    if fault == "overflow":
        assert c.resyncs == 1
    if expected:
        assert any(b.flags & BlockFlags.LOSS for b in blocks)
    src.close()


@pytest.mark.parametrize("kind", ["unplug", "unplug_eio"])
def test_unplug_and_replug_reconnects_with_backoff(rec, kind):
    model, src = _open(rec)
    _read(src, 2, rec)
    model.inject(kind, seconds=0.3)
    gone = {SourceState.DISCONNECTED, SourceState.BACKOFF}

    def noticed() -> bool:
        assert src.read_block(0.05) is None  # nothing arrives while the camera is away
        return src.state in gone

    wait_until(noticed, 5, lambda: f"the unplug to be noticed (state {src.state}, "
               f"counters {src.counters()})", interval=0)
    assert src.counters().disconnects == 1
    blocks = _read(src, 4, rec)
    c = src.counters()
    assert c.reconnects == 1 and c.connect_failures >= 1
    assert c.lost_frames == model.expected_loss
    assert blocks[0].index >= 2 * 64
    src.close()


def test_paced_stream_fifo_overflow_is_counted(rec):
    # a paced device with a tiny FIFO; the host pauses: frames are dropped on the device and
    # the driver counts exactly those from the index gap
    model, src = _open(rec, paced=True, rate_hz=20000, fifo_frames=256)
    _read(src, 2, rec)
    # the host pauses until the sensor has made 2000 frames more: only 256 fit in the FIFO
    wait_until(lambda: model.sensor_index(model.clock()) - model.next_index > 2000, 5,
               "the device FIFO to overflow", interval=0.01)
    _read(src, 3, rec)
    c = src.counters()
    assert model.dropped_total > 0
    assert c.lost_frames == model.expected_loss
    src.close()


def test_no_camera_keeps_trying(rec):
    model = CameraModel(rec)
    src = UsbCameraSource(vid=0xDEAD, pid=0xBEEF, backend=FakeUsbBackend(model),
                          backoff=(0.01, 0.02))
    src.open()  # does not raise: the service stays up without a camera
    assert src.state in (SourceState.BACKOFF, SourceState.DISCONNECTED)
    for _ in range(5):
        assert src.read_block(0.05) is None
    assert src.counters().connect_failures >= 2
    assert "no USB device" in (src.last_error or "")
    src.close()


def test_preloaded_backend_serves_consecutive_byte_exact_blocks(rec):
    # 700 frames, 64 per block: 175 blocks make a whole number of laps of the recording, so
    # the payloads served again in the second lap are still the frames their headers name
    backend = PreloadedUsbBackend(CameraModel(rec), blocks=175)
    src = UsbCameraSource(frames_per_block=64, backend=backend, read_timeout_ms=300)
    src.open()
    blocks = _read(src, 400, rec)  # two laps and more: the headers are rewritten
    assert [b.index for b in blocks] == list(range(0, 400 * 64, 64))
    c = src.counters()
    assert c.lost_frames == 0 and c.crc_errors == 0 and c.bad_headers == 0
    assert backend.served == 400 and backend.copy_s > 0
    src.close()


def test_preloaded_backend_checks_its_arguments(rec):
    with pytest.raises(ValueError, match="blocks"):
        PreloadedUsbBackend(CameraModel(rec), blocks=0)
