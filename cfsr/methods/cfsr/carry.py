"""Carried work (what this project adds beyond the paper): outputs close together continue
from the previous one instead of starting from nothing.

Within one span of ``carry_span`` steps, an output at most ``carry_gap`` steps after the previous
one reuses its CSR history frames (within half a stride of its own,
:func:`cfsr.methods.cfsr.history.history_scan`) and the PatchMatch frames of the group at the
same steps (:func:`cfsr.methods.cfsr.patchmatch_frames.pm_frames`' bank). The groups depend only
on the output steps and these two parameters (:func:`carry_groups`), so results do not depend on
how groups are shared between processes; a carried output moves by under 0.1 dB
(docs/methods.md, "Carried work").
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, NamedTuple

import numpy as np

from cfsr.methods.cfsr.settings import CfsrSettings
from cfsr.methods.registry import Memo

__all__ = ["Carry", "carry_groups", "carry_in", "carry_out", "continues"]


def carry_groups(times: Iterable[int], s: CfsrSettings) -> list[list[int]]:
    """Split output steps into the groups within which outputs carry work forward.

    The steps are sorted and deduplicated; a group ends where the next step lies in another
    span of ``carry_span`` steps (spans start at multiples of it, from step 0) or more than
    ``carry_gap`` steps after the previous one (``carry_span = 0``: every step alone). The
    groups depend only on the steps and these two parameters: the first output of a group is
    computed from nothing (as an isolated output) and the others continue from the one before
    them, so a group run in order with one memo gives the same frames in any process, and
    the frames do not depend on how the groups are shared between processes.
    """
    ts = sorted({int(t) for t in times})
    groups: list[list[int]] = []
    for t in ts:
        if groups and continues(groups[-1][-1], t, s):
            groups[-1].append(t)
        else:
            groups.append([t])
    return groups


def continues(prev: int, t: int, s: CfsrSettings) -> bool:
    """Whether output step ``t`` continues from ``prev`` (:func:`carry_groups`' rule)."""
    span = s.carry_span
    return span > 0 and prev // span == t // span and 0 < t - prev <= s.carry_gap


class Carry(NamedTuple):
    """What an output leaves in the memo for the next one (:func:`fine_stage`)."""

    t: int  #: absolute step of the output
    key: CfsrSettings  #: its settings but the carry rule's: another set carries nothing
    frames: dict[int, np.ndarray]  #: absolute last step -> CSR history frame (H, W) float32
    #: the PatchMatch frames of the group's last output that ran PatchMatch, by absolute
    #: step (:func:`cfsr.methods.cfsr.patchmatch_frames.pm_frames`)
    bank: dict[str, Any]


def carry_in(
    memo: Memo | None, t: int, center: int, s: CfsrSettings
) -> tuple[dict[int, np.ndarray] | None, dict[str, Any] | None]:
    """The previous output's history frames (window indices -> frame; None: none) when output
    step ``t`` continues from it (:func:`continues`), and the group's PatchMatch frames (an
    empty bank for the first output of a group; None without a memo or with
    ``carry_span = 0``)."""
    if memo is None or s.carry_span <= 0:
        return None, None
    old = memo.get("cfsr")
    if not isinstance(old, Carry) or not continues(old.t, t, s) or old.key != s.carry_key:
        return None, {}
    shift = t - center  # absolute step of window index 0
    return {a - shift: f for a, f in old.frames.items()}, old.bank


def carry_out(
    memo: Memo | None,
    t: int,
    center: int,
    s: CfsrSettings,
    frames: Mapping[int, np.ndarray] | None,
    bank: dict[str, Any] | None = None,
) -> None:
    """Leave this output's history frames (window index -> frame; None: none) and the
    group's PatchMatch frames (``bank``, which :func:`patchmatch_refine` fills in place) in
    ``memo``."""
    if memo is None or s.carry_span <= 0:
        return
    shift = t - center
    kept = {} if frames is None else {e + shift: f for e, f in frames.items()}
    memo["cfsr"] = Carry(t, s.carry_key, kept, {} if bank is None else bank)
