"""Method, parameters and display scaling, switchable at run time."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException

from service.deps import RuntimeDep, require_token
from service.models import ConfigModel, ConfigUpdate, MethodInfo

router = APIRouter(tags=["config"], dependencies=[Depends(require_token)])


@router.get("/api/methods", response_model=list[MethodInfo],
            summary="reconstruction methods with their parameters")
async def list_methods() -> list[dict]:
    from cfsr.methods.registry import methods

    return list(methods().values())


@router.get("/api/config", response_model=ConfigModel, summary="current configuration")
async def get_config(rt: RuntimeDep) -> dict:
    return rt.get_config()


@router.put("/api/config", response_model=ConfigModel,
            summary="switch method / parameters / display scaling",
            responses={422: {"description": "unknown method or invalid parameter"}})
async def put_config(body: ConfigUpdate, rt: RuntimeDep) -> dict:
    try:
        return rt.set_config(
            method=body.method,
            params=body.params,
            display=body.display.model_dump() if body.display else None,
            max_fps=body.max_fps,
        )
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from exc
