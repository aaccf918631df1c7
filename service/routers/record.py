"""Recording the live stream to .dat + sidecar in the data folder."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Depends, HTTPException

from cfsr_live.service.deps import RuntimeDep, hide_paths, require_token
from cfsr_live.service.models import RecordRequest, RecordStatus
from cfsr_live.service.runtime import ConflictError

router = APIRouter(tags=["record"], dependencies=[Depends(require_token)])


@router.get("/api/record", response_model=RecordStatus, summary="recording state")
async def record_status(rt: RuntimeDep) -> RecordStatus:
    return _public(rt, rt.record_status())


def _public(rt, st: RecordStatus) -> RecordStatus:
    """The status with no absolute server path in its error text (the path is relative)."""
    return st.model_copy(update={"error": hide_paths(rt.settings, st.error)})


@router.post("/api/record", response_model=RecordStatus,
             summary="start or stop recording (DATA_DIR/recordings/NAME.dat + sidecar)",
             responses={409: {"description": "already recording / not recording / exists"},
                        507: {"description": "not enough free space to start"}})
async def record(body: RecordRequest, rt: RuntimeDep) -> RecordStatus:
    try:
        if body.action == "start":
            st = await asyncio.to_thread(
                rt.start_recording, body.name, body.max_frames, body.max_bytes
            )
        else:
            st = await asyncio.to_thread(rt.stop_recording)
    except ConflictError as exc:
        raise HTTPException(409, hide_paths(rt.settings, str(exc))) from exc
    except ValueError as exc:
        raise HTTPException(422, hide_paths(rt.settings, str(exc))) from exc
    except OSError as exc:  # no room on the disk: the request cannot be served now
        raise HTTPException(507, hide_paths(rt.settings, str(exc))) from exc
    return _public(rt, st)
