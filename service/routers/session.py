"""The viewer's session: the page trades the access token once for a short-lived cookie, so
the token is never put in a URL (WebSocket URLs are logged) nor kept by the page."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request, Response, status
from pydantic import BaseModel, Field

from cfsr_live.service.deps import TooManyTries, client_key, token_matches, token_ok
from cfsr_live.service.models import STRICT
from cfsr_live.service.security import SESSION_COOKIE, SESSION_SECONDS

router = APIRouter(tags=["session"])


class SessionRequest(BaseModel):
    model_config = STRICT

    token: str = Field(min_length=1, max_length=4096, description="the service's access token")


class SessionState(BaseModel):
    token_required: bool
    authenticated: bool


def _authenticated(request: Request) -> bool:
    try:
        return token_ok(request)
    except TooManyTries:
        return False


@router.get("/api/session", response_model=SessionState,
            summary="whether the API needs a token, and whether this client has shown it")
async def get_session(request: Request) -> SessionState:
    settings = request.app.state.settings
    return SessionState(
        token_required=bool(settings.token),
        authenticated=_authenticated(request),
    )


@router.post("/api/session", response_model=SessionState,
             responses={401: {"description": "wrong token"},
                        429: {"description": "too many wrong tokens lately (Retry-After)"}},
             summary="show the token once; answers with an HttpOnly, SameSite=Strict cookie")
async def post_session(body: SessionRequest, request: Request, response: Response) -> SessionState:
    state = request.app.state
    if not state.settings.token:
        return SessionState(token_required=False, authenticated=True)
    key = client_key(request)
    wait = state.auth_throttle.retry_after(key)
    if wait > 0:  # right or wrong: while throttled, a try tells nothing
        raise TooManyTries(wait)
    if not token_matches(state.settings, body.token):
        state.auth_throttle.failed(key)
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "wrong access token")
    response.set_cookie(SESSION_COOKIE, state.sessions.new(), max_age=SESSION_SECONDS,
                        httponly=True, samesite="strict", path="/")
    return SessionState(token_required=True, authenticated=True)


@router.delete("/api/session", response_model=SessionState,
               summary="end this session: its cookie is worthless from now on, even a copy")
async def delete_session(request: Request, response: Response) -> SessionState:
    request.app.state.sessions.revoke(request.cookies.get(SESSION_COOKIE))
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return SessionState(token_required=bool(request.app.state.settings.token),
                        authenticated=not request.app.state.settings.token)
