"""Unit tests of service parts that need no running server: the WebSocket message format,
latest-only client queues, the latest-frame slot, settings and the data-folder catalog."""

from __future__ import annotations

import asyncio
import os
import struct
import subprocess
import sys

import numpy as np
import pytest

from cfsr_live.service.frameslot import FrameSlot
from cfsr_live.service.hub import ClientQueue, FrameHub, decode_ws_message, encode_ws_message
from cfsr_live.service.settings import Settings, SourceSpec


def _slot_with_frame(h=5, w=7, step=2**40 + 3):
    slot = FrameSlot.create(max_pixels=h * w)
    img = np.arange(h * w, dtype=np.uint8).reshape(h, w)
    coarse = np.zeros((h, w), bool)
    coarse[1, 2] = coarse[4, 6] = True
    slot.publish(step=step, image=img, masks={"coarse": coarse}, method="csr", gain=0.5,
                 t_arrival=0.0, compute_ms=1.5, latency_ms=2.5)
    return slot, img, coarse


def test_frame_slot_and_ws_message_roundtrip():
    slot, img, coarse = _slot_with_frame()
    try:
        f = slot.read()
        assert f is not None and f.step == 2**40 + 3 and f.method == "csr"
        assert np.array_equal(f.image, img) and set(f.masks) == {"coarse"}
        assert slot.read(since=f.seq) is None  # nothing newer
        names = slot.mask_names
        # every mask the methods declare, then the defect map's
        assert names == ("coarse", "fine", "motion", "defects")
        msg = encode_ws_message(f, names)
        assert len(msg) == 64 + 35 + 4 * 5  # header, image, four 35-bit planes
        d = decode_ws_message(msg, names)
        assert d["step"] == 2**40 + 3 and d["method"] == "csr" and d["gain"] == 0.5
        assert np.array_equal(d["image"], img)
        assert np.array_equal(d["masks"]["coarse"], coarse) and "fine" not in d["masks"]
    finally:
        slot.close()


def test_every_declared_mask_reaches_the_frame_message():
    """SNM's ``motion`` mask is published, carried in the WebSocket message and decoded by
    name (the slot's planes come from the methods' declared masks, not a fixed pair)."""
    from cfsr.methods import get_method
    from cfsr.methods import methods as registered

    slot = FrameSlot.create(max_pixels=12)
    try:
        for name in registered():
            assert set(get_method(name).masks) <= set(slot.mask_names), name
        motion = np.zeros((3, 4), bool)
        motion[2, 3] = True
        slot.publish(step=9, image=np.zeros((3, 4), np.uint8), masks={"motion": motion},
                     method="snm", gain=0.5, t_arrival=0.0, compute_ms=0.0, latency_ms=0.0)
        d = decode_ws_message(encode_ws_message(slot.read(), slot.mask_names), slot.mask_names)
        assert set(d["masks"]) == {"motion"} and np.array_equal(d["masks"]["motion"], motion)
        # a mask no plane holds is refused, never dropped on the way
        with pytest.raises(ValueError, match="not among the slot"):
            slot.publish(step=10, image=np.zeros((3, 4), np.uint8),
                         masks={"halo": motion}, method="x", gain=0.5, t_arrival=0.0,
                         compute_ms=0.0, latency_ms=0.0)
    finally:
        slot.close()


def test_worker_counters_are_one_typed_record():
    """The counters are fields of the schema: the worker's writes land in the web process's
    typed copy, and a misspelt counter fails instead of reading 0."""
    from cfsr_live.service.schema import COUNTER_DTYPE, WorkerCounters

    slot = FrameSlot.create(max_pixels=4)
    try:
        rec = slot.counters()[0]  # what the worker holds: a view into shared memory
        rec["frames_out"] += 3
        rec["compute_ms"] = 12.5
        st = slot.stats()
        assert isinstance(st, WorkerCounters)
        assert st.frames_out == 3 and isinstance(st.frames_out, int) and st.compute_ms == 12.5
        assert set(COUNTER_DTYPE.names) == set(WorkerCounters.__dataclass_fields__)
        with pytest.raises((ValueError, KeyError)):
            rec["frames_outt"] += 1
        with pytest.raises(AttributeError):
            st.frames_outt  # noqa: B018
    finally:
        slot.close()


