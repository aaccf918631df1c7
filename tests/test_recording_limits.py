"""Recording never leaves an unreadable file: a full disk trims the partial frame and the
sidecar is written atomically; a size cap and the free space stop a recording cleanly
(issue 12, item 9)."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from livehelpers import LiveServer, write_pattern

import cfsr
from cfsr.datfile import DatWriter, sidecar_path
from cfsr.layout import Layout

LAY = Layout(400, 250)


@contextlib.contextmanager
def tiny_tmpfs(where: Path, size: str):
    """A real filesystem that fills up: a tmpfs of ``size`` (needs root, as in CI)."""
    where.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {r.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def test_full_disk_keeps_whole_frames_and_a_whole_sidecar(tmp_path):
    with tiny_tmpfs(tmp_path / "fs", "1m") as fs:
        filler = fs / "filler"
        filler.write_bytes(b"\0" * 100_000)
        path = fs / "rec.dat"
        block = (np.arange(7 * LAY.frame_bytes) % 251).astype(np.uint8).reshape(7, -1)
        w = DatWriter(path, LAY, meta={"gain": 0.5})
        with pytest.raises(OSError) as exc:
            for _ in range(100):  # 100 x 7 frames = 8.75 MB > 1 MB
                w.write_packed(block)
        assert exc.value.errno == 28  # ENOSPC, not a made-up error
        size = path.stat().st_size
        assert size % LAY.frame_bytes == 0 and size == w.n_frames * LAY.frame_bytes > 0
        filler.unlink()  # room again for the sidecar
        w.close()
        rec = cfsr.read_dat(path)
        assert rec.n_frames == w.n_frames
        np.testing.assert_array_equal(rec.packed(0, 1)[0], block[0])
        assert json.loads(sidecar_path(path).read_text())["n_frames"] == w.n_frames
        assert not [p for p in fs.iterdir() if p.name.endswith(".tmp")]


def test_a_full_disk_still_gets_the_final_sidecar(tmp_path):
    """Another writer fills the disk during a recording: the sidecar's space was reserved when
    the .dat was created, so the final sidecar is written in place and the recording opens
    with its own geometry (a 256 x 128 recording used to be read as 400 x 250, or not at all)."""
    lay = Layout(256, 128)
    with tiny_tmpfs(tmp_path / "fs", "200k") as fs:
        path = fs / "rec.dat"
        w = DatWriter(path, lay, meta={"gain": 0.25})
        side = sidecar_path(path)
        # before the first byte of spikes the sidecar is there, with the geometry
        early = json.loads(side.read_text())
        assert (early["width"], early["height"], early["complete"]) == (256, 128, False)
        assert "n_frames" not in early
        with pytest.raises(OSError):
            for _ in range(100):
                w.write_packed(np.zeros((3, lay.frame_bytes), np.uint8))
        # the trimmed partial frame freed a little room: another writer takes it
        with open(fs / "other", "wb", buffering=0) as f, contextlib.suppress(OSError):
            while True:
                f.write(b"\1" * 4096)
        w.close()  # the disk is full: written into the reserved space
        final = json.loads(side.read_text())
        assert final["n_frames"] == w.n_frames > 0 and "complete" not in final
        assert not [p for p in fs.iterdir() if p.name.endswith(".tmp")]
        rec = cfsr.read_dat(path)
        assert (rec.layout.width, rec.layout.height, rec.n_frames) == (256, 128, w.n_frames)
        assert rec.gain == 0.25


def test_a_full_disk_at_the_start_leaves_no_file(tmp_path):
    """Not even the sidecar's reserve fits: the writer refuses, and leaves neither file."""
    with tiny_tmpfs(tmp_path / "fs", "64k") as fs:
        with open(fs / "other", "wb", buffering=0) as f, contextlib.suppress(OSError):
            while True:
                f.write(b"\1" * 4096)
        with pytest.raises(OSError):
            DatWriter(fs / "rec.dat", LAY)
        assert sorted(p.name for p in fs.iterdir()) == ["other"]


