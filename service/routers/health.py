"""Liveness and readiness."""

from __future__ import annotations

import math
import time

from fastapi import APIRouter, Response

from service.deps import RuntimeDep
from service.models import Health

router = APIRouter(tags=["health"])

#: a worker whose loop has not beaten for this long is not ready: its loop turns every frame
#: (a CFSR frame takes ~0.1 s), so only a frozen, stopped or still-compiling worker stays silent
READY_HEARTBEAT_S = 5.0


@router.get("/healthz", response_model=Health, summary="process and event loop alive")
async def healthz(rt: RuntimeDep) -> Health:
    return Health(uptime_s=time.monotonic() - rt.started)


@router.get("/readyz", summary="503 unless the source streams and the worker is alive and "
            f"beat within {READY_HEARTBEAT_S:g} s")
async def readyz(response: Response, rt: RuntimeDep) -> dict:
    w = rt.worker
    age = w.stats().get("heartbeat_age_s", math.inf) if w else math.inf
    fresh = age <= READY_HEARTBEAT_S
    ok = bool(w and w.alive and w.ready.is_set() and fresh and rt.acq and rt.acq.running)
    if not ok:
        response.status_code = 503
    return {"ready": ok, "heartbeat_age_s": age if math.isfinite(age) else None}
