"""FastAPI dependencies: the runtime, the hub and access-token checks (no globals)."""

from __future__ import annotations

import hmac
import math
from typing import Annotated

from fastapi import Depends, HTTPException, Request, WebSocket, status
from starlette.requests import HTTPConnection

from cfsr_live.service.hub import FrameHub
from cfsr_live.service.runtime import Runtime
from cfsr_live.service.security import SESSION_COOKIE, AttemptThrottle, throttle_key
from cfsr_live.service.settings import Settings

__all__ = [
    "HubDep",
    "RuntimeDep",
    "get_hub",
    "get_runtime",
    "get_settings",
    "hide_paths",
    "server_folders",
    "TooManyTries",
    "client_key",
    "require_token",
    "token_matches",
    "token_ok",
]


def get_runtime(request: Request) -> Runtime:
    return request.app.state.runtime


def get_hub(request: Request) -> FrameHub:
    return request.app.state.hub


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def server_folders(settings: Settings) -> list[str]:
    """Absolute folders whose names an answer never shows (longest first): the data folder
    (as given and resolved) and the folder of a recording named on the command line."""
    dirs = {settings.data_dir, settings.data_dir.resolve()}
    if settings.source.path is not None:
        dirs |= {settings.source.path.parent, settings.source.path.parent.resolve()}
    return sorted((str(d).rstrip("/") + "/" for d in dirs), key=len, reverse=True)


def hide_paths(settings: Settings, text: str | None) -> str | None:
    """``text`` with the server's folders (:func:`server_folders`) cut from the file names in
    it: ``/home/u/.local/share/cfsr/b.dat`` reads ``b.dat``, as in the listing."""
    if text:
        for d in server_folders(settings):
            text = text.replace(d, "")
    return text


def _supplied(headers) -> str | None:
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return headers.get("x-cfsr-token")


def client_key(conn: HTTPConnection) -> str:
    """Who a request comes from, for the wrong-token throttle: the peer address, or the
    local user of a loopback client (:func:`cfsr_live.service.security.throttle_key`)."""
    return throttle_key(conn.scope.get("client"), conn.scope.get("server"))


def token_matches(settings: Settings, given: str) -> bool:
    """Whether ``given`` is the access token (constant time)."""
    return bool(settings.token) and hmac.compare_digest(given.encode(), settings.token.encode())


def token_ok(conn: HTTPConnection) -> bool:
    """The token from a header (``Authorization: Bearer``, ``X-CFSR-Token``) or a live
    session cookie (:class:`cfsr_live.service.security.SessionStore`); never from the URL, which
    servers log. A wrong header token counts against the client's throttle, and a client
    over it is refused (429) whatever it sends
    (:class:`cfsr_live.service.security.AttemptThrottle`)."""
    state = conn.app.state
    settings: Settings = state.settings
    if not settings.token:
        return True
    given = _supplied(conn.headers)
    if given is not None:
        throttle: AttemptThrottle = state.auth_throttle
        key = client_key(conn)
        wait = throttle.retry_after(key)
        if wait > 0:
            raise TooManyTries(wait)
        if token_matches(settings, given):
            return True
        throttle.failed(key)
        return False
    return state.sessions.valid(conn.cookies.get(SESSION_COOKIE))


class TooManyTries(HTTPException):
    """429 with ``Retry-After``: the client gave too many wrong tokens lately."""

    def __init__(self, wait_s: float) -> None:
        secs = max(1, math.ceil(wait_s))
        super().__init__(status.HTTP_429_TOO_MANY_REQUESTS,
                         f"too many wrong access tokens; retry in {secs} s",
                         headers={"Retry-After": str(secs)})


def require_token(request: Request) -> None:
    """When the service has a token, every API call must carry it (header or session
    cookie)."""
    if not token_ok(request):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or wrong access token",
            headers={"WWW-Authenticate": "Bearer"},
        )


def ws_token_ok(ws: WebSocket) -> bool:
    try:
        return token_ok(ws)
    except TooManyTries:
        return False


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
HubDep = Annotated[FrameHub, Depends(get_hub)]
