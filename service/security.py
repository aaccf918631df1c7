"""Browser security for a service on the user's own machine.

A loopback service is still reachable from every web page the user opens. Two attacks matter:

* **Cross-site requests**: a page on ``http://evil.example`` opens ``ws://127.0.0.1:8000/ws`` (the
  browser sends the page's ``Origin``, but no same-origin rule stops a WebSocket) or submits a
  ``PUT``/``POST``. Defence: a WebSocket or a state-changing request that carries an ``Origin``
  must come from the service's own origin (``scheme://`` + the ``Host`` it asked for) or from
  the configured allow-list. Clients that are not browsers send no ``Origin`` and are let
  through (the token, when set, still applies).
* **DNS rebinding**: ``evil.example`` re-resolves to 127.0.0.1, so the page becomes "same
  origin" with the service. Defence: the ``Host`` header must be one of the names the service
  is bound to (loopback names by default, plus ``--allow-host``).

Tokens travel in a header (``Authorization: Bearer``, ``X-CFSR-Token``) or in the short-lived
``HttpOnly; SameSite=Strict`` session cookie that the viewer page obtains with
``POST /api/session``; never in a URL, where servers and proxies log it.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import time
from collections.abc import Iterable
from urllib.parse import urlsplit

__all__ = [
    "SESSION_COOKIE",
    "SESSION_SECONDS",
    "HostOriginGuard",
    "allowed_hosts",
    "make_session",
    "session_ok",
]

SESSION_COOKIE = "cfsr_session"
#: lifetime of a viewer session cookie: a working day
SESSION_SECONDS = 12 * 3600

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1", "localhost.localdomain")
_WILDCARDS = ("0.0.0.0", "::", "")
_STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})


def _strip_port(host: str) -> str:
    host = host.strip().lower()
    if host.startswith("["):  # [::1]:8000
        return host[1 : host.find("]")] if "]" in host else host
    if host.count(":") == 1:
        return host.split(":", 1)[0]
    return host


def allowed_hosts(bind: str, extra: Iterable[str] = ()) -> frozenset[str] | None:
    """Host names the service answers to; ``None`` (any) for a wildcard bind without
    ``--allow-host`` (such a bind requires a token, which is then the protection)."""
    extra = [_strip_port(h) for h in extra if h.strip()]
    if bind in _WILDCARDS and not extra:
        return None
    names = {*LOOPBACK_NAMES, *extra}
    if bind not in _WILDCARDS:
        names.add(_strip_port(bind))
    return frozenset(names)


def make_session(token: str, now: float | None = None) -> str:
    """A cookie value proving the token was shown: ``EXPIRY.HMAC(token, EXPIRY)`` (the token
    itself never leaves the server again)."""
    expiry = int((time.time() if now is None else now) + SESSION_SECONDS)
    mac = hmac.new(token.encode(), str(expiry).encode(), hashlib.sha256).hexdigest()
    return f"{expiry}.{mac}"


def session_ok(token: str, value: str | None, now: float | None = None) -> bool:
    if not value or "." not in value:
        return False
    expiry_s, mac = value.split(".", 1)
    try:
        expiry = int(expiry_s)
    except ValueError:
        return False
    if expiry < (time.time() if now is None else now):
        return False
    want = hmac.new(token.encode(), str(expiry).encode(), hashlib.sha256).hexdigest()
    return hmac.compare_digest(want.encode(), mac.encode())


class HostOriginGuard:
    """Pure ASGI middleware: 400 on a ``Host`` outside ``hosts``; 403 on a WebSocket or a
    state-changing request whose ``Origin`` is neither the service's own nor in ``origins``."""

    def __init__(self, app, *, hosts: frozenset[str] | None, origins: Iterable[str] = ()) -> None:
        self.app = app
        self.hosts = hosts
        self.origins = frozenset(o.rstrip("/").lower() for o in origins)

    def _origin_ok(self, origin: str, host: str, scheme: str) -> bool:
        origin = origin.rstrip("/").lower()
        if origin in self.origins:
            return True
        parts = urlsplit(origin)
        if parts.scheme not in ("http", "https") or not parts.netloc:
            return False  # includes the opaque "null" origin of sandboxed frames and files
        want_scheme = {"ws": "http", "wss": "https"}.get(scheme, scheme)
        return parts.scheme == want_scheme and parts.netloc == host.lower()

    async def __call__(self, scope, receive, send) -> None:
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1")
                   for k, v in scope.get("headers", [])}
        host = headers.get("host", "")
        if self.hosts is not None and _strip_port(host) not in self.hosts:
            await _deny(scope, send, 400, f"Host {host!r} is not a name this service serves "
                        "(see --allow-host)")
            return
        origin = headers.get("origin")
        guarded = kind == "websocket" or scope.get("method", "GET") in _STATE_CHANGING
        if guarded and origin is not None and not self._origin_ok(
            origin, host, scope.get("scheme", "http")
        ):
            await _deny(scope, send, 403, f"Origin {origin!r} may not use this service "
                        "(see --allow-origin)")
            return
        await self.app(scope, receive, send)


async def _deny(scope, send, status: int, detail: str) -> None:
    if scope["type"] == "websocket":
        # closing before accepting makes the server answer the handshake with 403
        await send({"type": "websocket.close", "code": 1008, "reason": detail[:120]})
        return
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})
