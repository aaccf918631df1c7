"""Browser security of the local service: foreign origins and rebinding host names are refused,
the token never appears in a URL or in the output (issue 12, items 6 and 7)."""

from __future__ import annotations

import os
import socket
import sys

import httpx
import pytest
from fastapi import FastAPI, WebSocket
from fastapi.testclient import TestClient
from livehelpers import LiveServer, write_pattern

from cfsr_live.service.security import (
    AttemptThrottle,
    HostOriginGuard,
    SessionStore,
    allowed_hosts,
    redact,
    throttle_key,
)


def _tiny_app(hosts, origins=()):
    app = FastAPI()

    @app.get("/r")
    def r():
        return {"ok": True}

    @app.put("/w")
    def w():
        return {"ok": True}

    @app.websocket("/ws")
    async def ws(websocket: WebSocket):
        await websocket.accept()
        await websocket.send_text("hi")
        await websocket.close()

    app.add_middleware(HostOriginGuard, hosts=hosts, origins=origins)
    return app


def test_allowed_hosts():
    assert allowed_hosts("127.0.0.1") >= {"127.0.0.1", "localhost", "::1"}
    assert "evil.example" not in allowed_hosts("127.0.0.1")
    assert allowed_hosts("0.0.0.0") is None  # token-protected wildcard bind: any Host
    assert allowed_hosts("0.0.0.0", ["cam.lab:8000"]) >= {"cam.lab", "localhost"}
    assert "10.0.0.5" in allowed_hosts("10.0.0.5")


def test_guard_host_and_origin_rules():
    c = TestClient(_tiny_app(frozenset({"testserver"}), ["http://tool.example:3000"]))
    assert c.get("/r").status_code == 200
    assert c.get("/r", headers={"Host": "evil.example"}).status_code == 400
    assert c.get("/r", headers={"Host": "testserver:8000"}).status_code == 200
    # reads are not guarded by Origin (the browser's same-origin policy hides the answer)
    assert c.get("/r", headers={"Origin": "http://evil.example"}).status_code == 200
    assert c.put("/w").status_code == 200  # no Origin: not a browser page
    assert c.put("/w", headers={"Origin": "http://evil.example"}).status_code == 403
    assert c.put("/w", headers={"Origin": "null"}).status_code == 403
    assert c.put("/w", headers={"Origin": "http://testserver"}).status_code == 200
    assert c.put("/w", headers={"Origin": "https://testserver"}).status_code == 403
    assert c.put("/w", headers={"Origin": "http://tool.example:3000"}).status_code == 200
    with c.websocket_connect("/ws") as ws:
        assert ws.receive_text() == "hi"
    with c.websocket_connect("/ws", headers={"Origin": "http://testserver"}) as ws:
        assert ws.receive_text() == "hi"
    from starlette.websockets import WebSocketDisconnect

    with pytest.raises(WebSocketDisconnect):
        with c.websocket_connect("/ws", headers={"Origin": "http://evil.example"}) as ws:
            ws.receive_text()


def test_sessions_are_random_expire_and_revoke():
    store = SessionStore(seconds=100, max_sessions=3)
    v = store.new(now=1000.0)
    assert store.valid(v, now=1050.0)
    assert not store.valid(v, now=1101.0)  # expired (and forgotten)
    assert not store.valid(v, now=1050.0)
    a = store.new(now=1000.0)
    assert store.new(now=1000.0) != a and len(a) >= 40  # 256 random bits, not derived
    store.revoke(a)
    assert not store.valid(a, now=1000.0)  # a copy of a revoked cookie is worthless
    assert not store.valid("garbage") and not store.valid(None) and not store.valid("x" * 999)
    first = store.new(now=1000.0)
    for _ in range(3):
        store.new(now=1000.0)
    assert not store.valid(first, now=1000.0)  # the oldest go once max_sessions are live


def test_wrong_tokens_are_throttled_per_client():
    t = AttemptThrottle(limit=3, window_s=10.0)
    for k in range(3):
        assert t.retry_after("a", now=100.0 + k) == 0
        t.failed("a", now=100.0 + k)
    assert t.retry_after("a", now=103.0) == pytest.approx(7.0)
    assert t.retry_after("b", now=103.0) == 0  # another client is not held
    assert t.retry_after("a", now=110.5) == 0  # the oldest try left the window


