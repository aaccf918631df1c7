"""Benchmarks: run time against error over a parameter grid, and throughput against real time.

Figures are ratios measured in the same run (to real time = 40,000 steps/s, and to display
rate = 25 fps), never absolute timing asserts. The CLI front end is ``cfsr bench``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from cfsr.config import MethodConfig
from cfsr.display import to_display
from cfsr.layout import STEP_RATE_HZ
from cfsr.methods import methods
from cfsr.methods.registry import get_method, resolve_params
from cfsr.metrics import psnr
from cfsr.pixelstate import PixelState
from cfsr.pool import FramePool
from cfsr.simulate import simulate
from cfsr.spikes import SpikeRecording
from cfsr.streaming import StreamingReconstructor

__all__ = [
    "DISPLAY_FPS",
    "FULL_GRID",
    "QUICK_GRID",
    "grid_specs",
    "pareto_front",
    "method_fps",
    "pool_fps",
    "core_forecast",
    "method_scaling",
    "amdahl",
    "streaming_state_rtf",
    "format_rows",
    "time_call",
    "TIER_CANDIDATES",
    "TIER_BARS",
    "tier_rows",
    "carried_rows",
]

#: Display rate that "real time" means for reconstructed frames (frames per second).
DISPLAY_FPS = 25.0

# Method specs ("name" or "name:k=v,k=v") of the parameter grid; names not registered in this
# build are skipped (and reported) rather than failing the run.
FULL_GRID = (
    "tfi",
    "tfi:max_isi=100",
    *(f"tfp:window={w},mode={m}" for w in (16, 32, 64, 160) for m in ("centred", "trailing")),
    "tfa",
    "tfstp",
    "snm",
    "csr",
    "csr:preset=simulated",
    "cfsr",
    "cfsr:preset=simulated",
)
QUICK_GRID = ("tfi", "tfp:window=32,mode=centred", "tfp:window=160", "csr", "cfsr")


def grid_specs(grid: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split a grid into (runnable specs, skipped specs whose method is not registered)."""
    known = set(methods())
    run, skipped = [], []
    for spec in grid:
        (run if spec.split(":", 1)[0] in known else skipped).append(spec)
    return run, skipped


def pareto_front(
    rows: Sequence[dict[str, Any]], *, cost: str = "ms_per_frame", score: str = "psnr_all"
) -> list[dict[str, Any]]:
    """Rows not dominated by another (lower cost and higher score), sorted by cost."""
    pts = [r for r in rows if _finite(r.get(cost)) and _finite(r.get(score))]
    pts.sort(key=lambda r: (r[cost], -r[score]))
    front, best = [], -math.inf
    for r in pts:
        if r[score] > best:
            front.append(r)
            best = r[score]
    return front


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def time_call(fn: Callable[[], Any], *, min_time: float = 0.5, max_reps: int = 50) -> float:
    """Median seconds per call after one warm-up call (JIT compile excluded)."""
    fn()
    times = []
    t_end = time.perf_counter() + min_time
    while len(times) < max_reps and (len(times) < 3 or time.perf_counter() < t_end):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def method_fps(
    packed: np.ndarray,
    layout,
    method: str,
    *,
    params: dict[str, Any] | None = None,
    preset: str | None = None,
    min_time: float = 0.5,
) -> dict[str, float]:
    """Output frames per second of ``method`` through the streaming reconstructor.

    ``packed`` holds enough frames for the method's window; the newest computable step is
    reconstructed repeatedly, as the live worker does.
    """
    sr = StreamingReconstructor(method, layout, params=params, preset=preset, slack=len(packed))
    sr.push(packed, 0)
    t = sr.latest_step()
    if t is None:
        raise ValueError(f"{len(packed)} frames are too few for {method}'s window")

    def isolated():
        sr.memo.clear()  # a recurrent method's state from the previous call is not shared
        return sr.compute(t)

    sec = time_call(isolated, min_time=min_time)
    fps = 1.0 / sec
    return {"ms_per_frame": sec * 1e3, "fps": fps, "display_rtf": fps / DISPLAY_FPS}


