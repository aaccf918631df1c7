"""``cfsr serve`` start-up failures, run as a user would: one line naming the problem, exit
status 2, and nothing left behind (no shared-memory segment of the failed server, no worker).
A crashed server's segments are removed by the next start, which says so."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from livehelpers import free_port, segments_of


def _serve(args: list[str], tmp_path: Path):
    env = {k: v for k, v in os.environ.items() if k != "CFSR_TOKEN"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "cfsr", "serve", "--host", "127.0.0.1", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
        env={**env, "CFSR_CACHE_DIR": str(tmp_path / "cache")},
    )
    out, err = proc.communicate(timeout=300)
    return proc.pid, proc.returncode, out, err


def _check_one_line(pid, rc, err, *needles):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, (rc, err)
    assert len(lines) == 1, err
    assert lines[0].startswith("cfsr serve: error:"), lines[0]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    assert segments_of(pid) == []


@pytest.fixture
def bad_dat(tmp_path) -> Path:
    p = tmp_path / "data" / "bad.dat"
    p.parent.mkdir()
    p.write_bytes(os.urandom(1000))  # not a whole 400 x 250 frame
    return p


def test_bad_replay_file(tmp_path, bad_dat):
    pid, rc, out, err = _serve(["--replay", str(bad_dat), "--port", str(free_port()),
                                "--data-dir", str(bad_dat.parent)], tmp_path)
    _check_one_line(pid, rc, err, "bad.dat", "not a multiple of the frame size")
    assert "viewer at" not in out


@pytest.mark.parametrize("port, says", [("70000", "70000 is not a port"),
                                        ("0", "0 is not a port"),
                                        ("http", "'http' is not a port number")])
def test_invalid_port(tmp_path, port, says):
    pid, rc, out, err = _serve(["--port", port], tmp_path)
    _check_one_line(pid, rc, err, "--port", says)


def test_taken_port(tmp_path, bad_dat):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        pid, rc, out, err = _serve(["--replay", str(bad_dat), "--port", str(port),
                                    "--data-dir", str(tmp_path / "d")], tmp_path)
    _check_one_line(pid, rc, err, f"127.0.0.1:{port}", "in use")


def test_unusable_data_folder(tmp_path, bad_dat):
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    pid, rc, out, err = _serve(["--port", str(free_port()), "--data-dir", str(not_a_folder)],
                               tmp_path)
    _check_one_line(pid, rc, err, "data folder", "is not a folder")
    below_a_file = not_a_folder / "sub"
    pid, rc, out, err = _serve(["--port", str(free_port()), "--data-dir", str(below_a_file)],
                               tmp_path)
    _check_one_line(pid, rc, err, "data folder", "cannot be created")


def test_non_loopback_without_token(tmp_path):
    pid, rc, out, err = _serve(["--host", "0.0.0.0", "--port", str(free_port())], tmp_path)
    _check_one_line(pid, rc, err, "requires an access token")


def test_crashed_servers_segments_are_removed_and_reported(tmp_path, bad_dat):
    if not Path("/dev/shm").is_dir():
        pytest.skip("no /dev/shm on this machine")
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = [Path("/dev/shm") / f"cfsr-ring-{dead.pid}-0-1", Path("/dev/shm") /
             f"cfsr-frame-{dead.pid}-1-2"]
    for p in stale:
        p.write_bytes(b"\0" * 4096)
    try:
        pid, rc, out, err = _serve(["--replay", str(bad_dat), "--port", str(free_port()),
                                    "--data-dir", str(bad_dat.parent)], tmp_path)
        assert not any(p.exists() for p in stale)
        # at least these two: the server removes every dead server's files, and on a shared
        # host another run may have left some
        m = re.search(r"removed (\d+) shared-memory file\(s\) left by a server", out)
        assert m and int(m.group(1)) >= len(stale), out
        _check_one_line(pid, rc, err, "bad.dat")
    finally:
        for p in stale:
            p.unlink(missing_ok=True)
