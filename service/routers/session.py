"""The viewer's session: the page trades the access token once for a short-lived cookie, so
the token is never put in a URL (WebSocket URLs are logged) nor kept by the page."""

from __future__ import annotations

import hmac

from fastapi import APIRouter, HTTPException, Request, Response, status
from pydantic import BaseModel, Field

from service.deps import token_ok
from service.security import SESSION_COOKIE, SESSION_SECONDS, make_session

router = APIRouter(tags=["session"])


class SessionRequest(BaseModel):
    token: str = Field(min_length=1, max_length=4096, description="the service's access token")


class SessionState(BaseModel):
    token_required: bool
    authenticated: bool


@router.get("/api/session", response_model=SessionState,
            summary="whether the API needs a token, and whether this client has shown it")
async def get_session(request: Request) -> SessionState:
    settings = request.app.state.settings
    return SessionState(
        token_required=bool(settings.token),
        authenticated=token_ok(settings, request.headers, request.cookies),
    )


@router.post("/api/session", response_model=SessionState,
             responses={401: {"description": "wrong token"}},
             summary="show the token once; answers with an HttpOnly, SameSite=Strict cookie")
async def post_session(body: SessionRequest, request: Request, response: Response) -> SessionState:
    token = request.app.state.settings.token
    if not token:
        return SessionState(token_required=False, authenticated=True)
    if not hmac.compare_digest(body.token.encode(), token.encode()):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "wrong access token")
    response.set_cookie(SESSION_COOKIE, make_session(token), max_age=SESSION_SECONDS,
                        httponly=True, samesite="strict", path="/")
    return SessionState(token_required=True, authenticated=True)


@router.delete("/api/session", response_model=SessionState, summary="forget this session")
async def delete_session(request: Request, response: Response) -> SessionState:
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return SessionState(token_required=bool(request.app.state.settings.token),
                        authenticated=not request.app.state.settings.token)
