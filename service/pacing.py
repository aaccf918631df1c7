"""How the live worker paces its frames from their measured cost (ms of pool time per frame):
CFSR's ``auto`` tier's choice between ``full`` and ``fast`` frames, and when a computed frame
is too late to show."""

from __future__ import annotations

from typing import Any, NamedTuple

from cfsr_live.service.config import WorkerConfig

__all__ = ["FrameTask", "LATE_S", "late_after_s", "pick_tier", "tiers_of"]

#: the least age (s, since its newest spike arrived) at which a frame is too late to show while
#: a newer frame of its config computes; a slower pipeline gets longer (:func:`late_after_s`)
LATE_S = 1.0


class FrameTask(NamedTuple):
    """A frame handed to the pool: its step, when its newest spike arrived, the tier, the
    config version it was computed under, when and to which process it went, whether it
    is that process's first frame of its method and tier (which may wait on the compiler),
    the step clock its step counts on (the worker's ``_restart_clock``), and whether it is a
    rung of the ladder shown while the config's first frame compiles."""

    step: int
    arrival: float
    quality: str
    version: int
    submitted: float
    process: int
    method: str
    cold: bool
    clock: int
    rung: bool = False  # a stand-in of the ladder (CSR while CFSR compiles), not the config's


def pick_tier(
    full_ms: float | None, fast_ms: float | None, budget_ms: float, credit: float
) -> tuple[str, float]:
    """CFSR's auto tier for the next frame, and the credit carried to the one after.

    ``full_ms``/``fast_ms``: measured cost of a frame of each tier (None: not measured yet,
    so that tier is tried); ``budget_ms``: what one frame may cost for the pool to keep the
    frame rate (processes / max_fps). Full when full frames fit the budget; otherwise the
    share of full frames that keeps the mean cost within it, ``(budget - fast) / (full -
    fast)``, spread evenly by the credit (none when even fast frames exceed it).
    """
    if full_ms is None:
        return "full", credit
    if full_ms <= budget_ms:
        return "full", 0.0
    if fast_ms is None:
        return "fast", credit
    share = 0.0 if full_ms <= fast_ms else (budget_ms - fast_ms) / (full_ms - fast_ms)
    credit += min(1.0, max(0.0, share))
    if credit >= 1.0:
        return "full", credit - 1.0
    return "fast", credit


def tiers_of(cfg: WorkerConfig) -> dict[str, Any]:
    """The method configs a worker config runs, by tier: the config as given under its own
    ``quality`` (``full`` for a method without one), or for a method with a ``quality``
    parameter (CFSR) under ``quality = auto``, its ``full`` and ``fast`` tiers."""
    m = cfg.method
    if "quality" not in m.params:
        return {"full": m}
    if cfg.quality != "auto":
        return {str(m.params["quality"]): m}
    return {
        "full": m.replace(params={"quality": "full"}),
        "fast": m.replace(params={"quality": "fast"}),
    }


def late_after_s(frame_ms: float | None, workers: int, max_fps: float) -> float:
    """Seconds after its newest spike arrived that a computed frame is too late to show (while
    a newer frame of its config computes): twice what a frame takes through the pool at the
    rate the machine holds, one frame's compute plus the interval between frames, and never
    under :data:`LATE_S`.

    ``frame_ms``: measured cost of one frame of its tier (ms of wall time in a pool process,
    None before one is measured); ``workers``: pool processes; ``max_fps``: the rate asked for.
    On a busy machine frames take longer and the rate falls: a fixed second threw away most
    of the frames it had computed, though each was the newest one shown.
    """
    if not frame_ms or frame_ms <= 0:
        return LATE_S
    compute_s = frame_ms / 1e3
    interval_s = max(1.0 / max_fps, compute_s / max(1, workers))
    return max(LATE_S, 2.0 * (compute_s + interval_s))
