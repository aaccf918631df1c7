"""Liveness and readiness."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from fastapi import APIRouter, Request, Response

from cfsr_live.driver.source import SourceState
from cfsr_live.service.deps import RuntimeDep, hide_paths
from cfsr_live.service.models import Health

router = APIRouter(tags=["health"])

#: a worker whose loop has not beaten for this long is not ready: its loop turns every frame
#: (a CFSR frame takes ~0.1 s), so only a frozen, stopped or still-compiling worker stays silent
READY_HEARTBEAT_S = 5.0


@router.get("/healthz", response_model=Health, summary="process and event loop alive")
async def healthz(rt: RuntimeDep) -> Health:
    return Health(uptime_s=time.monotonic() - rt.started)


#: a source that streams while the worker publishes no frame for this long (or three frame
#: intervals at the configured max_fps, if longer) is not ready: every frame fails, or the
#: source cannot be shown
READY_FRAME_S = 5.0


def _now() -> float:
    return time.monotonic()


@dataclass
class _FrameWatch:
    """When /readyz last saw the worker's frame count move, and the input at that time."""

    acq_id: int = 0
    frames_out: float = -1.0
    frames_in: int = 0
    since: float = 0.0


def _no_frame_for(request: Request, rt, frames_out: float) -> float:
    """Seconds the worker has published no frame while the source delivered frames (0 when
    it did publish, or nothing came in). Read each time /readyz is asked."""
    acq, t = rt.acq, _now()
    w: _FrameWatch | None = getattr(request.app.state, "frame_watch", None)
    if w is None:
        w = request.app.state.frame_watch = _FrameWatch()
    frames_in = int(getattr(acq, "frames", 0))
    if id(acq) != w.acq_id or frames_out != w.frames_out:
        w.acq_id, w.frames_out, w.frames_in, w.since = id(acq), frames_out, frames_in, t
        return 0.0
    if frames_in <= w.frames_in:
        w.since = t  # nothing came in: nothing could be shown
        return 0.0
    return t - w.since


@router.get("/readyz", summary="503 unless the source streams (and is not in error), the "
            "worker is alive, beat "
            f"within {READY_HEARTBEAT_S:g} s and publishes frames of what streams in",
            responses={503: {"description": "not ready (the same fields, and the reason when "
                                            "one is known)"}})
async def readyz(request: Request, response: Response, rt: RuntimeDep) -> dict:
    w = rt.worker
    age = w.heartbeat_age() if w else math.inf
    fresh = age <= READY_HEARTBEAT_S
    streaming = bool(rt.acq and rt.acq.running)
    frames_out = w.stats().frames_out if w else 0
    stalled = _no_frame_for(request, rt, float(frames_out)) if streaming else 0.0
    max_fps = getattr(getattr(rt, "config", None), "max_fps", None) or 1.0
    frame_limit = max(READY_FRAME_S, 3.0 / max_fps)
    src = rt.source
    failed = src is not None and src.state == SourceState.ERROR
    ok = bool(w and w.alive and w.ready.is_set() and fresh and streaming and not failed
              and stalled <= frame_limit)
    out = {"ready": ok, "heartbeat_age_s": age if math.isfinite(age) else None,
           "no_frame_s": round(stalled, 3)}
    if not ok:
        response.status_code = 503
        if failed:  # the acquisition thread may still run: the source itself says it failed
            why = hide_paths(request.app.state.settings, src.last_error) or "failed"
            out["reason"] = f"the source is in error: {why}"
        elif streaming and stalled > frame_limit:
            out["reason"] = (f"the source streams but no frame was published for "
                             f"{stalled:.1f} s")
    return out
