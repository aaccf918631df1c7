"""Hostile inputs, third round, at unit level: every size from outside bounded before anything
is allocated, bodies and connections bounded, a recording readable however it ends.

The same classes against a running server are rows 11-18 of the fault matrix
(``tests/test_fault_matrix_hostile.py``); these tests pin each mechanism down on its own.
"""

from __future__ import annotations

import asyncio
import json
import logging
import subprocess
import sys
import time
import tracemalloc

import numpy as np
import pytest
from livehelpers import REPO, write_pattern

from cfsr.datfile import (
    MAX_SIDECAR_DIGITS,
    SIDECAR_RESERVE_BYTES,
    DatWriter,
    SpikeFileError,
    read_dat,
    sidecar_path,
)
from cfsr.layout import Layout


# -- sizes from a sidecar -------------------------------------------------------------------------
def test_a_number_of_thousands_of_digits_is_named_with_its_file_and_key(tmp_path):
    dat = write_pattern(tmp_path / "w.dat", 10)
    side = sidecar_path(dat)
    side.write_text('{"width": ' + "9" * 5000 + ', "height": 250}')
    t = time.perf_counter()
    with pytest.raises(SpikeFileError) as ei:
        read_dat(dat)
    assert time.perf_counter() - t < 1.0
    msg = str(ei.value)
    assert "w.dat.json" in msg and "width = <a number of 5000 digits>" in msg, msg
    assert f"at most {MAX_SIDECAR_DIGITS} digits" in msg and "\n" not in msg
    side.write_text('{"scene": {"seeds": [1, ' + "7" * 300 + "]}}")  # nested, in any key
    with pytest.raises(SpikeFileError, match=r"scene\.seeds\.1 = <a number of 300 digits>"):
        read_dat(dat)


