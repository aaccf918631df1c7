"""Offline reconstruction of a recording through the streaming reconstructor, or the pool.

The CLI and batch tools use this, so offline results come from exactly the code the live
worker runs: blocks of packed frames are pushed into a :class:`StreamingReconstructor`, or,
when the work is worth several processes, the same windows go to a
:class:`~cfsr.pool.FramePool` (the live worker's pool), one carry group per task. Both give
the same numbers (a group's outputs depend only on its frames and its parameters). Only the
blocks that the requested times need are read, so sparse times in a long file cost little.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any

from cfsr.config import MethodConfig
from cfsr.defects import in_buffer
from cfsr.methods.registry import Output
from cfsr.pool import FramePool, PoolResult, borrowed_pool, default_workers, shared_pool_running
from cfsr.spikes import SpikeRecording
from cfsr.streaming import StreamingReconstructor
from cfsr.warmup import measured_compile

__all__ = ["carry_groups", "pool_outputs", "stream_reconstruct", "POOL_MIN_MS", "POOL_START_S"]

#: ``workers=None`` starts the pool only when the first group took at least this long per
#: output (ms): below it, copying windows to the processes costs about what they save
POOL_MIN_MS = 20.0
#: what starting the pool costs before its first frame (s): spawning its processes, their
#: imports and their kernels' loading from the cache, as ``cfsr bench --compile`` measured it
#: (the package's compile table; 3 s where the table lacks it); paid once per process (the
#: pool is reused), so ``workers=None`` starts it only for work of at least twice this long
POOL_START_S = float(measured_compile().get("pool_start_s", 3.0))


def _spans(
    times: Sequence[int], before: int, after: int, n: int
) -> list[tuple[int, int, list[int]]]:
    """Group sorted times into contiguous frame spans ``[a, b)`` that cover their windows."""
    spans: list[tuple[int, int, list[int]]] = []
    for t in times:
        a, b = max(0, t - before), min(n, t + after + 1)
        if spans and a <= spans[-1][1]:
            pa, pb, ts = spans[-1]
            spans[-1] = (pa, max(pb, b), ts + [t])
        else:
            spans.append((a, b, [t]))
    return spans


def carry_groups(config: MethodConfig, times: Sequence[int]) -> list[list[int]]:
    """Sorted, distinct ``times`` cut into the groups whose outputs may carry work from one to
    the next (the method's ``carry_groups``; every output alone for a method without one).
    A group's first output starts from nothing, so groups can run in any process."""
    fn = getattr(config.spec, "carry_groups", None)
    ts = sorted({int(t) for t in times})
    if fn is None:
        return [[t] for t in ts]
    return [list(g) for g in fn(ts, config.params)]


def _streamed(
    rec: SpikeRecording, sr: StreamingReconstructor, times: Sequence[int], block: int
) -> Iterator[tuple[int, Output]]:
    # a corrected recording is corrected in the buffer, not read through a corrected copy
    rec, sr.defects = in_buffer(rec)
    for a, b, group in _spans(times, sr.before, sr.after, rec.n_frames):
        sr.reset(a)
        blocks = ((s, rec.packed(s, min(b, s + block))) for s in range(a, b, block))
        # The span ends where the recording ends only if b == n; otherwise every window in the
        # group is complete inside [a, b), so "final" never clips a window early.
        yield from sr.run(blocks, group)


def _flat(rec: SpikeRecording, cfg: MethodConfig, outs: Iterable[tuple[int, Output]]
          ) -> Iterator[tuple[int, Output]]:
    """``outs`` of ``cfg`` with a flat-field gain divided out when ``rec`` carries one (a
    recording read through :func:`cfsr.defects.corrected` with a calibration:
    ``rec.flatten``)."""
    fix = getattr(rec, "flatten", None)
    for t, out in outs:
        yield t, (out if fix is None else fix(out, cfg.spec))


def stream_reconstruct(
    rec: SpikeRecording,
    method: str,
    times: Sequence[int],
    *,
    params: Mapping[str, Any] | None = None,
    preset: str | None = None,
    block: int = 1024,
    workers: int | None = 1,
    threads: int = 1,
    pool: Any = None,
) -> Iterator[tuple[int, Output]]:
    """Yield ``(t, Output)`` for each requested step, in increasing ``t``.

    Parameters
    ----------
    workers : int or None
        1: in this process, blocks of ``block`` packed frames read from ``rec`` (memory-mapped)
        and pushed through one :class:`StreamingReconstructor`, spans between distant times
        skipped. N > 1: on a :class:`~cfsr.pool.FramePool` of N processes of ``threads``
        threads, one carry group (:func:`carry_groups`) per task. None: the first group here,
        timed; the pool (one process per usable core; this process's shared pool, started
        once and reused by later calls) for the rest when there are at least two groups per
        process left, the first took :data:`POOL_MIN_MS` or more per output, and the rest
        would take here at least twice what starting the pool costs (:data:`POOL_START_S`;
        nothing when the shared pool already runs). The outputs are the same in every case.
    pool : FramePool, optional
        A running pool to use (then ``workers`` and ``threads`` are ignored).
    """
    ts = sorted({int(t) for t in times})
    bad = [t for t in ts if not 0 <= t < rec.n_frames]
    if bad:
        raise ValueError(f"times {bad} outside the recording (0..{rec.n_frames - 1} steps)")
    cfg = MethodConfig(method, params, preset)
    if pool is not None:
        groups = carry_groups(cfg, ts)
        yield from _flat(rec, cfg, pool_outputs(rec, cfg, groups, pool=pool, carry=True))
        return
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1:
        sr = StreamingReconstructor(cfg, rec.layout, slack=block)
        yield from _flat(rec, cfg, _streamed(rec, sr, ts, block))
        return
    groups = carry_groups(cfg, ts)
    if workers is None:
        n = default_workers(threads)
        if n < 2 or len(groups) < 3 * n:
            workers = 1
        else:
            sr = StreamingReconstructor(cfg, rec.layout, slack=block)
            t0 = time.perf_counter()
            yield from _flat(rec, cfg, _streamed(rec, sr, groups[0], block))
            per_output = (time.perf_counter() - t0) * 1e3 / len(groups[0])
            groups = groups[1:]
            left_s = per_output * sum(map(len, groups)) / 1e3  # what the rest costs here
            start_s = 0.0 if shared_pool_running(threads) else POOL_START_S
            workers = n if per_output >= POOL_MIN_MS and left_s >= 2 * start_s else 1
        if workers == 1:
            sr = StreamingReconstructor(cfg, rec.layout, slack=block)
            yield from _flat(rec, cfg, _streamed(rec, sr, [t for g in groups for t in g], block))
            return
    yield from _flat(rec, cfg, pool_outputs(rec, cfg, groups, workers=workers, threads=threads,
                                       carry=True))


def pool_outputs(
    recording: Any,
    config: MethodConfig,
    groups: Iterable[Sequence[int]],
    *,
    workers: int | None = None,
    threads: int = 1,
    carry: bool = False,
    pool: FramePool | None = None,
) -> Iterator[tuple[int, Output]]:
    """Yield ``(t, Output)`` for every step of ``groups``, in the order given, computed on a
    :class:`FramePool` (one group per task).

    ``recording`` is anything with ``packed(a, b)``, ``n_frames`` and ``layout`` (a
    :class:`~cfsr.spikes.SpikeRecording`). Each output's window is ``[t - before, t + after]``
    clipped to the recording, as in :func:`cfsr.reconstruct`, so the numbers are the same as
    one process's. With ``carry`` the outputs of a group continue one memo (carried work);
    a group's first output always starts from nothing, so the result does not depend on the
    number of processes.
    """
    before, after = config.window
    n = int(recording.n_frames)
    layout = recording.layout
    tasks = []
    for g in groups:
        spans = [(max(0, t - before), min(n, t + after + 1), int(t)) for t in g]
        if spans:
            a0, b0 = min(s[0] for s in spans), max(s[1] for s in spans)
            tasks.append((a0, b0, spans))
    need = max((b - a for a, b, _ in tasks), default=0) * layout.frame_bytes
    if pool is not None:
        yield from _run_tasks(pool, recording, config, tasks, need, carry)
        return
    with borrowed_pool(workers, threads, len(tasks), need) as borrowed:
        yield from _run_tasks(borrowed, recording, config, tasks, need, carry)


def _run_tasks(
    pool: FramePool,
    recording: Any,
    config: MethodConfig,
    tasks: list[tuple[int, int, list[tuple[int, int, int]]]],
    need: int,
    carry: bool,
) -> Iterator[tuple[int, Output]]:
    """Submit the tasks as processes come free; yield their outputs in the tasks' order."""
    if need > pool.region_bytes:
        pool.grow(need)
    done: dict[int, PoolResult] = {}
    nxt = 0  # next group to yield
    sub = 0  # next group to submit
    while nxt < len(tasks):
        while sub < len(tasks) and pool.idle:
            a0, b0, spans = tasks[sub]
            pool.submit(sub, config, recording.layout, recording.packed(a0, b0), a0, spans,
                        carry=carry)
            sub += 1
        while nxt not in done:
            r = pool.collect()
            assert r is not None
            done[r.tag] = r
        yield from done.pop(nxt).outputs
        nxt += 1
