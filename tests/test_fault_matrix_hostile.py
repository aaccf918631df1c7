"""The fault matrix, second table: hostile files and requests against a running ``cfsr serve``.

Each row is one reproduction of something a hostile (or careless) user did to the service: a
file the service writes, follows or lists, a request body, a header, a signal. The rows of
:data:`ROWS` run in order against one server (started with a token and ``--log-level trace``,
so the last row can read the whole log for secrets); after each, the service must still be up,
serve frames and hold exactly its ring and frame slot in ``/dev/shm``. The rows that need a
process of their own (signals, two servers on one folder, start-up flags) are separate tests.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from livehelpers import REPO, LiveServer, segments_of, write_pattern, ws_frames

pytestmark = [pytest.mark.timeout(900)]

TOKEN = "hostile-matrix-token-7f3a9c"


class Ctx:
    def __init__(self, server: LiveServer, data: Path, outside: Path) -> None:
        self.s = server
        self.data = data
        self.outside = outside

    def listing(self) -> list[dict]:
        r = self.s.get("/api/sources")
        assert r.status_code == 200, r.text[:500]
        return r.json()

    def switch_id(self, sid: str) -> httpx.Response:
        return self.s.put("/api/source", json={"id": sid})

    def raw(self, method: str, path: str, body: bytes, ctype: str, **kw) -> httpx.Response:
        headers = {"Content-Type": ctype, **self.s.headers(), **kw.pop("headers", {})}
        return httpx.request(method, self.s.url + path, content=body, headers=headers,
                             timeout=60, **kw)


def _record(c: Ctx, name: str) -> httpx.Response:
    """Start a recording, capped (were it to start, it must not fill the disk)."""
    return c.s.post("/api/record", json={"action": "start", "name": name,
                                         "max_bytes": 4_000_000})


def _short(r: httpx.Response) -> str:
    return f"{r.status_code} {r.text[:300]}"


# -- rows -----------------------------------------------------------------------------------------
def row_symlink_loop_in_the_data_folder(c: Ctx) -> None:
    loop = c.data / "loops"
    loop.mkdir()
    (loop / "self.dat").symlink_to(loop / "self.dat")  # ELOOP on stat
    (loop / "a.dat").symlink_to(loop / "b.dat")
    (loop / "b.dat").symlink_to(loop / "a.dat")
    (loop / "up").symlink_to(c.data)  # a folder link back up: never followed
    try:
        items = c.listing()
        noted = {x["name"]: x["note"] for x in items if x["name"].startswith("loops/")}
        assert noted and all(noted.values()), noted
        assert any("symbolic link" in n or "loop" in n for n in noted.values()), noted
        r = c.switch_id("sim:pattern")
        assert r.status_code == 200, _short(r)
        r = c.switch_id(c.source_id("a.dat"))
        assert r.status_code == 200, _short(r)
    finally:
        for p in loop.iterdir():
            p.unlink()
        loop.rmdir()


def row_recording_larger_than_the_display(c: Ctx) -> None:
    from cfsr.datfile import write_dat
    from cfsr_live.replay.pattern import pattern_recording

    big = c.data / "big.dat"
    write_dat(big, pattern_recording(4, height=1032, width=1024))
    items = [x for x in c.listing() if x["name"] == "big.dat"]
    assert items, "big.dat is not listed"
    before = c.s.status()["source"]["name"]
    r = c.switch_id(items[0]["id"])
    assert r.status_code == 422, _short(r)
    assert "1056768" in r.text.replace(",", "") and "1048576" in r.text.replace(",", ""), r.text
    assert c.s.status()["source"]["name"] == before  # the old source keeps running
    assert c.s.get("/readyz").status_code == 200
    big.unlink()
    big.with_name("big.dat.json").unlink()


def row_dangling_link_as_recording_name(c: Ctx) -> None:
    rec = c.data / "recordings"
    rec.mkdir(exist_ok=True)
    target = c.outside / "evil-target.dat"
    (rec / "evil.dat").symlink_to(target)
    try:
        r = _record(c, "evil")
        assert r.status_code == 409, _short(r)
        assert not target.exists() and not target.with_name("evil-target.dat.json").exists()
        assert (rec / "evil.dat").is_symlink()
        # a sidecar name that is a link is refused too: the recording would rename over it
        (rec / "side.dat.json").symlink_to(c.outside / "side.json")
        r = _record(c, "side")
        assert r.status_code == 409, _short(r)
        assert not (rec / "side.dat").exists()
    finally:
        for n in ("evil.dat", "side.dat.json"):
            (rec / n).unlink(missing_ok=True)


def row_recordings_folder_is_a_link(c: Ctx) -> None:
    rec = c.data / "recordings"
    moved = c.data / "recordings.real"
    rec.rename(moved)
    (c.data / "recordings").symlink_to(c.outside)
    try:
        before = set(os.listdir(c.outside))
        r = _record(c, "outside")
        assert r.status_code == 409, _short(r)
        assert "link" in r.text, r.text
        assert set(os.listdir(c.outside)) == before
    finally:
        (c.data / "recordings").unlink()
        moved.rename(rec)


def row_recording_is_created_exclusively(c: Ctx) -> None:
    # what a second server on the same folder does: the name appears between check and open
    rec = c.data / "recordings"
    rec.mkdir(exist_ok=True)
    (rec / "taken.dat").write_bytes(b"\0" * 12_500)
    r = _record(c, "taken")
    assert r.status_code == 409, _short(r)
    assert (rec / "taken.dat").stat().st_size == 12_500
    (rec / "taken.dat").unlink()


_CTYPES = ("application/JSON", "Application/Json", "APPLICATION/JSON; charset=utf-8",
           "application/vnd.api+json", "text/plain", "")
_NAN_BODIES = (
    ("PUT", "/api/config", b'{"max_fps": NaN}'),
    ("PUT", "/api/config", b'{"params": {"window": Infinity}}'),
    ("POST", "/api/record", b'{"action": "start", "max_bytes": NaN}'),
    ("PUT", "/api/source", b'{"id": NaN}'),
    ("POST", "/api/session", b'{"token": NaN}'),
    ("PUT", "/api/replay", b'{"speed": -Infinity}'),
)


def row_nan_in_any_content_type_spelling(c: Ctx) -> None:
    bad = []
    for ctype in _CTYPES:
        for method, path, body in _NAN_BODIES:
            r = c.raw(method, path, body, ctype)
            if r.status_code != 422:
                bad.append(f"{method} {path} [{ctype}]: {_short(r)}")
    assert not bad, "\n".join(bad)


_STRICT = (
    ("PUT", "/api/config", {"max_fps": True}),
    ("PUT", "/api/config", {"max_fps": "30"}),
    ("PUT", "/api/config", {"display": {"gain_mode": "fixed", "gain": True}}),
    ("PUT", "/api/config", {"params": {"window": "32"}}),
    ("PUT", "/api/config", {"params": {"window": True}}),
    ("PUT", "/api/config", {"params": {"window": 32.5}}),
    ("PUT", "/api/config", {"method": 1}),
    ("POST", "/api/record", {"action": "start", "max_frames": True}),
    ("POST", "/api/record", {"action": "start", "max_frames": "100"}),
    ("PUT", "/api/replay", {"speed": True}),
    ("PUT", "/api/replay", {"playing": 1}),
    ("POST", "/api/replay/step", {"n": "5"}),
    ("POST", "/api/replay/seek", {"position": False}),
    ("PUT", "/api/source", {"id": 5}),
    ("PUT", "/api/config", {"display": {"gain_mode": "fixed", "gain": 1e-300}}),
)


def row_strict_types(c: Ctx) -> None:
    before = c.s.get("/api/config").json()
    bad = []
    for method, path, body in _STRICT:
        r = c.raw(method, path, json.dumps(body).encode(), "application/json")
        if r.status_code != 422:
            bad.append(f"{method} {path} {body}: {_short(r)}")
    assert not bad, "\n".join(bad)
    after = c.s.get("/api/config").json()
    assert after["max_fps"] == before["max_fps"] and after["params"] == before["params"]


def row_error_quotes_little(c: Ctx) -> None:
    for size in (100_000, 20_000_000):
        name = "x" * size
        for method, path, body in (("PUT", "/api/config", {"method": name}),
                                   ("PUT", "/api/source", {"id": name}),
                                   ("POST", "/api/record", {"action": "start", "name": name}),
                                   ("PUT", "/api/config", {"params": {name: 1}})):
            r = c.raw(method, path, json.dumps(body).encode(), "application/json")
            assert r.status_code in (413, 422), (method, path, size, r.status_code)
            assert len(r.content) < 2048, (method, path, size, len(r.content))


def row_session_attempts_are_throttled(c: Ctx) -> None:
    codes = []
    for _ in range(40):
        r = httpx.post(c.s.url + "/api/session", json={"token": "wrong"}, timeout=30)
        codes.append(r.status_code)
    assert 429 in codes, codes
    assert set(codes) <= {401, 429}, codes
    # the right token is throttled too while the window lasts (else it could be guessed
    # through the throttle); it passes once the window is over
    r = httpx.post(c.s.url + "/api/session", json={"token": TOKEN}, timeout=30)
    assert r.status_code == 429 and "retry-after" in r.headers, _short(r)
    wait_s = float(r.headers["retry-after"])
    assert wait_s <= 60
    time.sleep(wait_s + 0.5)
    r = httpx.post(c.s.url + "/api/session", json={"token": TOKEN}, timeout=30)
    assert r.status_code == 200, _short(r)


def row_logout_invalidates_the_session(c: Ctx) -> None:
    r = httpx.post(c.s.url + "/api/session", json={"token": TOKEN}, timeout=30)
    assert r.status_code == 200, _short(r)
    cookie = r.cookies.get("cfsr_session")
    assert cookie
    jar = {"cfsr_session": cookie}
    assert httpx.get(c.s.url + "/api/status", cookies=jar, timeout=30).status_code == 200
    r = httpx.delete(c.s.url + "/api/session", cookies=jar, timeout=30)
    assert r.status_code == 200
    # the old cookie value, replayed (a copy kept by anyone), is no longer valid
    assert httpx.get(c.s.url + "/api/status", cookies=jar, timeout=30).status_code == 401
    st = httpx.get(c.s.url + "/api/session", cookies=jar, timeout=30).json()
    assert st["authenticated"] is False


def row_half_sent_headers_time_out(c: Ctx) -> None:
    t0 = time.monotonic()
    with socket.create_connection(("127.0.0.1", c.s.port), timeout=60) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        try:
            data = sock.recv(4096)  # the server closes (or answers 408) without a full header
        except TimeoutError:
            data = None
    took = time.monotonic() - t0
    assert data is not None, "the connection was still open after 60 s"
    assert took < 30, took


def row_listing_cap_is_global(c: Ctx) -> None:
    many = c.data / "many"
    for i in range(600):
        d = many / f"d{i:03d}"
        d.mkdir(parents=True)
        (d / "x.dat").write_bytes(b"")
    flat = c.data / "flat"
    flat.mkdir()
    for i in range(2000):
        (flat / f"f{i:04d}.dat").write_bytes(b"")
    try:
        items = c.listing()
        files = [x for x in items if x["kind"] == "file"]
        cut = [x for x in files if "listing stops" in (x["note"] or "")]
        assert len(cut) == 1 and files[-1] == cut[0], "the cut is not said, or not last"
        assert len(files) == 500 + 1, len(files)
        assert any(x["name"] == "a.dat" for x in items)
        r = c.switch_id(cut[0]["id"])
        assert r.status_code == 404, _short(r)
    finally:
        import shutil

        shutil.rmtree(many)
        shutil.rmtree(flat)


def row_no_secret_in_the_log(c: Ctx) -> None:
    # a WebSocket handshake and requests carrying the token, the cookie and a wrong token
    ws_frames(c.s, 1, timeout=60)
    r = httpx.post(c.s.url + "/api/session", json={"token": TOKEN}, timeout=30)
    cookie = r.cookies.get("cfsr_session")
    httpx.get(c.s.url + "/api/status", cookies={"cfsr_session": cookie}, timeout=30)
    httpx.get(c.s.url + "/api/status", headers={"X-CFSR-Token": TOKEN}, timeout=30)
    log = c.s.log.read_text(errors="replace")
    assert len(log) > 1000, "the trace log is nearly empty: the row tests nothing"
    assert TOKEN not in log
    assert cookie not in log


ROWS: list[tuple[str, Callable[[Ctx], None]]] = [
    ("3 symlink loop in the data folder", row_symlink_loop_in_the_data_folder),
    ("4 recording larger than the frame slot", row_recording_larger_than_the_display),
    ("5a dangling link as a recording name", row_dangling_link_as_recording_name),
    ("5b recordings folder is a link", row_recordings_folder_is_a_link),
    ("1 recording name taken between check and open", row_recording_is_created_exclusively),
    ("6 NaN under any Content-Type spelling", row_nan_in_any_content_type_spelling),
    ("7 bool and numeric strings as numbers; gain 1e-300", row_strict_types),
    ("8 errors quote at most a few hundred bytes", row_error_quotes_little),
    ("10 session attempts throttled", row_session_attempts_are_throttled),
    ("10 logout invalidates the session", row_logout_invalidates_the_session),
    ("10 half-sent headers time out", row_half_sent_headers_time_out),
    ("10 listing cap is global", row_listing_cap_is_global),
    ("9 no secret in the trace log", row_no_secret_in_the_log),
]


def _source_id(self: Ctx, name: str) -> str:
    items = [x for x in self.listing() if x["name"] == name]
    assert items, f"{name} is not listed"
    return items[0]["id"]


Ctx.source_id = _source_id  # type: ignore[attr-defined]


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    data = root / "data"
    outside = root / "outside"
    outside.mkdir()
    write_pattern(data / "a.dat", 3000)
    s = LiveServer(["--replay", str(data / "a.dat"), "--data-dir", str(data),
                    "--log-level", "trace"], token=TOKEN, env={"CFSR_TOKEN": TOKEN})
    s.cmd = [x for x in s.cmd if x != TOKEN]
    with s:
        yield Ctx(s, data, outside)
    assert segments_of(s.proc.pid) == [], "the stopped server left shared memory behind"


@pytest.mark.parametrize("name, row", ROWS, ids=[r[0] for r in ROWS])
def test_hostile(ctx, name, row):
    row(ctx)
    s = ctx.s
    assert s.get("/healthz").status_code == 200, f"service down after: {name}"
    assert len(ws_frames(s, 2, timeout=120)) == 2, f"no frames after: {name}"
    assert len(segments_of(s.proc.pid)) == 2, segments_of(s.proc.pid)


# -- rows with a process of their own -------------------------------------------------------------
def _env() -> dict[str, str]:
    return {"NUMBA_CACHE_DIR": os.environ.get("NUMBA_CACHE_DIR",
                                              str(REPO / ".cache" / "numba"))}


@pytest.mark.parametrize("group", [False, True], ids=["process", "group"])
@pytest.mark.parametrize("sig", ["SIGHUP", "SIGINT", "SIGTERM", "SIGQUIT"])
def test_every_ending_signal_stops_cleanly(tmp_path, sig, group):
    """Row 2: the signal reaches the server (``kill``) or its whole process group (a closed
    terminal, Ctrl+C, Ctrl+\\): the recording's sidecar is written, nothing stays in
    ``/dev/shm``, no semaphore is reported leaked, and the exit status is 128 + the signal."""
    data = tmp_path / "data"
    write_pattern(data / "a.dat", 3000)
    # a slow replay: a few MB/s to disk until the signal comes
    s = LiveServer(["--replay", str(data / "a.dat"), "--data-dir", str(data),
                    "--speed", "0.05"], env=_env())
    with s:
        r = s.post("/api/record", json={"action": "start", "name": "sig",
                                        "max_bytes": 200_000_000})
        assert r.status_code == 200, r.text
        # the worker is up (a signal to the group while it is still importing is another
        # matter: it has not yet set its own signal dispositions)
        s.wait_for(lambda x: x["recording"]["frames"] > 0 and x["worker"]["frames_out"] > 0,
                   120, "frames on disk and from the worker")
        pid = s.proc.pid
        assert len(segments_of(pid)) == 2
        (os.killpg if group else os.kill)(pid, getattr(signal, sig))
        try:
            rc = s.proc.wait(60)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the server did not stop on {sig}:\n{s.output()}")
        out = s.output()
    assert segments_of(pid) == [], (sig, segments_of(pid), out)
    side = data / "recordings" / "sig.dat.json"
    assert side.exists(), (sig, out)
    meta = json.loads(side.read_text())
    assert meta["n_frames"] * 12_500 == (data / "recordings" / "sig.dat").stat().st_size
    assert meta["stop_reason"] == "stopped"
    assert rc == 128 + getattr(signal, sig), (rc, out)
    assert "Traceback" not in out, out
    assert "leaked" not in out, out


def test_two_servers_on_one_folder_never_share_a_file(tmp_path):
    """Row 1: two servers on one data folder, different sources, the same recording name:
    the second is refused (409) and the file holds one source's frames; recordings without
    a name get distinct names; the second server says at start that the folder is shared."""
    data = tmp_path / "data"
    write_pattern(data / "a.dat", 3000)
    write_pattern(data / "b.dat", 2000, seed=1)
    env = _env()
    with LiveServer(["--replay", str(data / "a.dat"), "--data-dir", str(data)], env=env) as s1, \
            LiveServer(["--replay", str(data / "b.dat"), "--data-dir", str(data)],
                       env=env) as s2:
        assert "another cfsr serve" in s2.output() and str(s1.proc.pid) in s2.output()
        r1 = s1.post("/api/record", json={"action": "start", "name": "same", "max_frames": 768})
        assert r1.status_code == 200, r1.text
        r2 = s2.post("/api/record", json={"action": "start", "name": "same", "max_frames": 768})
        assert r2.status_code == 409, r2.text
        s1.wait_for(lambda x: not x["recording"]["recording"], 60, "the recording to end")
        # unnamed recordings started in the same second by both servers
        a = s1.post("/api/record", json={"action": "start", "max_frames": 256})
        b = s2.post("/api/record", json={"action": "start", "max_frames": 256})
        assert a.status_code == b.status_code == 200, (a.text, b.text)
        assert a.json()["name"] != b.json()["name"]
        for s in (s1, s2):
            s.wait_for(lambda x: not x["recording"]["recording"], 60, "the recording to end")
    meta = json.loads((data / "recordings" / "same.dat.json").read_text())
    assert meta["source"]["name"] == "a.dat" and meta["n_frames"] == 768
    assert (data / "recordings" / "same.dat").stat().st_size == 768 * 12_500


def test_blank_token_is_refused_for_a_non_loopback_bind():
    """Row 10: a token of blanks protects nothing."""
    for token in (" ", "\t", "   "):
        r = subprocess.run([sys.executable, "-m", "cfsr", "serve", "--host", "0.0.0.0",
                            "--port", "1"], env={**os.environ, "CFSR_TOKEN": token},
                           cwd=REPO, capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and "token" in r.stderr, (token, r.stderr)
    from cfsr_live.service.settings import Settings

    with pytest.raises(ValueError, match="blank"):
        Settings(host="0.0.0.0", token="  ")
    with pytest.raises(ValueError, match="blank"):
        Settings(token="\n")


def test_readyz_is_false_when_a_streaming_source_makes_no_frame(monkeypatch):
    """Row 4, second half: a worker that beats but publishes nothing (every frame fails) is
    not ready once the source has streamed for a few seconds without a frame."""
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

    from cfsr_live.service.routers import health
    from cfsr_live.service.schema import WorkerCounters

    class W:
        alive = True
        frames = 10.0

        class ready:
            @staticmethod
            def is_set() -> bool:
                return True

        def heartbeat_age(self) -> float:
            return 0.1

        def stats(self) -> WorkerCounters:
            return WorkerCounters(frames_out=int(self.frames))

    class A:
        running = True
        frames = 0

    class RT:
        started = time.monotonic()
        worker = W()
        acq = A()

    clock = [1000.0]
    monkeypatch.setattr(health, "_now", lambda: clock[0])
    app = FastAPI()
    app.state.runtime = RT()
    app.include_router(health.router)
    with TestClient(app) as client:
        assert client.get("/readyz").status_code == 200
        RT.acq.frames += 1000  # frames come in, the worker beats, but frames_out is stuck
        clock[0] += health.READY_FRAME_S + 1
        r = client.get("/readyz")
        assert r.status_code == 503 and "no frame" in r.text, r.text
        RT.worker.frames += 1
        assert client.get("/readyz").status_code == 200
        clock[0] += health.READY_FRAME_S + 1  # nothing came in (a paused replay): ready
        assert client.get("/readyz").status_code == 200
        RT.acq.running = False  # acquisition stopped: not ready (as before)
        assert client.get("/readyz").status_code == 503
