"""Pages that ask nothing of another machine: every HTML page the service serves (the viewer,
``/docs``, ``/redoc``) carries a Content-Security-Policy that lets it load scripts, styles,
images, fonts, workers and connections from this service only. The browser then refuses what a
bundled asset still points outside (ReDoc's footer shows its maker's logo from a CDN) before
any request leaves the machine.
"""

from __future__ import annotations

from typing import Any

__all__ = ["LOCAL_ONLY_POLICY", "LocalPagesOnly"]

#: what an HTML page of the service may load: itself, inline styles and scripts (the API docs'
#: start-up code), ``data:``/``blob:`` images and workers (ReDoc's search, the viewer's icon)
LOCAL_ONLY_POLICY = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data: blob:; font-src 'self' data:; worker-src 'self' blob:; "
    "connect-src 'self'; frame-ancestors 'self'; base-uri 'self'; form-action 'self'"
)


class LocalPagesOnly:
    """ASGI middleware: adds :data:`LOCAL_ONLY_POLICY` to every ``text/html`` response."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self._policy = LOCAL_ONLY_POLICY.encode()

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_policy(message: dict) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                kind = next((v for k, v in headers if k.lower() == b"content-type"), b"")
                if kind.startswith(b"text/html"):
                    headers.append((b"content-security-policy", self._policy))
                    message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_policy)