def test_frame_message_names_its_layout_once():
    """The header the encoder writes is the one the schema document describes to the
    viewer (offsets of every field), and one method-name length serves slot and wire."""
    from cfsr_live.service.schema import METHOD_NAME_BYTES, WS_HEADER, schema_document

    slot, img, coarse = _slot_with_frame()
    try:
        slot.publish(step=5, image=img, masks={"coarse": coarse}, method="m" * 40, gain=0.5,
                     t_arrival=0.0, compute_ms=1.5, latency_ms=2.5)
        f = slot.read()
        assert f.method == "m" * METHOD_NAME_BYTES  # cut to the same length as on the wire
        msg = encode_ws_message(f, slot.mask_names)
        doc = schema_document(slot.mask_names)
        off = doc["ws_offsets"]
        assert doc["ws_header_bytes"] == WS_HEADER.size
        assert int.from_bytes(msg[off["width"]:off["width"] + 2], "little") == f.width
        assert int.from_bytes(msg[off["step"]:off["step"] + 8], "little") == 5
        assert msg[off["mask_planes"]] == len(doc["masks"]) == len(slot.mask_names)
        assert msg[off["method"]:off["method"] + METHOD_NAME_BYTES] == f.method.encode()
        assert [m["name"] for m in doc["masks"]] == list(slot.mask_names)
        assert len(doc["heat_lut"]) == 256 * 3
        # every offset the viewer is given reads the field the encoder packed there
        packed = WS_HEADER.unpack_from(msg)
        codes = ("4s", "H", "H", "q", "I", "H", "H", "B", "B", "B", "f", "f", "f",
                 f"{METHOD_NAME_BYTES}s")
        names = sorted(off, key=off.get)
        assert len(names) == len(codes) == len(packed)
        for name, code, value in zip(names, codes, packed, strict=True):
            assert struct.unpack_from("<" + code, msg, off[name])[0] == value, name
        assert (packed[0], packed[2], packed[10], packed[11]) == (b"CFSR", 64, 0.5, 1.5)
    finally:
        slot.close()


def test_client_queue_is_latest_only():
    async def go():
        q = ClientQueue("ws")
        for i in range(100):
            q.offer(i)
        assert q.pending == 1 and q.dropped == 99
        assert await q.get() == 99
        assert q.pending == 0
        task = asyncio.create_task(q.get())
        await asyncio.sleep(0)
        q.offer("x")
        assert await asyncio.wait_for(task, 1) == "x"

    asyncio.run(go())


def test_hub_fans_out_once_per_frame():
    async def go():
        slot, img, _ = _slot_with_frame()
        try:
            hub = FrameHub(slot)
            a, b = hub.add(ClientQueue("ws")), hub.add(ClientQueue("mjpeg"))
            assert hub.poll_once() and not hub.poll_once()
            assert isinstance(await a.get(), bytes)
            assert (await b.get()).step == slot.read().step
            hub.remove(a)
            assert list(hub.clients) == [b.id]
        finally:
            slot.close()

    asyncio.run(go())


def test_empty_slot_reads_nothing_and_seq_counts_frames():
    slot = FrameSlot.create(max_pixels=16)
    try:
        assert slot.read() is None and slot.seq < 0  # nothing published yet
        img = np.zeros((4, 4), np.uint8)
        for k in (1, 2):
            slot.publish(step=k, image=img, masks={}, method="tfp", gain=0.5, t_arrival=0.0,
                         compute_ms=0.0, latency_ms=0.0)
            f = slot.read()
            assert f.seq == slot.seq == f.frame_no == k
    finally:
        slot.close()


