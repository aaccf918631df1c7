"""One strict parser for every request body, before any route sees it.

An ASGI middleware reads the body of every request that may carry one (POST, PUT, PATCH,
DELETE), whatever its ``Content-Type`` says (``application/JSON``, ``Application/Json;
charset=utf-8``, ``text/plain`` or none: the API speaks JSON only, and a guard that depended on
the spelling let ``NaN`` through to an error page that could not render it):

* at most :data:`MAX_BODY_BYTES` (413 beyond, before the rest is read);
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

import json
import math
from typing import Any

__all__ = ["MAX_BODY_BYTES", "MAX_QUOTE", "StrictJsonBody", "short"]

#: the largest request body, bytes (the largest the API needs, a full configuration, is ~1 kB)
MAX_BODY_BYTES = 64 * 1024
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


async def _answer(send, status: int, detail: Any) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


class StrictJsonBody:
    """Pure ASGI middleware: every body checked by :func:`check_json` (422 naming the fault,
    in FastAPI's validation-error shape), capped at ``max_bytes`` (413), and passed on as
    ``application/json``."""

    def __init__(self, app, *, max_bytes: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope.get("method") not in _WITH_BODY:
            await self.app(scope, receive, send)
            return
        too_big = f"the request body is over {self.max_bytes} bytes"
        for k, v in scope.get("headers", []):
            if k == b"content-length":
                try:
                    if int(v) > self.max_bytes:
                        await _answer(send, 413, too_big)
                        return
                except ValueError:
                    pass
        chunks: list[bytes] = []
        size = 0
        while True:
            msg = await receive()
            if msg["type"] == "http.disconnect":
                return
            part = msg.get("body", b"")
            size += len(part)
            if size > self.max_bytes:
                await _answer(send, 413, too_big)
                return
            chunks.append(part)
            if not msg.get("more_body", False):
                break
        body = b"".join(chunks)
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
