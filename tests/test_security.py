"""Browser security of the local service: foreign origins and rebinding host names are refused,
the token never appears in a URL or in the output (issue 12, items 6 and 7)."""

from __future__ import annotations

import httpx
import pytest
from fastapi import FastAPI, WebSocket
from fastapi.testclient import TestClient
from livehelpers import LiveServer, write_pattern

from service.security import HostOriginGuard, allowed_hosts, make_session, session_ok


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


def test_session_cookie_value():
    v = make_session("tok", now=1000.0)
    assert session_ok("tok", v, now=1000.0)
    assert not session_ok("other", v, now=1000.0)
    assert not session_ok("tok", v, now=10**9)  # expired
    assert not session_ok("tok", "garbage") and not session_ok("tok", None)
    assert "tok" not in v


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
