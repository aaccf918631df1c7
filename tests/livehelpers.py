"""Helpers for integration tests: start the real service (``cfsr serve``) on a free loopback
port in a subprocess, talk to it, and stop it; wait for a condition with a deadline; run
a spike array through the live and offline streaming paths.

Not a test module (no ``test_`` prefix). Test modules import it as ``livehelpers``: pytest puts
``tests/`` (a folder without ``__init__.py``) on ``sys.path`` for them, as for ``wheelenv``."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import httpx

from cfsr.layout import Layout

T = TypeVar("T")

REPO = Path(__file__).resolve().parents[1]


#: Stored layouts every packed path must read as the unpacked frames: plain, head columns,
#: head columns with right-to-left rows, rows stored upright
PACKED_LAYOUTS = (
    Layout(16, 6),
    Layout(16, 6, head_cols=8),
    Layout(16, 6, fliplr=True, head_cols=8),
    Layout(16, 6, flipud=False),
)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def segments_of(pid: int) -> list[Path]:
    """Shared-memory files (spike ring, frame slot) that process ``pid`` created."""
    from cfsr_live.service.frameslot import FRAME_PREFIX
    from cfsr_live.shm.files import shared_dirs
    from cfsr_live.shm.ring import RING_PREFIX

    return sorted(p for d in set(shared_dirs()) if d.is_dir()
                  for pre in (RING_PREFIX, FRAME_PREFIX) for p in d.glob(f"{pre}-{pid}-*"))


def wait_until(
    pred: Callable[[], T],
    timeout: float,
    what: str | Callable[[], str] = "condition",
    *,
    interval: float = 0.2,
) -> T:
    """Poll ``pred`` every ``interval`` s until it returns something true (returned) or
    ``timeout`` s are up (AssertionError naming ``what``, which may be a callable so that the
    message can show the last state seen).

    The one poll-with-deadline loop of the tests: a test waits for a condition, never for a
    fixed time, so it is as fast as the system allows and as patient as the deadline says.
    """
    end = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() >= end:
            text = what() if callable(what) else what
            raise AssertionError(f"timed out after {timeout} s waiting for {text}")
        time.sleep(interval)


def read_blocks(
    src: Any,
    k: int,
    timeout: float,
    *,
    check: Callable[[Any], None] | None = None,
    block_timeout: float = 0.5,
) -> list[Any]:
    """``k`` blocks from ``src`` (a :class:`cfsr_live.driver.source.Source`), each passed to
    ``check``
    first; AssertionError with the source's counters if they do not come within ``timeout`` s.

    Each read waits for its block itself (``block_timeout``), so the polling never sleeps."""
    out: list[Any] = []

    def got_all() -> bool:
        b = src.read_block(block_timeout)
        if b is not None:
            if check is not None:
                check(b)
            out.append(b)
        return len(out) >= k

    wait_until(got_all, timeout, lambda: f"{k} blocks (got {len(out)}; counters "
               f"{src.counters()})", interval=0)
    return out


def streamed_outputs(
    spikes: Any, method: str, times: list[int], params: dict[str, Any], block: int
) -> tuple[dict[int, Any], dict[int, Any]]:
    """``{t: Output}`` at ``times`` of ``spikes`` (upright ``(n, H, W)`` 0/1) by the two
    streaming paths: the live one (a StreamingReconstructor fed ``block``-frame packed
    blocks, as the worker is) and the offline file path (``stream_reconstruct``)."""
    from cfsr import StreamingReconstructor
    from cfsr.offline import stream_reconstruct
    from cfsr.spikes import SpikeRecording

    rec = SpikeRecording.from_array(spikes)
    sr = StreamingReconstructor(method, rec.layout, params=params, slack=block)
    blocks = ((a, rec.packed(a, a + block)) for a in range(0, len(rec), block))
    live = dict(sr.run(blocks, times))
    offline = dict(stream_reconstruct(rec, method, times, params=params, block=block))
    return live, offline


def write_pattern(path: Path, steps: int = 4000, **kw) -> Path:
    from cfsr.datfile import write_dat
    from cfsr_live.replay.pattern import pattern_recording

    path.parent.mkdir(parents=True, exist_ok=True)
    write_dat(path, pattern_recording(steps, **kw))
    return path


class LiveServer:
    """``cfsr serve ARGS`` on 127.0.0.1:<free port>; ``prefix`` runs it under a wrapper
    (e.g. ``umockdev-wrapper``) or a launcher script instead of ``python -m cfsr``; ``command``
    may also be an installed ``cfsr`` (with ``cwd`` outside the checkout and ``env`` of that
    install)."""

    def __init__(
        self,
        args: list[str],
        *,
        env: dict[str, str] | None = None,
        port: int | None = None,
        command: list[str] | None = None,
        token: str | None = None,
        startup_timeout: float = 180.0,
        cwd: Path | None = None,
    ) -> None:
        self.cwd = cwd or REPO
        self.port = port or free_port()
        self.token = token
        self.url = f"http://127.0.0.1:{self.port}"
        base = command or [sys.executable, "-m", "cfsr", "serve"]
        self.cmd = [*base, "--host", "127.0.0.1", "--port", str(self.port), *args]
        if port is not None and "--port" in args:
            self.cmd = [*base, *args]
        self.env = {**os.environ, **(env or {})}
        self.env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".cache" / "numba"))
        self.env.setdefault("PYTHONUNBUFFERED", "1")
        self.startup_timeout = startup_timeout
        self.log = Path(tempfile.mkstemp(prefix="cfsr-serve-", suffix=".log")[1])
        self.proc: subprocess.Popen | None = None

    def start(self) -> LiveServer:
        fh = open(self.log, "wb")  # noqa: SIM115 - closed with the process
        self.proc = subprocess.Popen(
            self.cmd, cwd=self.cwd, env=self.env, stdout=fh, stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        fh.close()

        def healthy() -> bool:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}:\n{self.output()}")
            try:
                return httpx.get(self.url + "/healthz", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        try:
            wait_until(healthy, self.startup_timeout, "the server to become healthy")
        except AssertionError:
            self.stop()
            raise RuntimeError(f"server did not become healthy:\n{self.output()}") from None
        return self

    def output(self) -> str:
        try:
            return self.log.read_text(errors="replace")[-6000:]
        except OSError:
            return ""

    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}

    def get(self, path: str, **kw) -> httpx.Response:
        kw.setdefault("timeout", 30)
        return httpx.get(self.url + path, headers=self.headers(), **kw)

    def put(self, path: str, json=None, **kw) -> httpx.Response:
        kw.setdefault("timeout", 60)
        return httpx.put(self.url + path, json=json, headers=self.headers(), **kw)

    def post(self, path: str, json=None, **kw) -> httpx.Response:
        kw.setdefault("timeout", 60)
        return httpx.post(self.url + path, json=json, headers=self.headers(), **kw)

    def status(self) -> dict:
        r = self.get("/api/status")
        r.raise_for_status()
        return r.json()

    def wait_for(self, pred, timeout: float = 60.0, what: str = "condition") -> dict:
        """Poll ``/api/status`` until ``pred(status)`` holds; returns that status."""
        last: dict = {}

        def check() -> dict | None:
            last["status"] = self.status()
            return last["status"] if pred(last["status"]) else None

        return wait_until(check, timeout, lambda: f"{what}; last status: {last.get('status')}")

    def ws_url(self, query: str = "") -> str:
        return f"ws://127.0.0.1:{self.port}/ws" + ("?" + query if query else "")

    def ws_connect(self, query: str = "", **kw):
        """A websockets sync client, with the token in a header (never in the URL)."""
        from websockets.sync.client import connect

        kw.setdefault("max_size", None)
        kw.setdefault("open_timeout", 30)
        return connect(self.ws_url(query), additional_headers=self.headers(), **kw)

    def stop(self) -> None:
        p = self.proc
        if p is None or p.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(10)

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def ws_frames(server: LiveServer, n: int, *, timeout: float = 60.0, method: str | None = None,
              query: str = ""):
    """Receive ``n`` decoded frames (optionally only those of ``method``) over the WebSocket."""
    from cfsr_live.service.hub import decode_ws_message

    # the mask planes' names, as a client learns them from the server
    names = tuple(m["name"] for m in server.get("/api/schema").json()["masks"])
    out = []
    end = time.monotonic() + timeout
    with server.ws_connect(query) as ws:
        while len(out) < n:
            left = end - time.monotonic()
            if left <= 0:
                raise AssertionError(f"only {len(out)} of {n} frames ({method}) in {timeout} s")
            try:
                msg = ws.recv(timeout=left)
            except TimeoutError:
                continue
            d = decode_ws_message(msg, names)
            if method is None or d["method"] == method:
                out.append(d)
    return out

