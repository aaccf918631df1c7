"""The newest frame as PNG, an MJPEG stream, and the binary WebSocket for the viewer."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math

from fastapi import APIRouter, Depends, HTTPException, Query, Request, WebSocket
from fastapi.responses import Response, StreamingResponse
from pydantic import ValidationError
from starlette.websockets import WebSocketDisconnect, WebSocketState

from cfsr_live.service.body import short
from cfsr_live.service.deps import HubDep, require_token, ws_token_ok
from cfsr_live.service.hub import ClientQueue, FrameHub
from cfsr_live.service.models import ClientMessage, SchemaModel
from cfsr_live.service.render import encode_jpeg, encode_png, render_rgb
from cfsr_live.service.schema import schema_document
from cfsr_live.service.settings import MAX_FPS_RANGE

router = APIRouter(tags=["media"])
log = logging.getLogger("cfsr.media")

_SEND_TIMEOUT = 10.0


def _overlays(spec: str, known: tuple[str, ...]) -> tuple[str, ...]:
    """The mask names of an ``overlay`` query, each one of the slot's (``known``)."""
    out = tuple(s for s in (x.strip() for x in spec.split(",")) if s)
    bad = [s for s in out if s not in known]
    if bad:
        raise HTTPException(422, f"unknown overlay(s) {bad[:4]}; use {', '.join(known)}")
    return out


@router.get("/api/schema", response_model=SchemaModel,
            summary="the frame message's layout, mask names and colours, heat map, counters")
async def get_schema(hub: HubDep) -> dict:
    return schema_document(hub.slot.mask_names)


@router.get(
    "/api/frame.png",
    dependencies=[Depends(require_token)],
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}, 503: {"description": "no frame yet"}},
    summary="the newest reconstructed frame as PNG",
)
async def frame_png(
    hub: HubDep,
    view: str = Query("gray", pattern="^(gray|heat)$"),
    overlay: str = Query("", description="comma list of masks to tint (GET /api/schema's "
                         "masks: coarse, fine, motion with the built-in methods)"),
    wait: float = Query(2.0, ge=0, le=30, description="seconds to wait for a first frame"),
) -> Response:
    ov = _overlays(overlay, hub.slot.mask_names)
    f = hub.latest
    if f is None and wait > 0:
        f = await hub.wait_frame(wait)
    if f is None:
        raise HTTPException(503, "no frame yet")
    png = await asyncio.to_thread(lambda: encode_png(render_rgb(f, view=view, overlays=ov)))
    return Response(
        png,
        media_type="image/png",
        headers={"Cache-Control": "no-store", "X-Frame-Step": str(f.step),
                 "X-Method": f.method},
    )


@router.get(
    "/stream.mjpg",
    dependencies=[Depends(require_token)],
    response_class=StreamingResponse,
    responses={200: {"content": {"multipart/x-mixed-replace; boundary=frame": {}}}},
    summary="MJPEG stream of the reconstruction (for <img>, curl, VLC)",
)
async def mjpeg(
    request: Request,
    hub: HubDep,
    fps: float = Query(15.0, gt=0, le=60),
    view: str = Query("gray", pattern="^(gray|heat)$"),
    overlay: str = Query(""),
) -> StreamingResponse:
    ov = _overlays(overlay, hub.slot.mask_names)
    client = hub.add(ClientQueue("mjpeg", max_fps=fps, peer=str(request.client)))

    async def frames():
        try:
            while not await request.is_disconnected():
                try:
                    f = await asyncio.wait_for(client.get(), 1.0)
                except TimeoutError:
                    continue
                jpg = await asyncio.to_thread(
                    lambda f=f: encode_jpeg(render_rgb(f, view=view, overlays=ov))
                )
                yield (
                    b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                    + str(len(jpg)).encode()
                    + b"\r\n\r\n"
                    + jpg
                    + b"\r\n"
                )
                client.sent += 1
                await asyncio.sleep(1.0 / fps)
        finally:
            hub.remove(client)

    return StreamingResponse(
        frames(),
        media_type="multipart/x-mixed-replace; boundary=frame",
        headers={"Cache-Control": "no-store"},
    )


def _client_fps(value) -> float | None:
    """A WebSocket client's ``max_fps`` (query or message), never NaN, infinite or so small
    that its sender would sleep for ever."""
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        return None
    if not math.isfinite(v) or v <= 0:
        return None
    lo, hi = MAX_FPS_RANGE  # outside: clamped (0 or none: no cap)
    return min(max(v, lo), hi)


def _client_message(msg: dict, client: ClientQueue) -> str | None:
    """Apply a client's message (:class:`~cfsr_live.service.models.ClientMessage`); why it is
    refused (unknown fields named), or None. Binary messages are refused: a client sends text."""
    text = msg.get("text")
    if text is None:
        return "send JSON text, not binary" if msg.get("bytes") else None
    try:
        req = ClientMessage.model_validate_json(text)
    except ValidationError as exc:
        faults = []
        for e in exc.errors()[:3]:
            where = ".".join(str(x) for x in e.get("loc", ())) or "message"
            why = "unknown field" if e["type"] == "extra_forbidden" else short(e["msg"], 40)
            faults.append(f"{short(where, 24)}: {why}")
        return "; ".join(faults)
    if "max_fps" in req.model_fields_set:
        client.max_fps = _client_fps(req.max_fps)
    return None


@router.websocket("/ws")
async def ws(websocket: WebSocket) -> None:
    """Binary frame messages (see ``cfsr_live.service.hub``), one per new frame, latest-only per
    client.

    The client may send JSON text ``{"max_fps": N}`` to cap its own rate.
    """
    if not ws_token_ok(websocket):
        await websocket.close(code=1008, reason="missing or wrong access token")
        return
    await websocket.accept()
    hub: FrameHub = websocket.app.state.hub
    max_fps = _client_fps(websocket.query_params.get("max_fps"))
    client = hub.add(ClientQueue("ws", max_fps=max_fps, peer=str(websocket.client)))

    async def sender() -> None:
        while True:
            msg = await client.get()
            await asyncio.wait_for(websocket.send_bytes(msg), _SEND_TIMEOUT)
            client.sent += 1
            if client.max_fps:
                await asyncio.sleep(1.0 / client.max_fps)

    send_task = asyncio.create_task(sender())
    try:
        while True:
            recv = asyncio.create_task(websocket.receive())
            done, _ = await asyncio.wait({recv, send_task}, return_when=asyncio.FIRST_COMPLETED)
            if send_task in done:
                recv.cancel()
                exc = send_task.exception()
                if exc is not None and not isinstance(exc, WebSocketDisconnect):
                    log.info("websocket client %s dropped: %r", client.id, exc)
                break
            msg = recv.result()
            if msg["type"] == "websocket.disconnect":
                break
            refused = _client_message(msg, client)
            if refused is not None:
                # the WebSocket's 422: an application close code (4000 + the HTTP status)
                # and a reason naming the fault (a close reason holds at most 123 bytes)
                await websocket.close(code=4422, reason=refused[:120])
                break
    except WebSocketDisconnect:
        pass
    finally:
        send_task.cancel()
        with contextlib.suppress(BaseException):
            await send_task
        hub.remove(client)
        if websocket.application_state == WebSocketState.CONNECTED:
            with contextlib.suppress(Exception):
                await websocket.close()
