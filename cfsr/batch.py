"""Batch reconstruction over many recordings, split into chunks, optionally on a Dask cluster.

Each task reconstructs a group of output steps of one recording. Because every method is a pure
function of the frames around ``t`` (see :mod:`cfsr.methods.registry`), a chunk only needs the
frames ``[first_t - before, last_t + after]``: chunks overlap by the method's window and their
results equal the single-process run exactly. Dask is imported only when a cluster is asked for.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cfsr.datfile import read_spikes
from cfsr.defects import with_defects
from cfsr.display import to_display
from cfsr.offline import stream_reconstruct
from cfsr.pool import FramePool

__all__ = [
    "ChunkTask",
    "dask_client",
    "plan_chunks",
    "run_chunk",
    "run_batch",
    "write_output",
]


@dataclass(frozen=True)
class ChunkTask:
    """Reconstruct ``times`` of ``path`` with ``method`` and write them under ``out_dir``."""

    path: str
    method: str
    times: tuple[int, ...]
    out_dir: str
    params: Mapping[str, Any]
    preset: str | None = None
    masks: bool = False
    gain: float | None = None
    read_kwargs: Mapping[str, Any] | None = None
    #: reconstruction processes (:func:`cfsr.offline.stream_reconstruct`; None: decided by
    #: the first group's cost) and threads in each
    workers: int | None = 1
    threads: int = 1
    #: hot/dead pixel correction (:func:`cfsr.defects.with_defects`): "sidecar", "auto",
    #: "off" or a calibration file
    defects: str | None = "sidecar"


def plan_chunks(times: Sequence[int], chunk_steps: int) -> list[tuple[int, ...]]:
    """Split sorted output steps into groups spanning at most ``chunk_steps`` steps each."""
    if chunk_steps < 1:
        raise ValueError(f"chunk_steps must be >= 1, got {chunk_steps}")
    groups: list[list[int]] = []
    for t in sorted(set(int(t) for t in times)):
        if groups and t - groups[-1][0] < chunk_steps:
            groups[-1].append(t)
        else:
            groups.append([t])
    return [tuple(g) for g in groups]


def write_output(out_dir: Path, t: int, out: Any, gain: float | None, masks: bool) -> None:
    """``tSTEP.npy`` (float32 rates) + ``tSTEP.png`` (8-bit), and masks if asked."""
    from PIL import Image

    np.save(out_dir / f"t{t}.npy", out.rate.astype(np.float32))
    Image.fromarray(to_display(out.rate, gain)).save(out_dir / f"t{t}.png")
    if masks:
        for name, mask in out.masks.items():
            np.save(out_dir / f"t{t}_mask_{name}.npy", mask.astype(bool))
            Image.fromarray(mask.astype(np.uint8) * 255).save(out_dir / f"t{t}_mask_{name}.png")


def run_chunk(
    task: ChunkTask, on_frame: Callable[[], None] | None = None, pool: Any = None
) -> dict[str, Any]:
    """Run one chunk (in this process or on a cluster worker), on ``pool`` (a running
    :class:`~cfsr.pool.FramePool`) if given; returns counts and timing."""
    t0 = time.perf_counter()
    rec = with_defects(read_spikes(task.path, **dict(task.read_kwargs or {})), task.defects)
    out_dir = Path(task.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    gain = task.gain if task.gain is not None else rec.gain
    n = 0
    for t, out in stream_reconstruct(
        rec,
        task.method,
        task.times,
        params=task.params,
        preset=task.preset,
        workers=task.workers,
        threads=task.threads,
        pool=pool,
    ):
        write_output(out_dir, t, out, gain, task.masks)
        n += 1
        if on_frame is not None:
            on_frame()
    return {
        "path": task.path,
        "frames": n,
        "seconds": time.perf_counter() - t0,
        "worker_pid": os.getpid(),
    }


def dask_client(cluster: str):
    """``(client, local_cluster_or_None)`` for ``"local"`` or a scheduler address."""
    from dask.distributed import Client, LocalCluster

    if cluster in ("", "local"):
        workers = max(1, min(4, os.cpu_count() or 1))
        lc = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        )
        return Client(lc), lc
    return Client(cluster), None


def run_batch(
    tasks: Sequence[ChunkTask],
    *,
    cluster: str | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[dict[str, Any]]:
    """Run chunk tasks in this process (``cluster=None``), on a local Dask cluster
    (``"local"``) or on the Dask scheduler at ``cluster`` (e.g. ``tcp://10.0.0.5:8786``).

    ``progress(n)`` is called with the number of frames just finished.
    """
    results: list[dict[str, Any]] = []
    if cluster is None:
        tick = (lambda: progress(1)) if progress else None
        fixed = {(t.workers, t.threads) for t in tasks if t.workers not in (None, 1)}
        if not fixed:
            return [run_chunk(task, tick) for task in tasks]

        (workers, threads), *_ = sorted(fixed)
        with FramePool(workers, threads) as pool:  # one pool for every chunk
            return [run_chunk(task, tick, pool) for task in tasks]
    from dataclasses import replace

    from dask.distributed import as_completed

    client, local = dask_client(cluster)
    try:
        # a Dask worker process is the unit of parallelism there: no pool inside it
        futures = [
            client.submit(run_chunk, replace(task, workers=1), pure=False) for task in tasks
        ]
        for fut in as_completed(futures):
            r = fut.result()
            results.append(r)
            if progress:
                progress(r["frames"])
    finally:
        client.close()
        if local is not None:
            local.close()
    return results