def dense_output(
    packed: np.ndarray,
    layout,
    method: str,
    *,
    stride: int,
    count: int,
    min_time: float = 0.5,
) -> dict[str, Any]:
    """Milliseconds per frame of ``count`` outputs ``stride`` steps apart, through one
    streaming reconstructor (as ``cfsr reconstruct --times A:B:stride`` runs them), beside the
    isolated frame of :func:`method_fps`; ``speedup`` is isolated / dense.

    Outputs closer together than a method's window may share work (a recurrent method's
    state, :attr:`cfsr.methods.registry.Method.recurrent`): TFSTP's results are the same,
    CFSR's carried outputs within 0.1 dB of isolated ones (:func:`carried_rows` measures it).
    """
    sr = StreamingReconstructor(method, layout, slack=len(packed))
    sr.push(packed, 0)
    last = sr.latest_step()
    times = [] if last is None else [last - stride * i for i in range(count)][::-1]
    if not times or times[0] - sr.before < 0:
        raise ValueError(f"{len(packed)} frames are too few for {count} {method} outputs")

    def run():
        sr.memo.clear()
        for t in times:
            sr.compute(t)

    sec = time_call(run, min_time=min_time, max_reps=20) / count
    iso = method_fps(packed, layout, method, min_time=min_time)["ms_per_frame"]
    return {
        "stride": int(stride),
        "frames": int(count),
        "ms_per_frame": sec * 1e3,
        "isolated_ms_per_frame": iso,
        "speedup": iso / (sec * 1e3),
    }


