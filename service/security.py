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
``POST /api/session`` (a random id the server remembers, revoked by ``DELETE /api/session``);
never in a URL, where servers and proxies log it. Wrong tokens are throttled per client
(:class:`AttemptThrottle`), and no log record of the process carries a secret
(:func:`install_log_redaction`).
"""

from __future__ import annotations

import ipaddress
import json
import re
import secrets
import struct
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Iterable
from pathlib import Path
from urllib.parse import urlsplit

__all__ = [
    "AttemptThrottle",
    "SessionStore",
    "install_log_redaction",
    "redact",
    "SESSION_COOKIE",
    "SESSION_SECONDS",
    "HostOriginGuard",
    "allowed_hosts",
    "throttle_key",
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


class SessionStore:
    """The viewer's sessions: random ids (256 bits) the server remembers until they expire
    (:data:`SESSION_SECONDS`) or are revoked by ``DELETE /api/session``; a copy of a cookie
    is worth nothing once its session is gone. At most ``max_sessions`` live at once (the
    oldest go first); a restart ends them all."""

    def __init__(self, seconds: float = SESSION_SECONDS, max_sessions: int = 256) -> None:
        self.seconds = seconds
        self.max_sessions = max_sessions
        self._expiry: OrderedDict[str, float] = OrderedDict()
        self._lock = threading.Lock()

    def new(self, now: float | None = None) -> str:
        sid = secrets.token_urlsafe(32)
        t = time.time() if now is None else now
        with self._lock:
            self._expiry[sid] = t + self.seconds
            while len(self._expiry) > self.max_sessions:
                self._expiry.popitem(last=False)
        return sid

    def valid(self, value: str | None, now: float | None = None) -> bool:
        if not value or len(value) > 128:
            return False
        t = time.time() if now is None else now
        with self._lock:
            expiry = self._expiry.get(value)
            if expiry is not None and expiry < t:
                del self._expiry[value]
                expiry = None
        return expiry is not None

    def revoke(self, value: str | None) -> None:
        if value:
            with self._lock:
                self._expiry.pop(value, None)


class AttemptThrottle:
    """Wrong tokens cost time: after ``limit`` wrong tries from one client within
    ``window_s`` seconds, that client's tries (right or wrong, so the throttle cannot be
    probed) are refused (HTTP 429) until the oldest of those falls out of the window.

    Keyed by client (:func:`throttle_key`: the address, or for a loopback connection the
    local user it comes from); at most ``max_clients`` are remembered (the least recent go
    first), so a flood of addresses cannot grow it without bound."""

    def __init__(self, limit: int = 5, window_s: float = 10.0, max_clients: int = 4096) -> None:
        self.limit, self.window_s, self.max_clients = limit, window_s, max_clients
        self._fails: OrderedDict[str, deque[float]] = OrderedDict()
        self._lock = threading.Lock()

    def retry_after(self, client: str, now: float | None = None) -> float:
        """Seconds ``client`` must wait before its next try counts (0: it may try now)."""
        t = time.monotonic() if now is None else now
        with self._lock:
            q = self._fails.get(client)
            if not q:
                return 0.0
            while q and q[0] <= t - self.window_s:
                q.popleft()
            if len(q) < self.limit:
                return 0.0
            return max(0.0, q[-self.limit] + self.window_s - t)

    def failed(self, client: str, now: float | None = None) -> None:
        t = time.monotonic() if now is None else now
        with self._lock:
            q = self._fails.pop(client, None) or deque(maxlen=self.limit)
            q.append(t)
            self._fails[client] = q
            while len(self._fails) > self.max_clients:
                self._fails.popitem(last=False)


#: where Linux shows its TCP sockets, with the user id that owns each
PROC_NET = Path("/proc/net")


def _proc_forms(host: str) -> list[str]:
    """``host`` as ``/proc/net/tcp`` (IPv4) and ``/proc/net/tcp6`` print it: 32-bit words
    in the machine's byte order, in hex."""
    ip = ipaddress.ip_address(host)
    v4 = ip if isinstance(ip, ipaddress.IPv4Address) else ip.ipv4_mapped
    forms = []
    if v4 is not None:
        forms.append(f"{struct.unpack('=I', v4.packed)[0]:08X}")
        ip = ipaddress.IPv6Address(b"\0" * 10 + b"\xff\xff" + v4.packed)
    forms.append("".join(f"{w:08X}" for w in struct.unpack("=4I", ip.packed)))
    return forms