def test_hub_run_logs_a_failure_and_goes_on(caplog):
    """The fan-out loop survives an error, counts it and logs it once (never silently)."""

    class Broken:
        calls = 0
        third = asyncio.Event()  # the handshake: the loop went on after two failures

        def read(self, since=None):
            Broken.calls += 1
            if Broken.calls >= 3:
                Broken.third.set()
            raise OSError("slot unmapped")

    async def go():
        hub = FrameHub(Broken(), poll_s=0.001)  # type: ignore[arg-type]
        task = asyncio.create_task(hub.run())
        await asyncio.wait_for(Broken.third.wait(), 30)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return hub

    with caplog.at_level("ERROR", logger="cfsr.hub"):
        hub = asyncio.run(go())
    assert hub.errors >= 3 and hub.last_error == "OSError: slot unmapped"
    logged = [r for r in caplog.records if "frame fan-out failed" in r.getMessage()]
    assert len(logged) == 1 and logged[0].exc_info is not None


def test_settings_token_rule(tmp_path):
    with pytest.raises(ValueError, match="token"):
        Settings(host="0.0.0.0", data_dir=tmp_path)
    assert Settings(host="0.0.0.0", token="t", data_dir=tmp_path).token == "t"
    assert Settings(host="localhost", data_dir=tmp_path).host == "localhost"


def test_catalog_lists_only_the_data_folder(tmp_path):
    from cfsr_live.replay.pattern import pattern_recording
    from cfsr_live.service.catalog import SourceCatalog

    data = tmp_path / "data"
    (data / "deep" / "er").mkdir(parents=True)
    from cfsr.datfile import write_dat

    write_dat(data / "deep" / "er" / "x.dat", pattern_recording(10, height=8, width=8))
    write_dat(tmp_path / "secret.dat", pattern_recording(10, height=8, width=8))
    os.symlink(tmp_path / "secret.dat", data / "alias.dat")
    os.symlink(tmp_path, data / "loop")  # a link to the parent: never followed
    cat = SourceCatalog(Settings(data_dir=data, source=SourceSpec("demo")))
    ids = set(cat.scan())
    assert "file:deep/er/x.dat" in ids
    assert not any("secret" in i or "alias" in i or "loop" in i for i in ids)
    assert cat.spec_for("file:deep/er/x.dat").path == (data / "deep/er/x.dat").resolve()
    for bad in ("file:../secret.dat", "file:alias.dat", str(tmp_path / "secret.dat")):
        with pytest.raises(KeyError):
            cat.spec_for(bad)