def pool_fps(
    packed: np.ndarray,
    layout,
    method: str,
    *,
    workers: int,
    threads: int,
    frames: int = 16,
    params: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Isolated output frames per second of ``method`` through a
    :class:`~cfsr.pool.FramePool` of ``workers`` processes of ``threads`` threads (the live
    worker's and ``cfsr reconstruct``'s pool): ``frames`` outputs spread over ``packed``, each
    from nothing, timed from the first submission to the last result after one warm-up frame
    per process. Also the resident memory each process holds after the run (MB, Linux)."""
    cfg = MethodConfig(method, params)
    before, after = cfg.window
    n = len(packed)
    lo, hi = before, n - after - 1
    if hi < lo:
        raise ValueError(f"{n} frames are too few for {method}'s window")
    ts = np.linspace(lo, hi, frames + workers).astype(int).tolist()
    spans = [(t - before, t + after + 1, t) for t in ts]
    with FramePool(workers, threads, region_bytes=(before + after + 1) * layout.frame_bytes) as p:
        for a, b, t in spans[:workers]:  # warm-up: kernels loaded, heaps grown
            p.submit(t, cfg, layout, packed[a:b], a, [(a, b, t)])
        while p.pending:
            p.collect()
        todo = list(spans[workers:])
        t0 = time.perf_counter()
        done = 0
        while done < len(spans) - workers:
            while todo and p.idle:
                a, b, t = todo.pop(0)
                p.submit(t, cfg, layout, packed[a:b], a, [(a, b, t)])
            if p.collect() is not None:
                done += 1
        sec = time.perf_counter() - t0
        rss = [_rss_mb(pid) for pid in p.pids]
    fps = done / sec
    return {
        "workers": int(workers),
        "threads": int(threads),
        "fps": fps,
        "ms_per_frame": 1e3 / fps,
        "rss_mb_per_worker": float(np.median([r for r in rss if r])) if any(rss) else None,
    }


def _rss_mb(pid: int) -> float:
    """Resident memory of process ``pid`` in MB (0 where /proc cannot tell)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def core_forecast(ms_1thread: float, measured: dict[str, Any], cores: Sequence[int]) -> dict:
    """What machines of ``cores`` cores should expect of a pool of one single-threaded
    process per core, from this machine's measurement: ``fps = cores * 1000 /
    ms_1thread * efficiency``, the efficiency being the measured pool's fps over its
    processes' fps had each run alone (what sharing memory bandwidth and caches costs here;
    assumed to hold on the bigger machine, so a forecast, not a measurement)."""
    w = int(measured["workers"]) * int(measured["threads"])
    eff = measured["fps"] / (w * 1e3 / ms_1thread) if ms_1thread > 0 and w else float("nan")
    return {
        "efficiency": eff,
        "fps": {int(c): c * 1e3 / ms_1thread * eff for c in cores},
    }


#: CFSR settings tried for the ``fast`` quality tier (``cfsr bench --tiers``): each changes
#: what the stage profile showed to cost (MOG history, the mirrored history, distinction
#: window, still-pixel reach, PatchMatch targets and search). ``quality=fast`` is the
#: cheapest that keeps :data:`TIER_BARS` on every scene.
TIER_CANDIDATES: tuple[tuple[str, dict[str, Any]], ...] = (
    ("mog 6x64", {"mog_frames": 6, "mog_stride": 64}),
    ("mog past", {"mog_sides": "past"}),
    ("still 0", {"still_reach": 0}),
    ("still 190", {"still_reach": 190}),
    ("pm 16x3", {"pm_count": 16, "pm_step": 3}),
    ("pm 20x2", {"pm_count": 20, "pm_step": 2}),
    ("pm 12x4", {"pm_count": 12, "pm_step": 4}),
    ("pm 10x5", {"pm_count": 10, "pm_step": 5}),
    # the fast tier keeps its 2 far targets 9 steps apart beyond these (it replaces only the
    # values left at their defaults)
    ("fast, pm 13x2", {"quality": "fast", "pm_count": 13, "pm_step": 2}),
    ("fast, pm 20x2", {"quality": "fast", "pm_count": 20, "pm_step": 2}),
    ("fast", {"quality": "fast"}),
)
#: Largest PSNR loss (dB) of ``fast`` against ``full``: whole frame, motion region.
TIER_BARS = (0.5, 1.0)


def _scores(outs, gts, masks, gain: float) -> tuple[float, float]:
    """Mean PSNR (dB) over frames: whole frame and true motion region (NaN without motion)."""
    imgs = [to_display(o.rate, gain) for o in outs]
    whole = [psnr(g, i) for g, i in zip(gts, imgs, strict=True)]
    motion = [psnr(g, i, mask=m) for g, i, m in zip(gts, imgs, masks, strict=True) if m.any()]
    return float(np.mean(whole)), float(np.mean(motion)) if motion else float("nan")


def _cpu_ms(fn: Callable[[], Any], rounds: int) -> float:
    """Median CPU milliseconds of ``fn()`` over ``rounds`` calls (after one warm-up): CPU
    time, so that other jobs on a shared machine move it less than wall time."""
    fn()
    out = []
    for _ in range(rounds):
        t0 = time.process_time()
        fn()
        out.append(time.process_time() - t0)
    return float(np.median(out)) * 1e3


def tier_rows(
    scenes: Sequence[str],
    candidates: Sequence[tuple[str, dict[str, Any]]] = TIER_CANDIDATES,
    *,
    steps: int = 1400,
    times: Sequence[int] = (492, 700, 892),
    cost_scene: str = "disk",
    rounds: int = 3,
) -> list[dict[str, Any]]:
    """PSNR (whole frame, motion region) of CSR, CFSR ``full`` and each candidate setting on
    each simulated scene, the loss against ``full`` and whether :data:`TIER_BARS` hold;
    on ``cost_scene`` also CPU ms per isolated frame (median of ``rounds`` passes over
    ``times``) and the cost relative to ``full``."""
    variants = [("csr", "csr", {}), ("full", "cfsr", {})] + [
        (label, "cfsr", params) for label, params in candidates
    ]
    rows = []
    for scene in scenes:
        sim = simulate(scene, steps, seed=0)
        gain = sim.rate_scale
        gts = [to_display(sim.ideal_rate(t), gain) for t in times]
        masks = [sim.motion_mask(t) for t in times]
        rec = SpikeRecording.from_array(sim.spikes)
        per: dict[str, dict[str, Any]] = {}
        for label, name, params in variants:
            sr = StreamingReconstructor(name, rec.layout, params=params, slack=steps)
            sr.push(rec.packed(0, steps), 0)

            def isolated(sr=sr):
                outs = []
                for t in times:
                    sr.memo.clear()
                    outs.append(sr.compute(t))
                return outs

            whole, motion = _scores(isolated(), gts, masks, gain)
            row = {
                "scene": scene,
                "tier": label,
                "method": name,
                "params": params,
                "psnr_all": whole,
                "psnr_motion": motion,
            }
            if scene == cost_scene:
                row["ms_per_frame"] = _cpu_ms(isolated, rounds) / len(times)
            per[label] = row
            rows.append(row)
        full = per["full"]
        for row in per.values():
            row["d_all"] = row["psnr_all"] - full["psnr_all"]
            row["d_motion"] = row["psnr_motion"] - full["psnr_motion"]
            row["above_csr"] = row["psnr_all"] > per["csr"]["psnr_all"]
            row["within_bars"] = row["d_all"] >= -TIER_BARS[0] and not (
                row["d_motion"] < -TIER_BARS[1]
            )
            if "ms_per_frame" in row:
                row["x_full_cost"] = row["ms_per_frame"] / full["ms_per_frame"]
    return rows


def carried_rows(
    scenes: Sequence[str],
    *,
    params: dict[str, Any] | None = None,
    stride: int = 32,
    count: int = 16,
    steps: int = 1400,
    rounds: int = 2,
) -> list[dict[str, Any]]:
    """Dense CFSR output (``count`` frames ``stride`` steps apart, one group of
    :meth:`cfsr.methods.registry.Method.carry_groups`, carried frame to frame) against the same
    frames isolated (memo emptied before each): PSNR of both (whole, motion region), the
    difference, CPU ms per frame of both (median of ``rounds``) and the ratio isolated /
    carried."""
    m = get_method("cfsr")
    p = resolve_params(m, params)
    before, after = m.window(p)
    span = int(p["carry_span"]) or 1
    # the group starts a span with its whole window inside the run and ends within that span
    first = -(-before // span) * span
    steps = max(int(steps), first + stride * (count - 1) + after + 1)
    rows = []
    for scene in scenes:
        sim = simulate(scene, steps, seed=0)
        gain = sim.rate_scale
        rec = SpikeRecording.from_array(sim.spikes)
        sr = StreamingReconstructor("cfsr", rec.layout, params=params, slack=steps)
        sr.push(rec.packed(0, steps), 0)
        times = [first + stride * i for i in range(count)]
        if len(m.carry_groups(times, p)) != 1:
            raise ValueError(f"{count} outputs {stride} steps apart do not fit one group")
        gts = [to_display(sim.ideal_rate(t), gain) for t in times]
        masks = [sim.motion_mask(t) for t in times]

        def run(carry: bool, sr=sr, times=times):
            sr.memo.clear()
            outs = []
            for t in times:
                if not carry:
                    sr.memo.clear()
                outs.append(sr.compute(t))
            return outs

        iso_all, iso_mot = _scores(run(False), gts, masks, gain)
        car_all, car_mot = _scores(run(True), gts, masks, gain)
        iso_ms = _cpu_ms(lambda run=run: run(False), rounds) / count
        car_ms = _cpu_ms(lambda run=run: run(True), rounds) / count
        rows.append(
            {
                "scene": scene,
                "stride": stride,
                "frames": count,
                "psnr_all_isolated": iso_all,
                "psnr_all_carried": car_all,
                "psnr_motion_isolated": iso_mot,
                "psnr_motion_carried": car_mot,
                "d_all": car_all - iso_all,
                "d_motion": car_mot - iso_mot,
                "ms_isolated": iso_ms,
                "ms_carried": car_ms,
                "speedup": iso_ms / car_ms,
            }
        )
    return rows


def amdahl(t1: float, tn: float, n: int) -> float:
    """Parallel fraction p of a run that takes ``t1`` on one thread and ``tn`` on ``n``
    (Amdahl's law, ``tn / t1 = (1 - p) + p / n``), clipped to [0, 1]."""
    if n <= 1 or t1 <= 0:
        return float("nan")
    p = (1.0 - tn / t1) / (1.0 - 1.0 / n)
    return float(min(1.0, max(0.0, p)))


def method_scaling(
    packed: np.ndarray,
    layout,
    method: str,
    *,
    threads: Sequence[int] = (1, 2),
    min_time: float = 0.5,
) -> dict[str, Any]:
    """Milliseconds per frame of ``method`` at each thread count, and its parallel fraction.

    Threads are numba's and OpenCV's (the two pools the methods use), set for the measurement
    and restored after; counts above numba's pool size are skipped. Returns ``{"ms_per_frame":
    {threads: ms}, "parallel_fraction": p}`` with p from the lowest and highest count
    measured (:func:`amdahl`), and the speed-up it predicts at 8 and 16 threads.
    """
    import cv2
    import numba

    top = numba.config.NUMBA_NUM_THREADS
    use = sorted({int(t) for t in threads if 1 <= int(t) <= top})
    old_nb, old_cv = numba.get_num_threads(), cv2.getNumThreads()
    ms: dict[int, float] = {}
    try:
        for t in use:
            numba.set_num_threads(t)
            cv2.setNumThreads(t)
            ms[t] = method_fps(packed, layout, method, min_time=min_time)["ms_per_frame"]
    finally:
        numba.set_num_threads(old_nb)
        cv2.setNumThreads(old_cv)
    out: dict[str, Any] = {"ms_per_frame": ms}
    if len(use) >= 2 and use[0] == 1:
        p = amdahl(ms[1], ms[use[-1]], use[-1])
        out["parallel_fraction"] = p
        out["predicted_speedup"] = {n: 1.0 / ((1.0 - p) + p / n) for n in (8, 16)}
    return out


def streaming_state_rtf(
    packed: np.ndarray, layout, *, block: int = 4096, min_time: float = 1.0
) -> float:
    """Steps per second of :class:`~cfsr.pixelstate.PixelState` over packed blocks / 40,000."""
    ps = PixelState(layout)
    n = len(packed)
    blocks = [packed[a : a + block] for a in range(0, n - block + 1, block)] or [packed]

    def run() -> None:
        ps.reset()
        for i, b in enumerate(blocks):
            ps.update(b, i * block)

    sec = time_call(run, min_time=min_time, max_reps=20)
    return sum(len(b) for b in blocks) / sec / STEP_RATE_HZ


def format_rows(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]]) -> str:
    """A plain-text table; ``columns`` are (key, header, format)."""
    head = [h for _, h, _ in columns]
    body = []
    for r in rows:
        line = []
        for key, _, fmt in columns:
            v = r.get(key)
            line.append(
                "-"
                if v is None or (isinstance(v, float) and not math.isfinite(v))
                else format(v, fmt)
                if fmt
                else str(v)
            )
        body.append(line)
    widths = [
        max(len(h), *(len(b[i]) for b in body)) if body else len(h) for i, h in enumerate(head)
    ]
    out = ["  ".join(h.ljust(w) for h, w in zip(head, widths, strict=True))]
    out.append("  ".join("-" * w for w in widths))
    out += [
        "  ".join(
            c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(b, widths, strict=True))
        )
        for b in body
    ]
    return "\n".join(out)
