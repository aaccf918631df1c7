"""Test hooks (only with ``cfsr serve --test-hooks``): make the worker crash on purpose."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Depends, HTTPException
from pydantic import BaseModel

from cfsr_live.service.deps import RuntimeDep, require_token
from cfsr_live.service.models import STRICT

router = APIRouter(tags=["debug"], dependencies=[Depends(require_token)])


class Inject(BaseModel):
    model_config = STRICT

    fault: Literal["crash", "raise"]


@router.post("/api/debug/worker", summary="inject a worker fault (test hook)")
async def inject(body: Inject, rt: RuntimeDep) -> dict:
    if rt.worker is None:
        raise HTTPException(409, "no worker")
    rt.worker.inject(body.fault)
    return {"injected": body.fault, "pid": rt.worker.pid}