def test_serve_on_a_busy_port_fails_with_one_clear_line(capsys):
    import socket

    from cfsr.cli import main

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["serve", "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"cannot listen on 127.0.0.1:{port}" in err and "--port" in err


def test_mask_colours_and_names_are_checked(monkeypatch):
    """Built-in masks keep their own overlay colour, another method's mask gets a stable one
    of the palette; the mask names every method declares must fit a frame's header."""
    import importlib

    from cfsr_live.service import schema

    registry = importlib.import_module("cfsr.methods")  # (cfsr.methods is also a function)

    for name, (rgb, _) in schema.MASK_STYLE.items():
        assert schema.mask_color(name) == rgb
    other = schema.mask_color("edges")
    assert other in schema._PALETTE and schema.mask_color("edges") == other
    assert schema.display_masks() == ("coarse", "fine", "motion", "defects")

    class _Declares:
        def __init__(self, masks):
            self.masks = masks

    def declared(*masks):
        monkeypatch.setattr(registry, "methods", lambda: {"x": None})
        monkeypatch.setattr(registry, "get_method", lambda _: _Declares(masks))
        return schema.display_masks

    longest = "m" * (schema.MASK_NAME_BYTES - 1)
    assert declared(longest, "a", "a")() == (longest, "a", "defects")  # each once
    for bad in ("m" * schema.MASK_NAME_BYTES, "", "maské"):
        with pytest.raises(ValueError, match="ASCII characters"):
            declared(bad)()
    # the defect map's mask takes one of the frame's places
    with pytest.raises(ValueError, match="masks"):
        declared(*(f"m{i}" for i in range(schema.MAX_MASKS)))()
    assert len(declared(*(f"m{i}" for i in range(schema.MAX_MASKS - 1)))()) == schema.MAX_MASKS


def test_web_process_does_not_load_the_worker():
    """The web process supervises the worker through messages and shared counters: building
    the app loads neither the worker's modules nor the reconstruction's pool (they load in the
    spawned worker only)."""
    code = (
        "import sys\n"
        "from cfsr_live.service.app import create_app\n"
        "from cfsr_live.service.runtime import Runtime\n"
        "from cfsr_live.service.supervisor import WorkerSupervisor\n"
        "bad = ('cfsr_live.service.worker_loop', 'cfsr_live.service.frame_worker', 'cfsr.pool')\n"
        "print(sorted(m for m in bad if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_late_is_judged_against_the_measured_pace():
    """A frame is late after twice what a frame takes through the pool at the rate it holds,
    never under a second: on a slow machine frames computed at its pace are shown."""
    from cfsr_live.service.pacing import LATE_S, late_after_s

    assert late_after_s(None, 2, 30.0) == LATE_S  # nothing measured yet
    assert late_after_s(20.0, 2, 30.0) == LATE_S  # a fast pipeline keeps the floor
    # 800 ms a frame on 2 processes: one every 0.4 s, so 2 x (0.8 + 0.4) s
    assert late_after_s(800.0, 2, 30.0) == pytest.approx(2.4)


def test_frame_priority_lowers_only_once_every_kernel_is_cached():
    """Pool processes compute frames below acquisition, but only once nothing can make them
    compile (a nice value raised cannot be lowered again)."""
    from cfsr_live.service.priority import FRAME_NICE, FramePriority

    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"],
                            stdin=subprocess.PIPE)
    try:
        cached = [False]
        prio = FramePriority(cached=lambda: cached[0], check_s=0.0)
        assert not prio.lower([proc.pid])
        assert os.getpriority(os.PRIO_PROCESS, proc.pid) == os.getpriority(os.PRIO_PROCESS, 0)
        cached[0] = True
        assert prio.lower([proc.pid])
        assert FramePriority.lowest([proc.pid]) == max(FRAME_NICE, os.nice(0))
    finally:
        proc.communicate(b"")


def test_hub_rate_reads_a_slow_stream_and_tells_the_viewer_count(monkeypatch):
    """The output rate is the rate delivered, at one frame a second too (it read 0 with
    fewer than 2 frames in 2 s); the hub tells who watches as clients come and go."""
    told: list[int] = []
    slot, _, _ = _slot_with_frame()
    try:
        hub = FrameHub(slot, on_viewers=told.append)
        now = 1000.0
        monkeypatch.setattr("cfsr_live.service.hub.time.monotonic", lambda: now)
        hub._times.extend([now - 3.0, now - 2.0, now - 1.0, now])  # one frame a second
        assert hub.fps() == pytest.approx(1.0)
        hub._times.clear()
        hub._times.extend(now - 1.0 + i / 8 for i in range(9))  # 8 fps, the last one now
        assert hub.fps() == pytest.approx(8.0)
        c = hub.add(ClientQueue("ws"))
        hub.remove(c)
        assert told == [0, 1, 0]
    finally:
        slot.close()


def test_frame_names_the_tier_that_made_it():
    """The tier travels with the frame (slot, WebSocket header at the schema's offset), so the
    viewer, the snapshot and the status name the tier of the frame shown, not the mode."""
    from cfsr_live.service.schema import QUALITY_TIERS, WS_OFFSETS

    slot, img, _ = _slot_with_frame()
    try:
        assert slot.read().quality == ""  # a method without tiers
        slot.publish(step=9, image=img, masks={}, method="cfsr", gain=0.5, t_arrival=0.0,
                     compute_ms=1.0, latency_ms=1.0, quality="fast")
        f = slot.read()
        msg = encode_ws_message(f, slot.mask_names)
        assert f.quality == "fast" and QUALITY_TIERS[msg[WS_OFFSETS["quality"]]] == "fast"
        assert decode_ws_message(msg, slot.mask_names)["quality"] == "fast"
    finally:
        slot.close()


@pytest.mark.parametrize("pairs", [False, True], ids=["steady", "in-pairs"])
def test_hub_rate_is_the_rate_delivered_below_a_frame_a_second(monkeypatch, pairs):
    """Below a frame a second the output rate the hub reports, sampled once a second as the
    status is, averages to the rate delivered over a minute from the hub's start, also when
    frames come in pairs (two pool processes finishing close together): the mean interval
    between the few frames of its window read 0.43 frames/s delivered in pairs as 0.50."""
    slot, img, _ = _slot_with_frame()
    now = [1000.0]
    monkeypatch.setattr("cfsr_live.service.hub.time.monotonic", lambda: now[0])
    try:
        for rate in (0.45, 0.3):
            hub = FrameHub(slot)
            hub.poll_once()  # the slot's frame, there before the hub: not one it delivers
            start, seconds, seq, step = now[0], 60, 0, 0
            # frame times: a steady stream, or pairs 0.2 s apart at the same mean rate
            gap = 2 / rate if pairs else 1 / rate
            times = sorted(start + k * gap + d for k in range(1, int(seconds / gap) + 1)
                           for d in ((0.0, 0.2) if pairs else (0.0,)))
            times = [t for t in times if t < start + seconds]
            readings = []
            for tick in np.arange(0.01, seconds + 1e-9, 0.01):
                now[0] = start + tick
                while times and times[0] <= now[0]:
                    times.pop(0)
                    step += 1
                    slot.publish(step=step, image=img, masks={}, method="csr", gain=0.5,
                                 t_arrival=0.0, compute_ms=1.0, latency_ms=1.0)
                    assert hub.poll_once()
                    seq += 1
                if round(tick * 100) % 100 == 0:  # once a second, as the status samples it
                    readings.append(hub.fps())
            delivered = seq / seconds
            reported = float(np.mean(readings[1:]))
            assert reported == pytest.approx(delivered, rel=0.1), (rate, readings)
    finally:
        slot.close()


def test_request_timeouts_come_from_the_environment(monkeypatch):
    """The request-head and request-body timeouts default to the service's own and can be
    lowered (the fault rows that wait them out do); what is not a number of seconds is
    refused."""
    from cfsr_live.service.body import BODY_TIMEOUT_S
    from cfsr_live.service.httpproto import HEADER_TIMEOUT_S

    monkeypatch.delenv("CFSR_HEADER_TIMEOUT_S", raising=False)
    monkeypatch.delenv("CFSR_BODY_TIMEOUT_S", raising=False)
    s = Settings()
    assert (s.header_timeout_s, s.body_timeout_s) == (HEADER_TIMEOUT_S, BODY_TIMEOUT_S)
    monkeypatch.setenv("CFSR_HEADER_TIMEOUT_S", "1.5")
    monkeypatch.setenv("CFSR_BODY_TIMEOUT_S", "2")
    s = Settings()
    assert (s.header_timeout_s, s.body_timeout_s) == (1.5, 2.0)
    for bad in ("nan", "0", "-1", "1e9"):
        monkeypatch.setenv("CFSR_BODY_TIMEOUT_S", bad)
        with pytest.raises(ValueError, match="CFSR_BODY_TIMEOUT_S"):
            Settings()
