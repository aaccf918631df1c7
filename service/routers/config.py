"""Method, parameters and display scaling, switchable at run time."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Response

from cfsr_live.service.body import short
from cfsr_live.service.config import ConfigChange
from cfsr_live.service.deps import RuntimeDep, require_token
from cfsr_live.service.models import ConfigModel, ConfigUpdate, Limits, MethodInfo

router = APIRouter(tags=["config"], dependencies=[Depends(require_token)])


def check_param_types(method: str, params: dict[str, Any]) -> None:
    """A method parameter's JSON type must be its own: a number for a numeric parameter
    (``true`` and ``"32"`` are not), a string among text choices, a boolean for a switch.
    ValueError naming the parameter; ranges, names and choices are the method's to check."""
    from cfsr.methods.registry import methods

    table = methods().get(method, {}).get("params", {})
    for name, value in params.items():
        info = table.get(name)
        if info is None:
            continue  # an unknown name: the method's own check names it with the known ones
        default = info.get("default")
        numeric = info.get("minimum") is not None or info.get("maximum") is not None
        if isinstance(default, bool):
            ok = isinstance(value, bool)
            want = "true or false"
        elif numeric or isinstance(default, int | float):
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            want = "a number"
        elif info.get("choices"):
            ok = type(value) in {type(c) for c in info["choices"]}
            want = "one of " + ", ".join(map(str, info["choices"]))
        else:
            ok = isinstance(value, str) if isinstance(default, str) else True
            want = "text"
        if not ok:
            raise ValueError(f"parameter {short(name, 64)}={short(value, 64)}: expected {want} "
                             f"({info.get('range') or ''})".replace(" ()", ""))


@router.get("/api/methods", response_model=list[MethodInfo],
            summary="reconstruction methods with their parameters")
async def list_methods() -> list[dict]:
    from cfsr.methods.registry import methods

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
                      "names it and its range), or a configuration the worker could not "
                      "apply (it keeps the previous one, which stays stored)"},
            })
async def put_config(body: ConfigUpdate, rt: RuntimeDep, response: Response) -> dict:
    try:
        if body.params:
            check_param_types(body.method or rt.config.method.method, body.params)
        # in a thread: it waits (a few seconds at most) for the worker's answer
        change = ConfigChange(
            method=body.method,
            params=body.params,
            display=body.display.model_dump() if body.display else None,
            max_fps=body.max_fps,
        )
        out = await asyncio.to_thread(rt.set_config, change)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from exc
    if out.get("state") == "pending":
        response.status_code = 202
    return out
