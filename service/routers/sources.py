"""Sources (recordings in the data folder, the demo, the USB camera, the simulator) and
replay controls."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Depends, HTTPException

from cfsr_live.driver.source import SourceError, SourceState
from cfsr_live.service.deps import RuntimeDep, hide_paths, require_token
from cfsr_live.service.models import (
    HoldRequest,
    ReplayState,
    ReplayUpdate,
    SeekRequest,
    SourceItem,
    SourceSelect,
    SourceStatus,
    StepRequest,
)
from cfsr_live.service.runtime import ConflictError, Runtime

# (NaN/Infinity in a body is refused before any route: service.body)
router = APIRouter(tags=["sources"], dependencies=[Depends(require_token)])


@router.get("/api/sources", response_model=list[SourceItem],
            summary="what can be opened: data-folder recordings, demo, USB camera, simulator")
async def list_sources(rt: RuntimeDep) -> list[dict]:
    return await asyncio.to_thread(rt.list_sources)


@router.put("/api/source", response_model=SourceStatus, summary="switch the live source",
            responses={404: {"description": "id not in GET /api/sources"},
                       422: {"description": "the source could not be opened"}})
async def put_source(body: SourceSelect, rt: RuntimeDep) -> SourceStatus:
    try:
        d = await asyncio.to_thread(rt.switch_source, body.id)
    except KeyError:
        raise HTTPException(404, f"no source with id {body.id!r}; see GET /api/sources") from None
    except (ValueError, OSError, SourceError) as exc:
        raise HTTPException(
            422, f"cannot open {body.id!r}: {hide_paths(rt.settings, str(exc))}") from exc
    # the state and capabilities as the switch left them (the source may move on at once)
    st = rt.source_report().status
    return st.model_copy(update={k: d[k] for k in ("state", "capabilities") if k in d})


def _replay(rt: Runtime):
    try:
        return rt.replay()
    except ConflictError as exc:
        raise HTTPException(409, str(exc)) from exc


def _replay_to_act(rt: Runtime):
    """The replay controls, for an action: 409 while the source is in error (a file that
    shrank under it stays failed until reopened; a play or seek would answer 200 and do
    nothing)."""
    ctl = _replay(rt)
    src = rt.source
    if src is not None and src.state == SourceState.ERROR:
        why = hide_paths(rt.settings, src.last_error) or "failed"
        raise HTTPException(409, f"the source is in error ({why}); select it again "
                            "(PUT /api/source) to reopen it")
    return ctl


@router.get("/api/replay", response_model=ReplayState, summary="replay transport state",
            responses={409: {"description": "the current source is not a replay"}})
async def get_replay(rt: RuntimeDep) -> dict:
    return _replay(rt).state()


@router.put("/api/replay", response_model=ReplayState, summary="play/pause, speed, loop",
            responses={409: {"description": "the current source is not a replay, or is in "
                                        "error"}})
async def put_replay(body: ReplayUpdate, rt: RuntimeDep) -> dict:
    ctl = _replay_to_act(rt)
    try:
        if body.speed is not None:
            ctl.set_speed(body.speed)
        if body.loop is not None:
            ctl.set_loop(body.loop)
        if body.playing is True:
            ctl.play()
        elif body.playing is False:
            ctl.pause()
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from exc
    return ctl.state()


@router.post("/api/replay/seek", response_model=ReplayState, summary="jump to a frame or time",
             responses={409: {"description": "the current source is not a replay"}})
async def seek(body: SeekRequest, rt: RuntimeDep) -> dict:
    ctl = _replay_to_act(rt)
    st = ctl.state()
    if body.position is None and body.seconds is None:
        raise HTTPException(422, "give position (frames) or seconds")
    pos = body.position if body.position is not None else int(round(body.seconds * st["rate_hz"]))
    try:
        ctl.seek(pos)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from exc
    return ctl.state()


@router.post("/api/replay/hold", summary="compute frames at one step (to compare methods)",
             responses={409: {"description": "the current source is not a replay"}})
async def hold(body: HoldRequest, rt: RuntimeDep) -> dict:
    """Frames at ``step`` instead of the newest while the worker's buffer holds it: on a
    paused replay, a method that looks less far ahead than the pinned one shows the pinned
    step too. The viewer sets it when it pins a frame and clears it on play, step or seek."""
    _replay_to_act(rt)
    rt.hold_step(body.step)
    return {"step": body.step}


@router.post("/api/replay/step", response_model=ReplayState,
             summary="deliver n frames (while paused)",
             responses={409: {"description": "the current source is not a replay"}})
async def step(body: StepRequest, rt: RuntimeDep) -> dict:
    ctl = _replay_to_act(rt)
    ctl.step(body.n)
    return ctl.state()
