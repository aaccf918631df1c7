"""The library's front door: ``reconstruct`` and ``reconstruct_many``."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from cfsr.methods.registry import Output, get_method, resolve_params
from cfsr.spikes import SpikeRecording, as_recording

__all__ = ["reconstruct", "reconstruct_outputs", "check_times"]


def check_times(times: Iterable[int] | int, n_frames: int) -> list[int]:
    """Validate output steps against a recording of ``n_frames`` steps."""
    ts = [int(times)] if np.isscalar(times) else [int(t) for t in times]  # type: ignore[arg-type]
    if not ts:
        raise ValueError("no output times given")
    bad = [t for t in ts if not 0 <= t < n_frames]
    if bad:
        raise ValueError(f"times {bad} outside the recording (0..{n_frames - 1} steps)")
    return ts


def reconstruct_outputs(
    spikes: SpikeRecording | np.ndarray,
    method: str,
    times: Sequence[int] | int,
    *,
    preset: str | None = None,
    params: Mapping[str, Any] | None = None,
) -> list[Output]:
    """Like :func:`reconstruct` but returns :class:`Output` objects (rate plus masks)."""
    rec = as_recording(spikes)
    m = get_method(method)
    p = resolve_params(m, params, preset)
    before, after = m.window(p)
    outs = []
    memo: dict[str, Any] = {}  # recurrent methods continue a state from output to output
    for t in check_times(times, rec.n_frames):
        a = max(0, t - before)
        b = min(rec.n_frames, t + after + 1)
        outs.append(m.run_window(rec, a, b, t, p, memo))
    return outs


def reconstruct(
    spikes: SpikeRecording | np.ndarray,
    method: str,
    times: Sequence[int] | int,
    *,
    preset: str | None = None,
    return_masks: bool = False,
    **params: Any,
):
    """Reconstruct images at the given steps.

    Parameters
    ----------
    spikes : SpikeRecording or ndarray (T, H, W) of 0/1
        What :func:`cfsr.read_dat` returns, or upright decoded spikes.
    method : str
        A name from :func:`cfsr.methods` (``tfi``, ``tfp``, ...).
    times : int or sequence of int
        Output steps (0-based frame indices into the recording).
    preset : str, optional
        Named parameter set (e.g. ``"paper"``) applied before ``params``.
    return_masks : bool
        Also return a dict of stacked boolean masks ``(len(times), H, W)`` per mask name.
    **params
        Method parameters (see ``cfsr.methods()[method]["params"]``).

    Returns
    -------
    rates : ndarray float32 (len(times), H, W)
        Firing rate in spikes per step (0..1), upright.
    masks : dict of str to ndarray bool, only if ``return_masks``

    Examples
    --------
    >>> import numpy as np, cfsr
    >>> spikes = (np.arange(100)[:, None, None] % 4 == 0).repeat(2, 1).repeat(4, 2)
    >>> cfsr.reconstruct(spikes.astype(np.uint8), "tfp", [50], window=40)[0, 0, 0]
    0.25
    """
    outs = reconstruct_outputs(spikes, method, times, preset=preset, params=params)
    rates = np.stack([o.rate for o in outs]).astype(np.float32, copy=False)
    if not return_masks:
        return rates
    names = sorted({k for o in outs for k in o.masks})
    masks = {k: np.stack([o.masks[k] for o in outs]) for k in names}
    return rates, masks
