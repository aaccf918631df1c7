"""FastAPI dependencies: the runtime, the hub and access-token checks (no globals)."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request, WebSocket, status

from service.hub import FrameHub
from service.runtime import Runtime
from service.security import SESSION_COOKIE, session_ok
from service.settings import Settings

__all__ = [
    "HubDep",
    "RuntimeDep",
    "get_hub",
    "get_runtime",
    "get_settings",
    "require_token",
    "token_ok",
]


def get_runtime(request: Request) -> Runtime:
    return request.app.state.runtime


def get_hub(request: Request) -> FrameHub:
    return request.app.state.hub


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def _supplied(headers) -> str | None:
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return headers.get("x-cfsr-token")


def token_ok(settings: Settings, headers, cookies) -> bool:
    """The token from a header (``Authorization: Bearer``, ``X-CFSR-Token``) or the viewer's
    session cookie (:mod:`service.security`); never from the URL, which servers log."""
    if not settings.token:
        return True
    given = _supplied(headers)
    if given is not None:
        return hmac.compare_digest(given.encode(), settings.token.encode())
    return session_ok(settings.token, cookies.get(SESSION_COOKIE))


def require_token(request: Request) -> None:
    """When the service has a token, every API call must carry it (header or session
    cookie)."""
    if not token_ok(request.app.state.settings, request.headers, request.cookies):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or wrong access token",
            headers={"WWW-Authenticate": "Bearer"},
        )


def ws_token_ok(ws: WebSocket) -> bool:
    return token_ok(ws.app.state.settings, ws.headers, ws.cookies)


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
HubDep = Annotated[FrameHub, Depends(get_hub)]