def loopback_peer_uid(client: tuple[str, int], server: tuple[str, int],
                      proc_net: Path = PROC_NET) -> int | None:
    """The user id that owns the client's end of a loopback TCP connection: the kernel's
    socket table line whose local end is ``client`` and remote end ``server``. ``None``
    where there is no such table (not Linux) or no live socket (the client closed already:
    a closed socket's time-wait line shows user 0 and no inode, so it is not believed)."""
    (chost, cport), (shost, sport) = client, server
    try:
        pairs = [(f"{c}:{cport:04X}", f"{s}:{sport:04X}")
                 for c in _proc_forms(chost) for s in _proc_forms(shost)]
    except ValueError:
        return None
    for table in ("tcp", "tcp6"):
        try:
            text = (proc_net / table).read_text()
        except OSError:
            continue
        for local, remote in pairs:
            at = text.find(f"{local} {remote}")
            while at >= 0:
                line = text[text.rfind("\n", 0, at) + 1:text.find("\n", at)].split()
                if len(line) > 9 and line[1:3] == [local, remote] and line[9] != "0":
                    return int(line[7])
                at = text.find(f"{local} {remote}", at + 1)
    return None


def throttle_key(client: tuple[str, int] | None, server: tuple[str, int] | None,
                 proc_net: Path = PROC_NET) -> str:
    """The wrong-token throttle's slot for a connection from ``client`` to ``server``.

    A remote client is its address. Every local process comes from a loopback address, so
    keyed by address one local process's wrong tokens locked out every Bearer user on the
    machine (and rotating the source over 127.0.0.0/8 escaped the throttle). A loopback
    client is keyed by the local user that owns its socket instead: another user's process
    throttles only that user. Processes of one user share a slot, as they share everything
    else (each can read the other's memory and environment); a slot per process would give
    an attacker a fresh slot per fork. Where the owner cannot be read, all loopback clients
    share one slot."""
    if not client:
        return "?"
    try:
        ip = ipaddress.ip_address(client[0])
    except ValueError:
        return client[0]
    v4 = ip.ipv4_mapped if isinstance(ip, ipaddress.IPv6Address) else None
    if not (ip.is_loopback or (v4 is not None and v4.is_loopback)):
        return client[0]
    uid = loopback_peer_uid(client, server, proc_net) if server else None
    return "loopback" if uid is None else f"loopback uid {uid}"


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


# -- secrets in logs ------------------------------------------------------------------------------
_SECRET_FIELDS = re.compile(
    r"(?i)(authorization|proxy-authorization|x-cfsr-token|cookie|set-cookie)"
    r"(['\"]?\s*,\s*b?['\"]|['\"]?\s*[:=]\s*['\"]?)[^\r\n'\")]*"
)
_BEARER = re.compile(r"(?i)\b(bearer)\s+[^\s'\",;)]+")
_SESSION_VALUE = re.compile(re.escape(SESSION_COOKIE) + r"=[^\s;'\",)]+")
REDACTED = "[redacted]"


def redact(text: str, values: Iterable[str] = ()) -> str:
    """``text`` with every secret replaced by ``[redacted]``: the values given (the token),
    the value of any ``Authorization``/``X-CFSR-Token``/``Cookie``/``Set-Cookie`` header in
    the forms loggers print them (``name: value``, ``(b'name', b'value')``, ``'name': 'value'``),
    bearer credentials and session cookies."""
    for s in values:
        if s:
            text = text.replace(s, REDACTED)
    text = _SECRET_FIELDS.sub(lambda m: m.group(1) + m.group(2) + REDACTED, text)
    text = _BEARER.sub(lambda m: m.group(1) + " " + REDACTED, text)
    return _SESSION_VALUE.sub(SESSION_COOKIE + "=" + REDACTED, text)


def install_log_redaction(values: Iterable[str] = ()) -> None:
    """Redact secrets (:func:`redact`) in every log record of this process, whatever its
    logger, level or handler: the record factory rewrites the message when the record is
    made (at debug, uvicorn's WebSocket layer logs every handshake header). Idempotent."""
    import logging

    known = [s for s in values if s]
    current = logging.getLogRecordFactory()
    base = getattr(current, "_cfsr_base", current)

    def factory(*args, **kwargs):
        rec = base(*args, **kwargs)
        try:
            msg = rec.getMessage()
        except Exception:  # noqa: BLE001 - a record that cannot format is left as it is
            return rec
        clean = redact(msg, known)
        if clean != msg:
            rec.msg, rec.args = clean, ()
        if rec.exc_info and not rec.exc_text:
            text = logging.Formatter().formatException(rec.exc_info)
            rec.exc_text = redact(text, known)
        return rec

    factory._cfsr_base = base  # type: ignore[attr-defined]
    logging.setLogRecordFactory(factory)
