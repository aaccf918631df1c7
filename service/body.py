"""One strict parser for every request body, before any route sees it.

An ASGI middleware reads the body of every request that may carry one (POST, PUT, PATCH,
DELETE), whatever its ``Content-Type`` says (``application/JSON``, ``Application/Json;
charset=utf-8``, ``text/plain`` or none: the API speaks JSON only, and a guard that depended on
the spelling let ``NaN`` through to an error page that could not render it):

* only once the request is admitted: a route that needs the access token refuses a request
  without it (401/429) before reading a byte of its body, so a client without the token
  cannot make the server hold bodies;
* at most :data:`MAX_BODY_BYTES` (413 beyond, before the rest is read), within
  :data:`BODY_TIMEOUT_S` seconds of the request head (408 after), and at most
  :data:`MAX_BODIES_IN_FLIGHT` bodies read at once (503 beyond, at once): a client that sends a
  head and then a byte of body now and then holds a socket for seconds, not for ever, and a
  thousand of them cannot starve ``/healthz`` or the viewer of the server's descriptors;
* strict JSON: ``NaN``, ``Infinity`` and numbers too large for a float (``1e999``) are refused,
  as are invalid UTF-8 and nesting too deep for the parser;
* the request then reaches FastAPI with ``Content-Type: application/json`` and the same bytes,
  so FastAPI's own parsing sees exactly what was checked.

Types are strict past this point: the request models (:mod:`cfsr_live.service.models`) run in
pydantic's
strict mode (no ``true`` for a number, no ``"32"`` for an integer), and every error the API
answers quotes at most :data:`MAX_QUOTE` characters of what it was sent (:func:`short`).
"""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import Callable
from typing import Any

__all__ = [
    "BODY_TIMEOUT_S",
    "MAX_BODIES_IN_FLIGHT",
    "MAX_BODY_BYTES",
    "MAX_QUOTE",
    "Refusal",
    "StrictJsonBody",
    "short",
]

#: the largest request body, bytes (the largest the API needs, a full configuration, is ~1 kB)
MAX_BODY_BYTES = 64 * 1024
#: seconds a client has to send a whole body once its head is in (a browser sends ~1 kB at once)
BODY_TIMEOUT_S = 10.0
#: request bodies read at the same time; more are refused at once (503) and their connection
#: closed. The viewer sends one at a time; 64 leaves room for scripts and several tabs.
MAX_BODIES_IN_FLIGHT = 64
#: a refusal before the body is read: (HTTP status, detail, extra response headers)
Refusal = tuple[int, str, list[tuple[bytes, bytes]]]
#: characters of a client's input an error message may quote
MAX_QUOTE = 200
_WITH_BODY = frozenset({"POST", "PUT", "PATCH", "DELETE"})


def short(value: Any, limit: int = MAX_QUOTE) -> str:
    """``value`` as text of at most ``limit`` characters (with how much was cut)."""
    text = value if isinstance(value, str) else repr(value)
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... ({len(text) - limit} more characters)"


class _Refused(ValueError):
    pass


def _constant(name: str) -> float:
    raise _Refused(f"the JSON body holds {name}: use a finite number")


def _float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise _Refused(f"the JSON body holds {short(text, 40)}, too large for a number")
    return v


def check_json(body: bytes) -> str | None:
    """Why ``body`` is not strict JSON (None when it is)."""
    try:
        json.loads(body.decode("utf-8"), parse_constant=_constant, parse_float=_float)
    except _Refused as exc:
        return str(exc)
    except UnicodeDecodeError as exc:
        return f"the body is not UTF-8 text (byte {exc.start})"
    except RecursionError:
        return "the JSON body is nested too deep"
    except ValueError as exc:
        return f"the body is not JSON: {short(str(exc), 120)}"
    return None


async def _answer(send, status: int, detail: Any, *, close: bool = False,
                  headers: list[tuple[bytes, bytes]] | tuple = ()) -> None:
    """A JSON error answer; ``close``: also close the connection (a body left unread)."""
    body = json.dumps({"detail": detail}).encode()
    head = [(b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()), *headers]
    if close:
        head.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": head})
    await send({"type": "http.response.body", "body": body})


class StrictJsonBody:
    """Pure ASGI middleware: every body checked by :func:`check_json` (422 naming the fault,
    in FastAPI's validation-error shape), capped at ``max_bytes`` (413) and ``timeout_s``
    seconds (408), at most ``max_in_flight`` read at once (503), and passed on as
    ``application/json``. ``admit(scope)`` runs first and may refuse the request (e.g. a
    missing token) before a byte of the body is read."""

    def __init__(self, app, *, max_bytes: int = MAX_BODY_BYTES,
                 timeout_s: float = BODY_TIMEOUT_S, max_in_flight: int = MAX_BODIES_IN_FLIGHT,
                 admit: Callable[[dict], Refusal | None] | None = None) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self.max_in_flight = max_in_flight
        self.admit = admit
        self.in_flight = 0  # bodies being read now (one event loop: no lock needed)

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope.get("method") not in _WITH_BODY:
            await self.app(scope, receive, send)
            return
        refusal = self.admit(scope) if self.admit is not None else None
        if refusal is not None:
            status, detail, headers = refusal
            await _answer(send, status, detail, close=True, headers=headers)
            return
        too_big = f"the request body is over {self.max_bytes} bytes"
        for k, v in scope.get("headers", []):
            if k == b"content-length":
                try:
                    if int(v) > self.max_bytes:
                        await _answer(send, 413, too_big, close=True)
                        return
                except ValueError:
                    pass
        if self.in_flight >= self.max_in_flight:
            await _answer(send, 503, f"{self.in_flight} request bodies are being read, the "
                          f"most at once; retry", close=True, headers=[(b"retry-after", b"1")])
            return
        self.in_flight += 1
        try:
            async with asyncio.timeout(self.timeout_s):
                body = await self._read(receive)
        except TimeoutError:
            await _answer(send, 408, f"the request body did not come within {self.timeout_s:g} s",
                          close=True)
            return
        finally:
            self.in_flight -= 1
        if body is None:  # the client left
            return
        if len(body) > self.max_bytes:
            await _answer(send, 413, too_big, close=True)
            return
        if body:
            why = check_json(body)
            if why is not None:
                await _answer(send, 422, [{"type": "json_invalid", "loc": ["body"],
                                           "msg": why, "input": None}])
                return
            headers = [(k, v) for k, v in scope.get("headers", []) if k != b"content-type"]
            scope = {**scope, "headers": [*headers, (b"content-type", b"application/json")]}
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _read(self, receive) -> bytes | None:
        """The whole body (cut at one chunk past ``max_bytes``), or None if the client left."""
        chunks: list[bytes] = []
        size = 0
        while True:
            msg = await receive()
            if msg["type"] == "http.disconnect":
                return None
            part = msg.get("body", b"")
            size += len(part)
            chunks.append(part)
            if size > self.max_bytes or not msg.get("more_body", False):
                return b"".join(chunks)
