"""Bad files never take the service down (issue 12).

- a recording truncated or rewritten while it is replayed ends the replay with a message
  instead of killing the process with SIGBUS (these run in a subprocess: a SIGBUS would kill
  pytest itself);
- every sidecar value is checked once, with bounds a real camera can reach;
- one bad file in the data folder (bad sidecar, bad size, a FIFO) never breaks the listing or
  switching, and a FIFO is never opened in a way that blocks;
- a 1-frame looping recording paces itself in whole blocks; ``loop`` set after the end resumes.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from cfsr.datfile import (
    MAX_FRAME_PIXELS,
    MAX_SIDE_PX,
    DatWriter,
    SpikeFileError,
    read_dat,
    read_sidecar,
    sidecar_path,
    write_dat,
)
from cfsr.layout import Layout
from cfsr_live.driver.source import BlockFlags, ReplayControl, SourceEnded, SourceState
from cfsr_live.replay.device import ReplayDevice
from cfsr_live.replay.pattern import pattern_recording

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "NUMBA_CACHE_DIR": str(REPO / ".cache" / "numba")}


def _isolated(code: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (a SIGBUS there fails the test, not the run)."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=REPO, env=ENV, capture_output=True, text=True, timeout=timeout,
    )


def _last_json(r: subprocess.CompletedProcess) -> dict:
    assert r.returncode == 0, (
        f"child died with {r.returncode} (-7 is SIGBUS); stderr:\n{r.stderr[-3000:]}"
    )
    return json.loads(r.stdout.strip().splitlines()[-1])


def _pattern(path: Path, steps: int, **kw) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_dat(path, pattern_recording(steps, height=kw.pop("height", 20),
                                      width=kw.pop("width", 32), **kw))
    return path


def _set_sidecar(dat: Path, **changes) -> None:
    sp = sidecar_path(dat)
    d = json.loads(sp.read_text())
    d.update(changes)
    # json writes NaN/Infinity (not strict JSON, but what Python's json reads back as floats)
    sp.write_text(json.dumps(d))


# --- 1. a file that shrinks under a running replay -----------------------------------------------


def test_truncated_under_a_running_replay_ends_it_cleanly(tmp_path):
    dat = _pattern(tmp_path / "scene.dat", 4000)
    r = _isolated(f"""
        import json, os, threading
        from cfsr_live.driver.source import ReplayControl, SourceEnded
        from cfsr_live.replay.device import ReplayDevice
        dev = ReplayDevice({str(dat)!r}, mode="paced", speed=20.0, loop=True, block_frames=64)
        dev.open()
        out = {{"blocks": 0, "ended": None}}
        playing = threading.Event()  # set once 5 blocks went through: the replay is running
        def pump():
            # what the acquisition thread does: read, touch every byte (as the ring copy does)
            while True:
                try:
                    b = dev.read_block(0.2)
                except SourceEnded as exc:
                    out["ended"] = str(exc)
                    return
                if b is not None:
                    int(b.data.sum())
                    out["blocks"] += 1
                    if out["blocks"] >= 5:
                        playing.set()
        t = threading.Thread(target=pump, daemon=True)
        t.start()
        assert playing.wait(60), f"the replay did not start: {{out}}"
        os.truncate({str(dat)!r}, 64 * 80)  # keep 80 of 4000 frames: the replay is past them
        t.join(30)
        out.update(alive=t.is_alive(), state=dev.state.value, last_error=dev.last_error,
                   ctl=dev.get_facility(ReplayControl).state())
        print(json.dumps(out))
    """)
    out = _last_json(r)
    assert not out["alive"]
    assert out["state"] == "error"
    msg = out["last_error"]
    assert "scene.dat" in msg and "shrank" in msg and "\n" not in msg
    assert out["ended"] == msg
    assert out["ctl"]["ended"] is True


def test_rewritten_shorter_file_then_controls_do_not_revive_it(tmp_path):
    dat = _pattern(tmp_path / "scene.dat", 1000)
    short = _pattern(tmp_path / "short.dat", 100)
    r = _isolated(f"""
        import json
        from cfsr_live.driver.source import ReplayControl, SourceEnded
        from cfsr_live.replay.device import ReplayDevice
        dev = ReplayDevice({str(dat)!r}, mode="unpaced", loop=True, block_frames=256)
        dev.open()
        first = dev.read_block(0).data.copy()
        # `cp short.dat scene.dat`: truncate to 0 and write the shorter content in place
        with open({str(dat)!r}, "wb") as fh:
            fh.write(open({str(short)!r}, "rb").read())
        errs = []
        for _ in range(3):
            try:
                dev.read_block(0)
            except SourceEnded as exc:
                errs.append(str(exc))
        ctl = dev.get_facility(ReplayControl)
        ctl.play(); ctl.set_loop(True); ctl.seek(0); ctl.step(5); ctl.pause(); ctl.play()
        try:
            dev.read_block(0)
            revived = True
        except SourceEnded:
            revived = False
        print(json.dumps({{"errs": errs, "state": dev.state.value, "revived": revived,
                          "delivered": dev.counters().frames_delivered,
                          "describe": dev.describe()["last_error"]}}))
    """)
    out = _last_json(r)
    assert len(out["errs"]) == 3 and all("scene.dat" in e for e in out["errs"])
    assert out["state"] == "error" and not out["revived"]
    assert out["delivered"] == 256  # the failed reads delivered and counted nothing
    assert "shrank" in out["describe"]


def test_replay_reads_are_byte_exact_and_do_not_alias(tmp_path):
    # the bounds-checked reads return the file's bytes; each block owns its array
    dat = _pattern(tmp_path / "p.dat", 700)
    rec = read_dat(dat)
    dev = ReplayDevice(dat, mode="unpaced", loop=True, block_frames=256)
    dev.open()
    blocks = [dev.read_block(0) for _ in range(4)]
    assert [b.n_frames for b in blocks] == [256, 256, 188, 256]
    assert np.array_equal(blocks[0].data, rec.packed(0, 256))
    assert np.array_equal(blocks[2].data, rec.packed(512, 700))
    assert np.array_equal(blocks[3].data, rec.packed(0, 256))
    dev.close()
    assert dev.read_block(0) is None
    dev.open()  # reopening after close reads again
    assert dev.read_block(0).n_frames == 256


# --- 4. tiny files and loop after the end --------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.t = 50.0

    def __call__(self) -> float:
        return self.t


def test_one_frame_loop_paces_in_whole_blocks(tmp_path):
    dat = _pattern(tmp_path / "one.dat", 1)
    clk = FakeClock()
    dev = ReplayDevice(dat, mode="paced", loop=True, block_frames=256, clock=clk)
    dev.open()
    frame = read_dat(dat).packed(0, 1)
    blocks = []
    for _ in range(4000):  # 0.1 s of sensor time in 25 us ticks
        clk.t += 25e-6
        b = dev.read_block(0)
        if b is not None:
            blocks.append(b)
    # 4000 steps in 256-frame blocks: 15 blocks, not 4000 one-frame blocks
    assert 14 <= len(blocks) <= 16
    assert all(b.n_frames == 256 for b in blocks)
    assert [b.index for b in blocks] == [256 * i for i in range(len(blocks))]
    assert np.array_equal(blocks[3].data, np.repeat(frame, 256, axis=0))
    assert dev.counters().loops == 256 * len(blocks)
    assert dev.counters().replay_behind_frames == 0


def test_short_loop_longer_than_one_frame(tmp_path):
    dat = _pattern(tmp_path / "few.dat", 100)
    rec = read_dat(dat)
    dev = ReplayDevice(dat, mode="unpaced", loop=True, block_frames=256)
    dev.open()
    b = dev.read_block(0)
    assert b.n_frames == 200  # two whole passes fit in a block
    assert np.array_equal(b.data, np.concatenate([rec.packed(0, 100)] * 2))
    ctl = dev.get_facility(ReplayControl)
    ctl.seek(90)  # from the middle: the rest of the pass, then whole passes again
    assert dev.read_block(0).n_frames == 10
    assert dev.read_block(0).n_frames == 200


def test_one_frame_loop_does_not_spin_a_real_clock(tmp_path):
    dat = _pattern(tmp_path / "one.dat", 1)
    dev = ReplayDevice(dat, mode="paced", loop=True, block_frames=256)
    dev.open()
    c0, t0, n = time.thread_time(), time.monotonic(), 0
    while time.monotonic() - t0 < 1.0:  # a measurement over one second of wall time, no wait
        b = dev.read_block(0.2)
        if b is not None:
            n += 1
    cpu = time.thread_time() - c0
    assert n <= 200  # 40,000 steps/s in 256-frame blocks is 156 blocks/s
    assert cpu < 0.2, f"reading a 1-frame loop used {cpu:.2f} s of CPU per second"


def test_loop_set_after_the_end_resumes(tmp_path):
    dat = _pattern(tmp_path / "a.dat", 300)
    dev = ReplayDevice(dat, mode="unpaced", loop=False, block_frames=128)
    dev.open()
    for _ in range(3):
        dev.read_block(0)
    with pytest.raises(SourceEnded):
        dev.read_block(0)
    ctl = dev.get_facility(ReplayControl)
    assert ctl.state()["ended"]
    ctl.set_loop(True)
    assert not ctl.state()["ended"]
    b = dev.read_block(0)
    assert b is not None and b.index == 300 and b.flags & BlockFlags.DISCONTINUITY
    assert np.array_equal(b.data, read_dat(dat).packed(0, 128))
    for _ in range(5):  # and it keeps looping
        assert dev.read_block(0) is not None
    assert dev.state == SourceState.STREAMING


# --- 2. sidecar values ---------------------------------------------------------------------------

BAD_SIDECARS = [
    ("width", "abc", "integer in [1, 65535]"),
    ("width", None, "integer in [1, 65535]"),
    ("width", 0, "integer in [1, 65535]"),
    ("width", 70_000, "integer in [1, 65535]"),
    ("width", 31.5, "integer in [1, 65535]"),
    ("width", True, "integer in [1, 65535]"),
    ("height", -250, "integer in [1, 65535]"),
    ("height", 10**9, "integer in [1, 65535]"),
    ("head_cols", -16, "integer in [0, 65535]"),
    ("flipud", "yes", "true or false"),
    ("frame_bytes", 99, "bytes (its geometry)"),
    ("n_frames", -1, "integer in [0, "),
    ("rate_hz", 0, "[1, 10000000] steps/s"),
    ("rate_hz", -40_000, "[1, 10000000] steps/s"),
    ("rate_hz", math.nan, "[1, 10000000] steps/s"),
    ("rate_hz", math.inf, "[1, 10000000] steps/s"),
    ("rate_hz", 2e7, "[1, 10000000] steps/s"),
    ("rate_hz", "40000", "[1, 10000000] steps/s"),
    ("gain", math.nan, "[1e-06, 1] spikes/step"),
    ("gain", 0, "[1e-06, 1] spikes/step"),
    ("gain", -0.5, "[1e-06, 1] spikes/step"),
    ("gain", 3.0, "[1e-06, 1] spikes/step"),
    # the far ends: a rate no frame ever comes at, a gain the API refuses, a 5000-digit number
    ("rate_hz", 1e-300, "[1, 10000000] steps/s"),
    ("gain", 5e-324, "[1e-06, 1] spikes/step"),
]


@pytest.mark.parametrize(("key", "value", "allowed"), BAD_SIDECARS)
def test_bad_sidecar_value_is_one_clear_error(tmp_path, key, value, allowed):
    dat = _pattern(tmp_path / "s.dat", 10, height=8, width=16)
    _set_sidecar(dat, **{key: value})
    with pytest.raises(SpikeFileError) as ei:
        read_dat(dat)
    msg = str(ei.value)
    assert "\n" not in msg
    assert "s.dat.json: " in msg and f"{key} = " in msg and allowed in msg
    shown = json.dumps(value)
    assert shown in msg
    with pytest.raises(SpikeFileError):
        read_sidecar(dat)


def test_absurd_frame_size_is_refused(tmp_path):
    dat = _pattern(tmp_path / "s.dat", 10, height=8, width=16)
    sp = sidecar_path(dat)
    side = json.loads(sp.read_text())
    side.update(width=60_000, height=60_000, frame_bytes=None)
    del side["frame_bytes"]
    sp.write_text(json.dumps(side))
    limits = f"at most {MAX_SIDE_PX} pixels a row and {MAX_FRAME_PIXELS} a frame"
    with pytest.raises(SpikeFileError, match="s.dat.json: wrong geometry: stored frame "
                       f"60000 x 60000 pixels .*{limits}"):
        read_dat(dat)


def test_good_sidecar_values_pass_and_are_normalised(tmp_path):
    dat = _pattern(tmp_path / "s.dat", 10, height=8, width=16)
    _set_sidecar(dat, width=16.0, rate_hz=1e7, gain=None)
    rec = read_dat(dat)
    assert rec.layout.width == 16 and isinstance(rec.meta["width"], int)
    assert rec.rate_hz == 1e7 and rec.gain is None
    _set_sidecar(dat, gain=1, rate_hz=1)
    assert read_dat(dat).gain == 1.0


def test_cli_info_with_a_bad_sidecar_prints_one_line_and_exits_2(tmp_path):
    dat = _pattern(tmp_path / "s.dat", 10, height=8, width=16)
    _set_sidecar(dat, rate_hz=0)
    r = subprocess.run([sys.executable, "-m", "cfsr", "info", str(dat)], cwd=REPO, env=ENV,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "s.dat.json" in lines[0] and "rate_hz = 0" in lines[0]


def test_explicit_geometry_and_rate_have_the_same_bounds(tmp_path):
    f = tmp_path / "g.dat"
    f.write_bytes(bytes(70_000 * 8 // 8))
    with pytest.raises(SpikeFileError, match="wrong geometry.*65535"):
        read_dat(f, width=70_000, height=8)
    _pattern(tmp_path / "r.dat", 10, height=8, width=16)
    for bad in (0.0, -1.0, math.nan, 1e8):
        with pytest.raises(SpikeFileError, match="rate_hz"):
            read_dat(tmp_path / "r.dat", rate_hz=bad)


def test_writer_refuses_a_sidecar_the_reader_would_refuse(tmp_path):
    with pytest.raises(SpikeFileError, match="gain"):
        DatWriter(tmp_path / "w.dat", Layout(16, 8), meta={"gain": math.nan})
    with pytest.raises(SpikeFileError, match="rate_hz"):
        DatWriter(tmp_path / "w.dat", Layout(16, 8), rate_hz=0.0)
    assert not (tmp_path / "w.dat").exists()


def test_hostile_sidecar_files(tmp_path):
    dat = _pattern(tmp_path / "s.dat", 10, height=8, width=16)
    sp = sidecar_path(dat)
    sp.write_text("[" * 100_000 + "]" * 100_000)  # nesting beyond the parser's recursion
    with pytest.raises(SpikeFileError, match="unreadable sidecar"):
        read_dat(dat)
    sp.write_text(json.dumps({"width": 16, "height": 8, "pad": "x" * (1 << 20)}))
    with pytest.raises(SpikeFileError, match="sidecar is .* bytes, more than"):
        read_dat(dat)
    sp.unlink()
    sp.mkdir()
    with pytest.raises(SpikeFileError, match="sidecar is a directory"):
        read_dat(dat)


def test_fifo_sidecar_and_fifo_recording_never_block(tmp_path):
    # in a child with a timeout: opening a FIFO for reading blocks until a writer comes
    dat = _pattern(tmp_path / "s.dat", 10, height=8, width=16)
    sidecar_path(dat).unlink()
    os.mkfifo(sidecar_path(dat))
    os.mkfifo(tmp_path / "pipe.dat")
    try:
        r = _isolated(f"""
            import json
            from cfsr.datfile import SpikeFileError, read_dat
            out = []
            for p in ({str(dat)!r}, {str(tmp_path / "pipe.dat")!r}):
                try:
                    read_dat(p)
                    out.append("opened")
                except SpikeFileError as exc:
                    out.append(str(exc))
            print(json.dumps(out))
        """, timeout=20)
    except subprocess.TimeoutExpired:
        pytest.fail("reading a FIFO sidecar or FIFO .dat blocked")
    side, pipe = _last_json(r)
    assert "s.dat.json: sidecar is a FIFO (named pipe), not a regular file" in side
    assert "pipe.dat: is a FIFO (named pipe), not a regular file" in pipe
    assert "empty" not in pipe


# --- 3. the data folder --------------------------------------------------------------------------


@pytest.fixture
def hostile_folder(tmp_path):
    data = tmp_path / "data"
    _pattern(data / "good.dat", 300)
    for name, change in (("abc.dat", {"width": "abc"}), ("null.dat", {"width": None}),
                         ("rate0.dat", {"rate_hz": 0}), ("nan.dat", {"gain": math.nan}),
                         ("wide.dat", {"width": 70_000})):
        _set_sidecar(_pattern(data / name, 50), **change)
    (data / "partial.dat").write_bytes(bytes(12_500 + 7))
    (data / "empty.dat").write_bytes(b"")
    _pattern(data / "junk.dat", 20)
    sidecar_path(data / "junk.dat").write_text("{not json")
    os.mkfifo(data / "pipe.dat")
    return data


def test_catalog_survives_bad_files_and_reports_them(hostile_folder, caplog):
    from cfsr_live.service.catalog import SourceCatalog
    from cfsr_live.service.settings import Settings, SourceSpec

    cat = SourceCatalog(Settings(data_dir=hostile_folder, source=SourceSpec("demo")))
    with caplog.at_level("INFO", logger="cfsr.catalog"):
        entries = cat.scan()
        cat.scan()  # a second scan (every GET /api/sources) logs nothing new
    good = entries["file:good.dat"]
    assert good.usable and good.note is None and good.frames == 300
    bad = {k: e for k, e in entries.items() if k.startswith("file:") and k != "file:good.dat"}
    assert set(bad) == {f"file:{n}.dat" for n in
                        ("abc", "null", "rate0", "nan", "wide", "partial", "empty", "junk",
                         "pipe")}
    for k, e in bad.items():
        assert not e.usable and e.note, k
        assert str(hostile_folder) not in e.note  # clients see names, not server paths
        json.dumps(e.public(), allow_nan=False)  # what GET /api/sources serialises
        with pytest.raises(ValueError, match="cannot be opened"):
            cat.spec_for(k)
    assert "width = \"abc\"" in bad["file:abc.dat"].note
    assert "rate_hz = 0" in bad["file:rate0.dat"].note
    assert "FIFO (named pipe)" in bad["file:pipe.dat"].note
    assert "empty" not in bad["file:pipe.dat"].note
    assert "empty file" in bad["file:empty.dat"].note
    assert "multiple" in bad["file:partial.dat"].note
    logged = [r.getMessage() for r in caplog.records]
    assert len(logged) == len(bad)
    assert all("skipping" in m for m in logged)
    # switching to a good recording (and to anything else listed) still works
    assert cat.spec_for("file:good.dat").path == (hostile_folder / "good.dat").resolve()
    assert cat.spec_for("demo").kind == "demo"


@pytest.mark.timeout(600)
def test_service_stays_up_through_bad_files(hostile_folder):
    from livehelpers import LiveServer

    scene = _pattern(hostile_folder / "scene.dat", 20_000)
    with LiveServer(["--replay", str(scene), "--data-dir", str(hostile_folder)]) as s:
        s.wait_for(lambda x: x["source"]["state"] == "streaming"
                   and x["input_steps_per_s"] > 0, what="replay streaming")
        r = s.get("/api/sources")
        assert r.status_code == 200, r.text
        items = {d["id"]: d for d in r.json()}
        assert "FIFO" in items["file:pipe.dat"]["note"]
        assert "rate_hz" in items["file:rate0.dat"]["note"]
        r = s.put("/api/source", json={"id": "file:abc.dat"})
        assert r.status_code == 422 and "abc.dat" in r.text
        r = s.put("/api/source", json={"id": "file:scene.dat"})
        assert r.status_code == 200, r.text
        s.wait_for(lambda x: x["source"]["state"] == "streaming", what="scene streaming")
        # shrink the file being replayed, in place: the replay ends, the service stays up
        os.truncate(scene, read_dat(scene).layout.frame_bytes * 10)
        st = s.wait_for(lambda x: x["source"]["state"] == "error", timeout=60,
                        what="replay ended by the shrunk file")
        assert "scene.dat" in st["source"]["last_error"]
        assert "shrank" in st["source"]["last_error"]
        assert s.proc.poll() is None
        assert s.get("/healthz").status_code == 200
        r = s.put("/api/source", json={"id": "file:good.dat"})
        assert r.status_code == 200, r.text
        s.wait_for(lambda x: x["source"]["state"] == "streaming"
                   and x["source"]["last_error"] is None, what="switched on")