def test_the_ring_is_capped_in_bytes():
    from cfsr_live.shm.ring import DEFAULT_MAX_BYTES, SpikeRing

    # 1024 x 1024 at 10 MHz, 0.25 s: 2.5 million frames of 128 kB asked (328 GB)
    fb = 1024 * 1024 // 8
    want = 0.25 * 1e7
    assert SpikeRing.nbytes_for(int(want // 256), 256, fb) > 300e9
    n = SpikeRing.slots_for(want, 256, fb, max_bytes=DEFAULT_MAX_BYTES)
    assert SpikeRing.nbytes_for(n, 256, fb) <= DEFAULT_MAX_BYTES
    assert n >= 8
    # a small wish is kept as it is
    assert SpikeRing.slots_for(0.25 * 40_000, 256, 12_500, max_bytes=DEFAULT_MAX_BYTES) == 40
    # 8 blocks that do not fit: refused, naming both sizes
    with pytest.raises(ValueError, match=r"needs \d+ bytes, over the ring's cap of 1000000 bytes"):
        SpikeRing.slots_for(1e6, 256, 12_500, max_bytes=1_000_000)
    with pytest.raises(ValueError, match="over the ring's cap"):
        SpikeRing.create(100, 256, 12_500, max_bytes=10_000_000)


def test_the_ring_cap_fits_the_memory_available(monkeypatch):
    from cfsr.cli import _common
    from cfsr_live.service.commands.serve import _fit_ring_to_memory
    from cfsr_live.service.settings import Settings

    said = []
    st = Settings(ring_max_bytes=1 << 30)
    monkeypatch.setattr(_common, "available_memory", lambda: 2 << 30)  # 2 GiB free
    _fit_ring_to_memory(st, said.append)
    assert st.ring_max_bytes == 512 << 20 and "512 MiB" in said[0]
    monkeypatch.setattr(_common, "available_memory", lambda: 64 << 30)
    st = Settings(ring_max_bytes=1 << 30)
    _fit_ring_to_memory(st, said.append)
    assert st.ring_max_bytes == 1 << 30 and len(said) == 1


# -- bodies ---------------------------------------------------------------------------------------
def _run_body(mw, body_parts, *, delay: float = 0.0, stall: bool = False):
    """Drive the middleware with one PUT whose body comes in ``body_parts`` (``delay`` s before
    each; ``stall``: then nothing more, for ever); what the app saw and what was sent back."""
    seen: dict = {"reads": 0}
    sent: list[dict] = []

    async def receive():
        seen["reads"] += 1
        if not body_parts:
            await asyncio.sleep(3600)
        await asyncio.sleep(delay)
        part = body_parts.pop(0)
        return {"type": "http.request", "body": part, "more_body": bool(body_parts) or stall}

    async def send(msg):
        sent.append(msg)

    async def main():
        scope = {"type": "http", "method": "PUT", "path": "/api/config", "headers": []}
        await mw(scope, receive, send)

    asyncio.run(main())
    status = next((m["status"] for m in sent if m["type"] == "http.response.start"), None)
    headers = dict(next((m["headers"] for m in sent if m["type"] == "http.response.start"), []))
    return seen, status, headers


async def _ok_app(scope, receive, send):
    msg = await receive()
    await send({"type": "http.response.start", "status": 200, "headers": []})
    await send({"type": "http.response.body", "body": msg["body"]})


def test_the_token_is_checked_before_a_byte_of_body_is_read():
    from cfsr_live.service.body import StrictJsonBody

    mw = StrictJsonBody(_ok_app, admit=lambda scope: (401, "no token", []))
    seen, status, headers = _run_body(mw, [b"{", b"}"])
    assert status == 401 and seen["reads"] == 0
    assert headers.get(b"connection") == b"close"  # the unread body ends the connection


def test_a_body_has_a_deadline_and_a_slot():
    from cfsr_live.service.body import StrictJsonBody

    mw = StrictJsonBody(_ok_app, timeout_s=0.3)
    t = time.monotonic()
    _, status, headers = _run_body(mw, [b"{"], stall=True)  # one byte, then nothing
    assert status == 408 and time.monotonic() - t < 2
    assert headers.get(b"connection") == b"close" and mw.in_flight == 0
    _, status, _ = _run_body(mw, [b'{"max_fps":', b" 10}"], delay=0.05)
    assert status == 200
    mw.in_flight = mw.max_in_flight  # every slot taken by stalled bodies
    seen, status, headers = _run_body(mw, [b"{}"])
    assert status == 503 and seen["reads"] == 0 and headers.get(b"retry-after") == b"1"


# -- the log --------------------------------------------------------------------------------------
def test_the_same_log_line_is_let_through_once_per_window():
    from cfsr_live.service.httpproto import RepeatedLogFilter

    flt = RepeatedLogFilter(window_s=60)
    rec = lambda msg: logging.LogRecord("asyncio", logging.ERROR, __file__, 1, msg, (), None)  # noqa: E731
    passed = sum(flt.filter(rec("socket.accept() out of system resource")) for _ in range(5000))
    assert passed == 1
    assert flt.filter(rec("something else"))
    flt.window_s = 0  # the window over: the next one says how many were held back
    r = rec("socket.accept() out of system resource")
    assert flt.filter(r) and "4999 more like this" in r.msg


def test_invalid_utf8_from_a_client_is_one_quiet_line():
    from cfsr_live.service.httpproto import RepeatedLogFilter

    try:
        b"\xff".decode()
    except UnicodeDecodeError:
        exc = sys.exc_info()
    r = logging.LogRecord("uvicorn.error", logging.ERROR, __file__, 1,
                          "Invalid UTF-8 sequence received from client.", (), exc)
    logging.getLogger("uvicorn.error").setLevel(logging.INFO)
    assert RepeatedLogFilter().filter(r)
    assert r.levelno == logging.INFO and r.exc_info is None


# -- the command line -----------------------------------------------------------------------------
def test_times_are_checked_before_a_list_is_made():
    from cfsr.cli._common import parse_times

    spec = parse_times("0:1000000000000000000:1")
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=r"outside the recording \(0..2999\)"):
            spec.resolve(3000)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, peak
    assert parse_times("10:20:5").resolve(3000) == [10, 15]
    assert parse_times("0::1000").resolve(3000) == [0, 1000, 2000]


# -- recordings -----------------------------------------------------------------------------------
def test_the_sidecar_exists_before_the_first_byte_of_spikes(tmp_path):
    lay = Layout(256, 128)
    w = DatWriter(tmp_path / "r.dat", lay, meta={"gain": 0.25})
    side = sidecar_path(tmp_path / "r.dat")
    assert (tmp_path / "r.dat").stat().st_size == 0
    assert side.stat().st_size == SIDECAR_RESERVE_BYTES  # the room for the final one
    w.write_packed(np.zeros((3, lay.frame_bytes), np.uint8))
    # a crash here (nothing closes the writer): the file still opens with its own geometry
    rec = read_dat(tmp_path / "r.dat")
    assert (rec.layout.width, rec.layout.height, rec.n_frames, rec.gain) == (256, 128, 3, 0.25)
    w.close()
    assert json.loads(side.read_text())["n_frames"] == 3
    assert side.stat().st_size < 2048  # the final sidecar is plain


def test_a_recording_that_got_no_frame_leaves_no_file(tmp_path):
    from cfsr_live.service.recorder import Recorder
    from cfsr_live.shm.ring import SpikeRing

    lay = Layout(64, 32)
    ring = SpikeRing.create(8, 16, lay.frame_bytes, directory=tmp_path)
    try:
        (tmp_path / "rec").mkdir()
        r = Recorder(ring, tmp_path / "rec" / "e.dat", lay, rate_hz=40_000.0)
        # while it waits for frames its files have no names yet (a SIGKILL now leaves
        # nothing), but the name is held: a second recording of it is refused
        assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == []
        with pytest.raises(FileExistsError):
            Recorder(ring, tmp_path / "rec" / "e.dat", lay, rate_hz=40_000.0)
        st = r.stop()
        assert st.frames == 0 and st.path is None
        assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == []
        # with frames it is kept, and shown relative to the data folder
        r = Recorder(ring, tmp_path / "rec" / "f.dat", lay, rate_hz=40_000.0)
        for k in range(20):
            ring.write(k * 16, np.zeros((16, lay.frame_bytes), np.uint8))
            time.sleep(0.005)
            if r.frames:
                break
        st = r.stop()
        assert st.frames > 0 and st.path == "rec/f.dat", st
        assert read_dat(tmp_path / "rec" / "f.dat").n_frames == st.frames
    finally:
        ring.close()


def test_cli_record_with_no_frame_leaves_no_file(tmp_path):
    """``cfsr record`` from a source that gives nothing: one line, exit 2, no file."""
    empty = tmp_path / "empty.dat"
    DatWriter(empty, Layout(400, 250)).close()  # a recording of 0 frames, with a sidecar
    out = tmp_path / "out.dat"
    r = subprocess.run([sys.executable, "-m", "cfsr", "record", "--replay", str(empty),
                        "--frames", "10", str(out)], cwd=REPO, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert not out.exists() and not sidecar_path(out).exists()


def test_info_says_sidecar_only_when_there_is_one(tmp_path):
    dat = write_pattern(tmp_path / "p.dat", 20)
    sidecar_path(dat).unlink()
    with open(dat, "ab") as fh:
        fh.write(b"\0" * 100)  # a partial frame: the reader notes it in the metadata

    def info() -> dict:
        r = subprocess.run([sys.executable, "-m", "cfsr", "info", str(dat), "--json", "-q"],
                           cwd=REPO, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)

    assert info()["sidecar"] is False
    w = DatWriter(tmp_path / "q.dat", Layout(400, 250))  # provisional: never closed
    w.write_packed(np.zeros((2, 12_500), np.uint8))
    dat = tmp_path / "q.dat"
    got = info()
    assert got["sidecar"] is True and got["sidecar_final"] is False


def test_the_library_simulation_is_bounded_as_the_cli(tmp_path):
    """``simulate_to_dat`` refuses what ``cfsr simulate`` refuses, by its argument names,
    before a file exists (the library call started writing 12.5 TB, or tracebacked on a
    74.5 GiB allocation, where the CLI said no)."""
    from cfsr.simulate import simulate_to_dat

    out = tmp_path / "x.dat"
    for kw, name in (({"steps": 1_000_000_000}, "steps"),
                     ({"steps": 200_000, "gt_every": 1}, "gt_every"),
                     ({"steps": 10, "width": 100_000, "height": 100_000}, "width"),
                     ({"steps": 10, "start": 10**21}, "start")):
        with pytest.raises(ValueError, match=name):
            simulate_to_dat("disk", path=out, **kw)
        assert list(tmp_path.iterdir()) == [], kw
    assert simulate_to_dat("disk", 20, out, gt_every=None, height=16, width=32) == out
