"""Liveness and readiness."""

from __future__ import annotations

import time

from fastapi import APIRouter, Response

from service.deps import RuntimeDep
from service.models import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="process and event loop alive")
async def healthz(rt: RuntimeDep) -> Health:
    return Health(uptime_s=time.monotonic() - rt.started)


@router.get("/readyz", summary="503 unless the source streams and the worker is alive")
async def readyz(response: Response, rt: RuntimeDep) -> dict:
    w = rt.worker
    ok = bool(w and w.alive and w.ready.is_set() and rt.acq and rt.acq.running)
    if not ok:
        response.status_code = 503
    return {"ready": ok}
