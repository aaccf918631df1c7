"""Typed request and response models of the HTTP API (they make the OpenAPI document)."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from cfsr_live.service.config import GainMode, Quality
from cfsr_live.service.settings import (
    MAX_DISPLAY_PIXELS,
    MAX_FPS_RANGE,
    MIN_DISPLAY_GAIN,
    RECORDING_NAME_PATTERN,
)
from cfsr_live.service.status import (
    ClientDrops,
    Drops,
    RecordStatus,
    ReplayState,
    RingStatus,
    SourceStatus,
    StatusModel,
    WorkerStatus,
)

__all__ = [
    "ClientDrops",
    "ClientMessage",
    "ConfigModel",
    "ConfigUpdate",
    "DisplayConfig",
    "Drops",
    "FiniteFloat",
    "Health",
    "Limits",
    "MethodInfo",
    "NumberRange",
    "RecordRequest",
    "RecordStatus",
    "ReplayState",
    "ReplayUpdate",
    "RingStatus",
    "SeekRequest",
    "SourceItem",
    "SourceSelect",
    "SourceStatus",
    "StatusModel",
    "StepRequest",
    "WorkerStatus",
]

#: Request bodies are read in pydantic's strict mode: ``true`` is no number, ``1`` no boolean,
#: ``"32"`` no integer (a client that sends them has a bug the service should name, not guess
#: around). Bodies are strict JSON before they get here (:mod:`cfsr_live.service.body`).
#: Unknown fields are refused (422 naming them): ``{"max_fsp": 10}`` or ``{"display":
#: {"gainmode": "auto"}}`` was accepted and silently changed nothing (or reset a default).
STRICT = ConfigDict(strict=True, extra="forbid")


def _nan_as_text(v: Any) -> Any:
    # A 422 answer echoes the bad input, and JSON cannot carry NaN or Infinity (rendering
    # it fails: a 500). As text, the value is still refused ("NaN" is no finite number) and
    # the answer can name it.
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


#: A float that must be finite: NaN and +-Infinity are refused (422, not 500). Starlette's
#: JSON parser accepts the literals ``NaN``/``Infinity`` and ``1e999`` gives an infinity, and
#: NaN passes every ``gt``/``le`` bound (all comparisons with NaN are false).
FiniteFloat = Annotated[float, Field(allow_inf_nan=False), BeforeValidator(_nan_as_text)]


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    uptime_s: float


class ClientMessage(BaseModel):
    """What a WebSocket client may send (JSON text): its own frame-rate cap."""

    model_config = STRICT

    max_fps: FiniteFloat | None = Field(
        None, description="most frames/s this client wants (clamped to the limits; 0 or null: "
        "no cap of its own)")


class DisplayConfig(BaseModel):
    gain_mode: GainMode = Field(
        "recording",
        description="recording: the file's display gain if it has one, else auto; auto: the "
        "99.5th percentile of each frame; fixed: `gain`",
    )
    gain: FiniteFloat | None = Field(
        None, ge=MIN_DISPLAY_GAIN, le=1,
        description="firing rate shown as white, spikes/step (fixed mode)",
    )


class DisplayUpdate(DisplayConfig):
    model_config = STRICT


class ConfigModel(BaseModel):
    method: str = Field(description="reconstruction method (see GET /api/methods)")
    params: dict[str, Any] = Field(description="method parameters, validated by the method")
    display: DisplayConfig
    max_fps: float = Field(description="most frames per second the worker publishes")
    quality: Quality | None = Field(
        None, description="CFSR's tier in the live service: auto (full when max_fps allows "
        "it, fast frames between), full or fast; null for a method without tiers")
    defects: bool = Field(True, description="hot and dead pixels (and a calibration's gain) "
                          "corrected before every method; the status's worker.defects says "
                          "what the map holds")
    effective_gain: float | None = Field(
        None, description="gain in use (None: automatic per frame), spikes/step"
    )
    state: Literal["applied", "pending"] = Field(
        "applied",
        description="after PUT: applied (the worker runs it; HTTP 200) or pending (the worker "
        "did not answer within a few seconds, e.g. compiling; HTTP 202: it applies commands in "
        "order, see worker.applied_version in GET /api/status)",
    )
    version: int | None = Field(None, description="after PUT: the worker's config version")


class NumberRange(BaseModel):
    minimum: float = Field(description="smallest accepted value")
    maximum: float = Field(description="largest accepted value")


class MaskInfo(BaseModel):
    """One mask plane of the frame message: its name, overlay colour and meaning."""

    name: str
    color: list[int] = Field(description="overlay colour, RGB 0..255")
    meaning: str


class SchemaModel(BaseModel):
    """The live frame schema (:mod:`cfsr_live.service.schema`), for clients that decode the
    WebSocket frames: the viewer reads the header offsets, the mask names (in plane order),
    their colours and the heat colour map here instead of repeating them."""

    ws_version: int
    ws_header_bytes: int
    ws_offsets: dict[str, int] = Field(description="byte offset of each header field")
    method_name_bytes: int
    quality_tiers: list[str] = Field(description="the header's quality byte: the index of the "
                                     "tier that made the frame (\"\": a method without tiers)")
    masks: list[MaskInfo] = Field(description="the mask planes, in the order they follow "
                                  "the image; bit k of mask_flags marks plane k present")
    mask_alpha: float = Field(description="opacity of a mask's colour over the image")
    heat_lut: list[int] = Field(description="256 x RGB heat colour map, flattened")
    counters: dict[str, str] = Field(description="the worker's counters and their meaning")


class Limits(BaseModel):
    """Bounds the API enforces, for clients that check input before sending it.

    Why an endpoint: the viewer's form fields take them from here, so each rule is written
    once (:mod:`cfsr_live.service.settings`) and a change there reaches the page with no edit to it.
    """

    max_fps: NumberRange = Field(
        default_factory=lambda: NumberRange(minimum=MAX_FPS_RANGE[0], maximum=MAX_FPS_RANGE[1]),
        description="frames per second the worker (config `max_fps`) or one WebSocket client "
        "may ask for",
    )
    max_frame_pixels: int = Field(
        MAX_DISPLAY_PIXELS,
        description="most pixels (width x height) a source may have: what the display's frame "
        "slot holds; a recording over it is listed with a note and cannot be selected",
    )
    recording_name_pattern: str = Field(
        RECORDING_NAME_PATTERN,
        description="regular expression a recording's name (POST /api/record) must match; "
        "Python and ECMAScript read it alike",
    )


class ConfigUpdate(BaseModel):
    model_config = STRICT

    method: str | None = Field(None, max_length=64)
    params: dict[str, Any] | None = Field(
        None, description="parameters to set; omitted ones keep their values (reset on a "
        "method change); each must lie in its range (GET /api/methods), else 422"
    )
    display: DisplayUpdate | None = None
    max_fps: FiniteFloat | None = Field(
        None, ge=MAX_FPS_RANGE[0], le=MAX_FPS_RANGE[1],
        description="most frames per second the worker publishes",
    )
    defects: bool | None = Field(
        None, description="correct hot and dead pixels (and a calibration's gain) before "
        "every method: true (the default) or false (the map is still learnt)")
    quality: Quality | None = Field(
        None, description="CFSR's tier: auto (full when max_fps allows it, fast frames "
        "between), full or fast; omitted: kept (auto after a change of method). Not a "
        "parameter: params.quality is refused (422); ignored by a method without tiers")


class ParamInfo(BaseModel):
    default: Any
    unit: str
    help: str
    minimum: float | None = Field(None, description="smallest accepted value (numbers)")
    maximum: float | None = Field(None, description="largest accepted value (numbers)")
    choices: list[Any] | None = Field(None, description="accepted values (text)")
    range: str = Field("", description="the accepted values in words")


class MethodInfo(BaseModel):
    name: str
    summary: str
    reference: str = ""
    masks: list[str]
    params: dict[str, ParamInfo]
    presets: dict[str, dict[str, Any]] = {}
    max_window_steps: int | None = Field(
        None, description="most steps a parameter set may reach around t (before + after)"
    )


class ReplayUpdate(BaseModel):
    model_config = STRICT

    playing: bool | None = None
    speed: FiniteFloat | None = Field(None, gt=0, le=1000, description="1.0 = real time")
    loop: bool | None = None


class SeekRequest(BaseModel):
    model_config = STRICT

    # bounds keep seconds * rate_hz an exact int64 frame (2^48 frames: 223 years at 40 kHz)
    position: int | None = Field(None, ge=0, le=1 << 48, description="file frame")
    seconds: FiniteFloat | None = Field(
        None, ge=0, le=(1 << 48) / 40_000, description="time into the recording, s"
    )


class HoldRequest(BaseModel):
    model_config = STRICT

    step: int | None = Field(
        ge=0, le=1 << 62,
        description="the step to compute frames at instead of the newest, while the worker's "
        "buffer holds it (comparing methods on one step of a paused replay); null: the newest")


class StepRequest(BaseModel):
    model_config = STRICT

    n: int = Field(1, ge=1, le=1_000_000, description="frames to deliver while paused")


class SourceItem(BaseModel):
    id: str
    kind: str
    name: str
    frames: int | None = None
    bytes: int | None = None
    width: int | None = None
    height: int | None = None
    duration_s: float | None = None
    note: str | None = None
    current: bool = False


class SourceSelect(BaseModel):
    model_config = STRICT

    id: str = Field(max_length=4096, description="an id from GET /api/sources")


class RecordRequest(BaseModel):
    model_config = STRICT

    action: Literal["start", "stop"]
    name: str | None = Field(
        None, pattern=RECORDING_NAME_PATTERN,
        description="file name without folder (.dat added); default rec-<time>",
    )
    max_frames: int | None = Field(None, ge=1, description="stop by itself after this many")
    max_bytes: int | None = Field(
        None, ge=1, le=2**50,
        description="size cap of the .dat in bytes (default and upper limit: the free space "
        "less 64 MB); the recording stops cleanly there",
    )
