"""Method, parameters and display scaling, switchable at run time."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Response

from cfsr.methods.registry import get_method, methods
from cfsr_live.service.body import short
from cfsr_live.service.config import ConfigChange
from cfsr_live.service.deps import RuntimeDep, require_token
from cfsr_live.service.models import ConfigModel, ConfigUpdate, Limits, MethodInfo

router = APIRouter(tags=["config"], dependencies=[Depends(require_token)])


def check_param_types(method: str, params: dict[str, Any]) -> None:
    """Each method parameter checked strictly (:meth:`cfsr.methods.registry.Param.check`): its
    JSON type must be its own (a number for a numeric parameter, ``true`` and ``"32"`` are
    not), and its value in range. ValueError naming the parameter; unknown names and
    methods are the method's own check to name, with the known ones."""
    try:
        table = get_method(method).params
    except ValueError:
        return
    for name, value in params.items():
        if name in table:
            table[name].check(value, strict=True, name=short(name, 64))


@router.get("/api/methods", response_model=list[MethodInfo],
            summary="reconstruction methods with their parameters")
async def list_methods() -> list[dict]:
    return list(methods().values())


@router.get("/api/limits", response_model=Limits,
            summary="bounds the API enforces (frame-rate cap, recording names)")
async def get_limits() -> Limits:
    """The viewer reads its form bounds here instead of repeating them."""
    return Limits()


@router.get("/api/config", response_model=ConfigModel, summary="current configuration")
async def get_config(rt: RuntimeDep) -> dict:
    return rt.get_config()


@router.put("/api/config", response_model=ConfigModel,
            summary="switch method / parameters / display scaling",
            responses={
                202: {"model": ConfigModel,
                      "description": "stored and sent, but the worker has not answered yet "
                      "(busy, e.g. compiling); `state` is pending"},
                422: {"description": "unknown method, parameter out of range (the message "
                      "names it and its range), CFSR's tier among the parameters (it is "
                      "the field quality), or a configuration the worker could not "
                      "apply (it keeps the previous one, which stays stored)"},
            })
async def put_config(body: ConfigUpdate, rt: RuntimeDep, response: Response) -> dict:
    try:
        change = ConfigChange(  # refuses the tier among the parameters, naming its field
            method=body.method,
            params=body.params,
            display=body.display.model_dump() if body.display else None,
            max_fps=body.max_fps,
            defects=body.defects,
            quality=body.quality,
        )
        if body.params:
            check_param_types(body.method or rt.config.method.method, body.params)
        # in a thread: it waits (a few seconds at most) for the worker's answer
        out = await asyncio.to_thread(rt.set_config, change)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from exc
    if out.get("state") == "pending":
        response.status_code = 202
    return out
