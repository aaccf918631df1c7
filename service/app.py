"""The FastAPI application factory.

``create_app(settings)`` builds an app whose lifespan owns every resource: it starts the
source, acquisition, ring and worker (:class:`cfsr_live.service.runtime.Runtime`) and the frame hub
on startup, and stops them in reverse on shutdown. ``cfsr serve`` starts the runtime itself first,
so that a source that cannot open is one line and not a server trace, and hands it over with
``create_app(settings, runtime=rt)``: the lifespan then owns (and stops) that one. Routers are
split by concern (``service/routers``); shared state reaches handlers through dependencies
(``service/deps``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, HTTPException, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline

from cfsr.cli import version
from cfsr_live.service.body import (
    MAX_BODIES_IN_FLIGHT,
    MAX_QUOTE,
    Refusal,
    StrictJsonBody,
    short,
)
from cfsr_live.service.deps import TooManyTries, token_ok
from cfsr_live.service.hub import FrameHub
from cfsr_live.service.local_pages import LocalPagesOnly
from cfsr_live.service.routers import (
    config,
    debug,
    health,
    media,
    record,
    session,
    sources,
    status,
)
from cfsr_live.service.runtime import Runtime
from cfsr_live.service.security import AttemptThrottle, HostOriginGuard, SessionStore, allowed_hosts
from cfsr_live.service.settings import Settings

__all__ = ["create_app", "viewer_dir"]

log = logging.getLogger("cfsr.app")


def viewer_dir(settings: Settings | None = None) -> Path:
    if settings is not None and settings.viewer_dir is not None:
        return Path(settings.viewer_dir)
    # package data: the viewer ships inside the wheel as cfsr_live.viewer (the repository's
    # viewer/ folder), found by import so that the checkout and a wheel agree
    from importlib.resources import files

    return Path(str(files("cfsr_live.viewer")))


#: routes with a body that need no token: the login that trades the token for a cookie
_OPEN_WITH_BODY = frozenset({"/api/session"})


def _token_before_body(scope: dict) -> Refusal | None:
    """401 (or 429 for a client over the wrong-token throttle) for a request with a body to a
    route that needs the token, when it has none: answered before the body is read. The route's
    own dependency checks again (the same function), so the answer is the same either way."""
    from starlette.requests import HTTPConnection

    if scope.get("path") in _OPEN_WITH_BODY:
        return None
    try:
        if token_ok(HTTPConnection(scope)):
            return None
    except TooManyTries as exc:
        return 429, exc.detail, [(k.lower().encode(), v.encode())
                                 for k, v in (exc.headers or {}).items()]
    return 401, "missing or wrong access token", [(b"www-authenticate", b"Bearer")]


def create_app(settings: Settings, runtime: Runtime | None = None) -> FastAPI:
    """The app; ``runtime`` is an already started :class:`Runtime` to own (else one is made)."""
    @asynccontextmanager
    async def lifespan(app: FastAPI):
        rt = runtime
        if rt is None:
            rt = Runtime(settings)
            await asyncio.to_thread(rt.start)
        hub = FrameHub(rt.slot, on_viewers=rt.set_viewers)
        app.state.runtime = rt
        app.state.hub = hub
        task = asyncio.create_task(hub.run(), name="cfsr-hub")
        try:
            yield
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            await asyncio.to_thread(rt.stop)

    # FastAPIOffline is FastAPI with /docs (Swagger UI) and /redoc served from the assets its
    # wheel ships, not from a CDN: the API docs work on a machine with no internet
    app = FastAPIOffline(
        title="CFSR live",
        version=version(),
        summary="Live spike-camera reconstruction: sources, worker, frames, masks, metrics.",
        description=(
            "Units: time in steps (1 step = 25 us at 40 kHz), rates in spikes/step. "
            "Frames stream over `WS /ws` (binary: 64-byte header, 8-bit image, coarse and fine "
            "masks as bit planes) and `GET /stream.mjpg`. When the service was started with an "
            "access token, send it as `Authorization: Bearer ...` (or `X-CFSR-Token`); the "
            "viewer trades it once for a session cookie (`POST /api/session`). Requests from "
            "another web page (`Origin`) and unknown `Host` names are refused."
        ),
        lifespan=lifespan,
    )
    _add_error_handlers(app)
    app.state.sessions = SessionStore()
    app.state.auth_throttle = AttemptThrottle()

    app.state.settings = settings
    app.state.metrics = status.make_registry(app)
    for r in (health, session, status, config, sources, record, media):
        app.include_router(r.router)
    if settings.test_hooks:
        app.include_router(debug.router)
    _add_guards(app, settings)
    vd = viewer_dir(settings)
    if vd.is_dir():
        app.mount("/", StaticFiles(directory=vd, html=True), name="viewer")
    else:
        log.warning("viewer folder %s is missing; only the API is served", vd)
    return app

def _add_error_handlers(app: FastAPI) -> None:
    """One 422 shape for the whole API, and no answer that quotes much of a request."""

    @app.exception_handler(HTTPException)
    async def _http_error(request: Request, exc: HTTPException):
        # One 422 shape for the whole API: our own checks (a method's parameter range, a seek
        # outside the recording) answer in FastAPI's validation-error format, the one the
        # OpenAPI document promises for 422, not a bare string. No answer quotes more than
        # a few hundred characters of what the client sent (a 20 MB method name included).
        detail = short(exc.detail, 2 * MAX_QUOTE) if isinstance(exc.detail, str) else exc.detail
        if exc.status_code == 422 and isinstance(detail, str):
            detail = [{"loc": ["body"], "msg": detail, "type": "value_error"}]
        exc = HTTPException(exc.status_code, detail, headers=exc.headers)
        return await http_exception_handler(request, exc)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError):
        errors = [
            {
                "type": e.get("type"),
                "loc": [short(x, 80) if isinstance(x, str) else x for x in e.get("loc", ())],
                "msg": short(e.get("msg", ""), 2 * MAX_QUOTE),
                "input": short(e["input"]) if "input" in e else None,
            }
            for e in exc.errors()[:20]
        ]
        return JSONResponse({"detail": errors}, status_code=422)


def _add_guards(app: FastAPI, settings: Settings) -> None:
    """The middleware every request meets before a route: Host and Origin, then the body."""
    # every request body, strict JSON of bounded size and time, before any route
    # (cfsr_live.service.body); the token is checked before a byte of it is read
    # a quarter of the connections at most wait on bodies: the rest stay free for others
    # (/healthz, the viewer) however many clients stall their bodies
    app.add_middleware(StrictJsonBody, admit=_token_before_body,
                       timeout_s=settings.body_timeout_s,
                       max_in_flight=max(4, min(MAX_BODIES_IN_FLIGHT,
                                                settings.max_connections // 4)))
    # every HTML page loads from this service only (cfsr_live.service.local_pages)
    app.add_middleware(LocalPagesOnly)
    # outermost: a request from a foreign page or a rebinding name goes no further
    app.add_middleware(
        HostOriginGuard,
        hosts=allowed_hosts(settings.host, settings.allowed_hosts),
        origins=settings.allowed_origins,
    )