def test_cli_record_stops_at_the_size_cap(tmp_path):
    src = write_pattern(tmp_path / "src.dat", 1000)
    out = tmp_path / "out.dat"
    r = subprocess.run([sys.executable, "-m", "cfsr", "record", "--replay", str(src),
                        "--frames", "1000", "--max-bytes", str(300 * LAY.frame_bytes + 5),
                        "-o", str(out)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "capped at 300 frames" in r.stderr
    assert cfsr.read_dat(out).n_frames == 300
    r = subprocess.run([sys.executable, "-m", "cfsr", "record", "--replay", str(src),
                        "--frames", "10", "--max-bytes", "100", "-o", str(tmp_path / "x.dat")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "less than one frame" in r.stderr


def test_live_recording_stops_cleanly_at_its_cap_and_opens(tmp_path):
    data = tmp_path / "data"
    src = write_pattern(data / "a.dat", 3000)
    with LiveServer(["--replay", str(src), "--data-dir", str(data)]) as s:
        cap = 5_000_000  # 400 frames: more than one ring block, less than a second
        r = s.post("/api/record", json={"action": "start", "name": "capped", "max_bytes": cap})
        assert r.status_code == 200, r.text
        st = s.wait_for(lambda x: not x["recording"]["recording"], timeout=60,
                        what="the recording to stop at its cap")
        rec = st["recording"]
        assert rec["stop_reason"].startswith("size cap reached"), rec
        assert rec["frames"] == cap // LAY.frame_bytes and rec["error"] is None
        path = data / "recordings" / "capped.dat"
        assert path.stat().st_size == rec["frames"] * LAY.frame_bytes
        assert cfsr.read_dat(path).n_frames == rec["frames"]
        # listed as usable and playable
        items = [x for x in s.get("/api/sources").json() if x["name"] == "recordings/capped.dat"]
        assert items and items[0]["frames"] == rec["frames"]
        assert s.put("/api/source", json={"id": items[0]["id"]}).status_code == 200
        # a cap below one block is refused up front, nothing is created
        for tiny in (1000, 100 * LAY.frame_bytes):  # under a frame, under a block
            r = s.post("/api/record", json={"action": "start", "name": "tiny", "max_bytes": tiny})
            assert r.status_code == 422 and "less than one block" in r.text, r.text
        assert not (data / "recordings" / "tiny.dat").exists()
        assert os.path.exists(path)


def test_a_live_recording_stays_readable_when_another_writer_fills_the_disk(tmp_path):
    """The live recorder on a disk another writer fills: the recording stops (disk nearly
    full, or the write fails), and its .dat opens with its own geometry and a final sidecar
    (before, the sidecar was lost 5 times of 5 and a 256 x 128 recording read as 400 x 250)."""
    from cfsr_live.service.recorder import RESERVE_BYTES, Recorder
    from cfsr_live.shm.ring import SpikeRing

    lay = Layout(256, 128)
    ring = SpikeRing.create(8, 64, lay.frame_bytes, directory=tmp_path)
    size_mb = RESERVE_BYTES // 2**20 + 24
    try:
        with tiny_tmpfs(tmp_path / "fs", f"{size_mb}m") as fs:
            rec = Recorder(ring, fs / "live.dat", lay, rate_hz=40_000.0, meta={"gain": 0.25})
            k = 0
            while rec.frames < 64 and k < 200:  # a few blocks on disk
                ring.write(k * 64, np.full((64, lay.frame_bytes), k % 251, np.uint8))
                k += 1
                time.sleep(0.01)
            with open(fs / "other", "wb", buffering=0) as f, contextlib.suppress(OSError):
                while True:  # another writer takes every byte left
                    f.write(b"\1" * 65536)
            for _ in range(100):  # the recorder keeps being fed until it stops
                if not rec.running:
                    break
                ring.write(k * 64, np.zeros((64, lay.frame_bytes), np.uint8))
                k += 1
                time.sleep(0.02)
            st = rec.stop()
            assert st.frames > 0 and st.stop_reason is not None, st
            assert not (st.error or "").count("sidecar"), st.error
            side = json.loads(sidecar_path(fs / "live.dat").read_text())
            assert side["n_frames"] == st.frames and "complete" not in side
            got = cfsr.read_dat(fs / "live.dat")
            assert (got.layout.width, got.layout.height, got.n_frames) == (256, 128, st.frames)
            assert got.gain == 0.25
    finally:
        ring.close()


_KILLED_WRITER = r"""
import os, sys
import numpy as np
from cfsr.layout import Layout
from cfsr_live.service.recorder import FolderDatWriter
lay = Layout(256, 128)
fd = os.open(sys.argv[1], os.O_RDONLY | os.O_DIRECTORY)
w = FolderDatWriter(fd, "k.dat", lay, rate_hz=40000.0, meta={"gain": 0.25})
print("open", flush=True)
if sys.stdin.readline().strip() == "write":
    w.write_packed(np.full((3, lay.frame_bytes), 7, np.uint8))
    print("wrote", flush=True)
sys.stdin.readline()
"""


def _killed_writer(folder: Path, write: bool) -> None:
    """A process that opens a recording ``k.dat`` in ``folder`` (and writes 3 frames when
    ``write``), then is killed by SIGKILL: nothing of it runs after the signal."""
    from cfsr_live.service.recorder import FolderDatWriter

    p = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(folder)], text=True,
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert p.stdout.readline().strip() == "open"
        # the name is held while that recording waits for its first frames, though no file
        # has it yet: a second recording of the name is refused
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            with pytest.raises(FileExistsError):
                FolderDatWriter(fd, "k.dat", Layout(256, 128), rate_hz=40000.0)
        finally:
            os.close(fd)
        if write:
            p.stdin.write("write\n")
            p.stdin.flush()
            assert p.stdout.readline().strip() == "wrote"
        p.kill()
    finally:
        p.kill()
        p.wait(60)


def test_a_recording_killed_before_its_first_frame_leaves_no_file(tmp_path):
    """SIGKILL before the first block used to leave an empty .dat (which nothing opens) and a
    sidecar: the files get their names only with the first frames. Killed after them, the
    recording opens with its own geometry (its reserved sidecar) and the frames on disk."""
    folder = tmp_path / "rec"
    folder.mkdir()
    _killed_writer(folder, write=False)
    assert sorted(p.name for p in folder.iterdir()) == []
    _killed_writer(folder, write=True)  # the name is free again once its holder is gone
    assert sorted(p.name for p in folder.iterdir()) == ["k.dat", "k.dat.json"]
    rec = cfsr.read_dat(folder / "k.dat")
    assert (rec.layout.width, rec.layout.height, rec.n_frames, rec.gain) == (256, 128, 3, 0.25)


def test_a_recording_with_no_frame_and_one_with_frames(tmp_path):
    """Closed with no frame: no file; with frames: the .dat and its final sidecar, and a
    name that another process took meanwhile is never replaced."""
    from cfsr_live.service.recorder import FolderDatWriter

    lay = Layout(256, 128)
    fd = os.open(tmp_path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        w = FolderDatWriter(fd, "a.dat", lay, rate_hz=40000.0)
        w.close()
        assert list(tmp_path.iterdir()) == []
        w = FolderDatWriter(fd, "a.dat", lay, rate_hz=40000.0)
        w.write_packed(np.zeros((2, lay.frame_bytes), np.uint8))
        w.close()
        assert json.loads(sidecar_path(tmp_path / "a.dat").read_text())["n_frames"] == 2
        assert cfsr.read_dat(tmp_path / "a.dat").n_frames == 2
        w = FolderDatWriter(fd, "b.dat", lay, rate_hz=40000.0)
        (tmp_path / "b.dat").write_bytes(b"someone else's")
        with pytest.raises(FileExistsError):
            w.write_packed(np.zeros((2, lay.frame_bytes), np.uint8))
        w.discard()
        assert (tmp_path / "b.dat").read_bytes() == b"someone else's"
        assert not (tmp_path / "b.dat.json").exists()
    finally:
        os.close(fd)
