"""The library's front door: ``reconstruct`` and ``reconstruct_outputs``."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from cfsr.config import MethodConfig
from cfsr.methods.registry import Memo, Output, get_method, resolve_params
from cfsr.spikes import SpikeRecording, as_recording

__all__ = ["reconstruct", "reconstruct_outputs", "check_times"]


def check_times(
    times: Iterable[int] | int, n_frames: int, what: str = "the recording"
) -> list[int]:
    """Validate output steps against ``what`` (a recording, a simulated run) of ``n_frames``
    steps: at least one, each in ``0..n_frames - 1``."""
    ts = [int(times)] if np.isscalar(times) else [int(t) for t in times]  # type: ignore[arg-type]
    if not ts:
        raise ValueError("no output times given")
    bad = [t for t in ts if not 0 <= t < n_frames]
    if bad:
        raise ValueError(f"times {bad} outside {what} (0..{n_frames - 1} steps)")
    return ts


def reconstruct_outputs(
    spikes: SpikeRecording | np.ndarray,
    method: str,
    times: Sequence[int] | int,
    *,
    preset: str | None = None,
    params: Mapping[str, Any] | None = None,
    workers: int | None = 1,
    threads: int = 1,
) -> list[Output]:
    """Like :func:`reconstruct` but returns :class:`Output` objects (rate plus masks).

    ``workers``/``threads``: as in :func:`reconstruct` (default here: 1, this process).

    The outputs are computed in increasing step, group by group
    (:func:`cfsr.offline.carry_groups`): within a group a method may continue work from the
    previous output (``memo``), so the numbers depend on the set of steps asked for, never
    on their order, the number of processes or how the groups are spread over them.
    """
    # deferred: keeps the process pool (multiprocessing) out of `import cfsr` and the web process
    from cfsr.offline import carry_groups, stream_reconstruct

    rec = as_recording(spikes)
    m = get_method(method)
    p = resolve_params(m, params, preset)
    ts = check_times(times, rec.n_frames)
    if workers != 1:
        got = dict(
            stream_reconstruct(rec, m.name, ts, params=p, workers=workers, threads=threads)
        )
        return [got[t] for t in ts]
    settings = m.settings_of(p)  # the method's typed, frozen settings, built once
    before, after = m.window(settings)
    got = {}
    for group in carry_groups(MethodConfig(m.name, p), ts):
        memo: Memo = {}  # a group's outputs may continue work from one to the next
        for t in group:
            a = max(0, t - before)
            b = min(rec.n_frames, t + after + 1)
            got[t] = m.run_window(rec, a, b, t, settings, memo)
    fix = getattr(rec, "flatten", None)  # a flat-field gain (cfsr.defects.corrected)
    return [got[t] if fix is None else fix(got[t], m) for t in ts]


def reconstruct(
    spikes: SpikeRecording | np.ndarray,
    method: str,
    times: Sequence[int] | int,
    *,
    preset: str | None = None,
    return_masks: bool = False,
    workers: int | None = None,
    threads: int = 1,
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
    workers : int or None
        Reconstruction processes (:class:`cfsr.pool.FramePool`), each on its own outputs.
        None (default): this process, unless there are many outputs and the first ones cost
        enough to pay for starting one process per core
        (:func:`cfsr.offline.stream_reconstruct`). The numbers are the same in every case.
    threads : int
        numba/OpenCV threads in each of those processes.
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
    outs = reconstruct_outputs(
        spikes, method, times, preset=preset, params=params, workers=workers, threads=threads
    )
    rates = np.stack([o.rate for o in outs]).astype(np.float32, copy=False)
    if not return_masks:
        return rates
    names = sorted({k for o in outs for k in o.masks})
    masks = {k: np.stack([o.masks[k] for o in outs]) for k in names}
    return rates, masks
