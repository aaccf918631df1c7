"""How good a defect map is against the truth (the simulator's own map)."""

from __future__ import annotations

import numpy as np

from cfsr.defects.defect_map import DefectMap

__all__ = ["score_map"]


def score_map(found: DefectMap, truth: DefectMap) -> dict[str, float | int | None]:
    """Precision and recall of ``found`` against ``truth``, for hot and for dead pixels.

    Returns ``hot_precision``, ``hot_recall``, ``dead_precision``, ``dead_recall`` (None where
    nothing was flagged, or nothing is true) and the counts behind them (``hot_found``,
    ``hot_true``, ``dead_found``, ``dead_true``, ``false_hot``, ``false_dead``).
    """
    out: dict[str, float | int | None] = {}
    for kind in ("hot", "dead"):
        f = np.asarray(getattr(found, kind), bool)
        t = np.asarray(getattr(truth, kind), bool)
        hit = int((f & t).sum())
        nf, nt = int(f.sum()), int(t.sum())
        out[f"{kind}_precision"] = hit / nf if nf else None
        out[f"{kind}_recall"] = hit / nt if nt else None
        out[f"{kind}_found"] = nf
        out[f"{kind}_true"] = nt
        out[f"false_{kind}"] = nf - hit
    return out
