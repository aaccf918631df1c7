"""How the live worker paces CFSR: the ``auto`` tier's choice between ``full`` and ``fast``
frames from their measured cost (ms of pool time per frame)."""

from __future__ import annotations

from typing import Any

from cfsr_live.service.config import WorkerConfig

__all__ = ["pick_tier", "tiers_of"]


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