def test_a_loopback_client_is_keyed_by_its_local_user():
    """Every local process comes from a loopback address: keyed by address, one process's
    wrong tokens locked out every local Bearer user, and rotating the source address over
    127.0.0.0/8 escaped the throttle. The key is the user that owns the client's socket."""
    me = f"loopback uid {os.getuid()}"
    with socket.create_server(("127.0.0.1", 0)) as srv:
        for source in ("127.0.0.1", "127.0.0.2", "127.9.8.7"):
            with socket.socket() as c:
                c.bind((source, 0))
                c.connect(srv.getsockname())
                conn, _ = srv.accept()
                with conn:
                    assert throttle_key(conn.getpeername(), conn.getsockname()) == me, source
    if socket.has_ipv6:
        with socket.create_server(("::1", 0), family=socket.AF_INET6) as srv6, \
                socket.create_connection(srv6.getsockname()[:2]):
            conn, _ = srv6.accept()
            with conn:
                assert throttle_key(conn.getpeername()[:2], conn.getsockname()[:2]) == me
    assert throttle_key(("192.0.2.7", 5000), ("192.0.2.1", 8000)) == "192.0.2.7"
    assert throttle_key(("testclient", 50000), None) == "testclient"
    assert throttle_key(None, None) == "?"


@pytest.mark.skipif(sys.byteorder != "little", reason="the table below is a little-endian one")
def test_another_users_wrong_tokens_do_not_throttle_mine(tmp_path):
    """Keys from the kernel's socket table as Linux prints it: user 1001's client end of
    127.0.0.1:4660 -> 127.0.0.1:8080, user 1000's of :4661, and a closed one's time-wait
    line (user 0, no inode), which is not believed."""
    head = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid"
    rows = [("1234", "01", 1001, 555), ("1235", "01", 1000, 556), ("1236", "06", 0, 0)]
    (tmp_path / "tcp").write_text("\n".join([head] + [
        f"   {i}: 0100007F:{port} 0100007F:1F90 {st} 00000000:00000000 00:00000000 00000000 "
        f"{uid:>5}        0 {inode} 1 0000000000000000 20 4 0 10 -1"
        for i, (port, st, uid, inode) in enumerate(rows)]) + "\n")
    server = ("127.0.0.1", 8080)

    def key(port: int) -> str:
        return throttle_key(("127.0.0.1", port), server, proc_net=tmp_path)

    assert key(0x1234) == "loopback uid 1001" and key(0x1235) == "loopback uid 1000"
    assert key(0x1236) == key(0x4321) == "loopback"  # closed, or not in the table
    t = AttemptThrottle(limit=3, window_s=10.0)
    for k in range(10):
        t.failed(key(0x1234), now=100.0 + k / 10)
    assert t.retry_after(key(0x1234), now=101.0) > 0
    assert t.retry_after(key(0x1235), now=101.0) == 0  # user 1000 is not locked out


def test_redact_hides_every_form_of_a_secret():
    for line in ["< authorization: Bearer abc123", "> Cookie: cfsr_session=xyz; a=1",
                 "headers [(b'authorization', b'Bearer abc123')]", "x-cfsr-token: abc123",
                 "{'authorization': 'Bearer abc123'}", "the token abc123 was sent",
                 "set-cookie: cfsr_session=xyz; HttpOnly"]:
        out = redact(line, ["abc123"])
        assert "abc123" not in out and "xyz" not in out, out
        assert "[redacted]" in out
    assert redact("GET /api/status 200") == "GET /api/status 200"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    d = tmp_path_factory.mktemp("sec")
    dat = write_pattern(d / "data" / "p.dat", 3000)
    with LiveServer(["--replay", str(dat), "--data-dir", str(d / "data")]) as s:
        yield s


def test_live_service_refuses_foreign_pages(server):
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    with pytest.raises(InvalidStatus) as exc:
        with connect(server.ws_url(), open_timeout=10,
                     additional_headers={"Origin": "http://evil.example"}):
            pass
    assert exc.value.response.status_code == 403
    with connect(server.ws_url(), open_timeout=10,
                 additional_headers={"Origin": server.url}) as ws:
        assert isinstance(ws.recv(timeout=60), bytes)
    r = httpx.put(server.url + "/api/config", json={"max_fps": 30},
                  headers={"Origin": "http://evil.example"}, timeout=30)
    assert r.status_code == 403
    r = httpx.put(server.url + "/api/config", json={"max_fps": 30},
                  headers={"Origin": server.url}, timeout=30)
    assert r.status_code == 200
    # DNS rebinding: the page's name reaches our address but is not ours
    r = httpx.get(server.url + "/api/status", headers={"Host": "evil.example"}, timeout=30)
    assert r.status_code == 400
    r = httpx.get(server.url + "/api/status", headers={"Host": f"localhost:{server.port}"},
                  timeout=30)
    assert r.status_code == 200
    # the viewer page of a token-less service needs no session
    assert httpx.get(server.url + "/api/session").json() == {"token_required": False,
                                                             "authenticated": True}
