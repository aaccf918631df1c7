"""FastAPI dependencies: the runtime, the hub and access-token checks (no globals)."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request, WebSocket, status

from service.hub import FrameHub
from service.runtime import Runtime
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


def _supplied(headers, query) -> str | None:
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return headers.get("x-cfsr-token") or query.get("token")


def token_ok(settings: Settings, headers, query) -> bool:
    if not settings.token:
        return True
    given = _supplied(headers, query)
    return given is not None and hmac.compare_digest(given.encode(), settings.token.encode())


def require_token(request: Request) -> None:
    """When the service has a token, every API call must carry it (Bearer, X-CFSR-Token or
    ``?token=``)."""
    if not token_ok(request.app.state.settings, request.headers, request.query_params):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or wrong access token",
            headers={"WWW-Authenticate": "Bearer"},
        )


def ws_token_ok(ws: WebSocket) -> bool:
    return token_ok(ws.app.state.settings, ws.headers, ws.query_params)


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
HubDep = Annotated[FrameHub, Depends(get_hub)]
