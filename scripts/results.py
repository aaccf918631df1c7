"""docs/results.md and its plots, generated from the JSON files `cfsr bench` writes (never typed
by hand: rerun the benchmark, then this script).

    ./tasks bench --out docs/bench                  # accuracy.json (and pareto.png)
    ./tasks bench --throughput --out docs/bench     # throughput.json
    ./tasks bench --sweep --out docs/bench          # sweep.json
    ./tasks bench --tiers --out docs/bench          # tiers.json
    ./tasks bench --compile --out docs/bench        # compile.json
    ./tasks bench --defects --out docs/bench        # defects.json
    python scripts/results.py                       # docs/results.md, docs/bench/*.png,
                                                    # cfsr/_compile_table.json
    python scripts/results.py --check               # exit 1 if docs/results.md is stale

A JSON file that is absent leaves its section out; keys a file lacks leave their rows out.
The plots need matplotlib (`cfsr[bench]`); without it the page is still written.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "docs" / "bench"
PAGE = ROOT / "docs" / "results.md"
#: the measured compile table the progress bars estimate from (package data)
TABLE = ROOT / "cfsr" / "_compile_table.json"
#: the order of the tables: the paper's methods, then the baselines, then anything else
ORDER = ("tfi", "tfp", "tfa", "tfstp", "snm", "csr", "cfsr")


def _ok(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _f(v: Any, fmt: str) -> str:
    return format(v, fmt) if _ok(v) else "-"


def _rank(name: str) -> tuple[int, str]:
    return (ORDER.index(name) if name in ORDER else len(ORDER), name)


def _order(names: Sequence[str]) -> list[str]:
    return sorted(set(names), key=_rank)


def _distinct(rows: Sequence[dict[str, Any]], key: str) -> list[Any]:
    """The values of ``key`` in ``rows``, each once, in the order they first appear."""
    return list(dict.fromkeys(r[key] for r in rows))


def _table_head(title: str, intro: str, cols: Sequence[str]) -> list[str]:
    """A section's title, its introduction and the head of its table."""
    return [f"## {title}", "", intro, "", "| " + " | ".join(cols) + " |",
            "|" + "---|" * len(cols)]


def _load(name: str, folder: Path) -> dict[str, Any] | None:
    p = folder / name
    return json.loads(p.read_text()) if p.exists() else None


def _machine(res: dict[str, Any]) -> str:
    m = res.get("machine") or {}
    parts = [f"{m['cores']} cores" if m.get("cores") else "", m.get("cpu", ""),
             f"Python {m['python']}" if m.get("python") else ""]
    return ", ".join(p for p in parts if p)


def _best_per_method(rows: list[dict[str, Any]], scene: str) -> dict[str, dict[str, Any]]:
    """Per method name, its variant with the highest whole-frame PSNR on ``scene``."""
    best: dict[str, dict[str, Any]] = {}
    for r in rows:
        if r["scene"] != scene or not _ok(r.get("psnr_all")):
            continue
        if r["name"] not in best or r["psnr_all"] > best[r["name"]]["psnr_all"]:
            best[r["name"]] = r
    return best


def accuracy_section(acc: dict[str, Any]) -> list[str]:
    rows = acc["rows"]
    sim = sorted({r["scene"] for r in rows if not r["scene"].startswith("reds:")})
    reds = "reds:mean" if any(r["scene"] == "reds:mean" for r in rows) else None
    names = _order([r["name"] for r in rows])
    best = {s: _best_per_method(rows, s) for s in [*sim, *([reds] if reds else [])]}
    out = [
        "## Accuracy",
        "",
        f"`cfsr bench`: simulator scenes at 400 x 250, {acc.get('steps', '?')} steps, outputs at "
        f"steps {', '.join(str(t) for t in acc.get('times', []))}; PSNR in dB of the 8-bit display "
        "(rate / rate_scale * 255) against the exact ground truth, whole frame / inside the true "
        "motion mask. A method tried with several settings shows its best one (the setting in "
        "brackets). The best value of each column is in bold."
        + (" REDS: the mean over the REDS samples (ground truth frame 150, display rate / 0.6 "
           "* 255)." if reds else ""),
        "",
    ]
    cols = [*sim, *([reds] if reds else [])]
    head = ["method", *[("REDS" if c == reds else c) for c in cols], "ms/frame"]
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    top = {c: max((r["psnr_all"] for r in best[c].values()), default=None) for c in cols}
    for n in names:
        cells = [n]
        for c in cols:
            r = best[c].get(n)
            if r is None:
                cells.append("-")
                continue
            v = _f(r["psnr_all"], ".2f")
            if c != reds:
                v += " / " + _f(r.get("psnr_motion"), ".2f")
            if top[c] is not None and r["psnr_all"] == top[c]:
                v = f"**{v}**"
            label = r["method"].partition(":")[2]
            if label and len({x["method"] for x in rows if x["name"] == n}) > 1:
                v += f" ({label})"
            cells.append(v)
        ms = [r["ms_per_frame"] for r in rows if r["name"] == n and _ok(r.get("ms_per_frame"))
              and not r["scene"].startswith("reds:")]
        cells.append(_f(sorted(ms)[len(ms) // 2], ".1f") if ms else "-")
        out.append("| " + " | ".join(cells) + " |")
    out += ["", "ms/frame: the median over the simulator rows of each method (all settings).", ""]
    iou_keys = sorted({k for r in rows for k in r if k.startswith("iou_")})
    if iou_keys:
        out += ["Mask IoU with the true motion mask, per mask a method makes:", "",
                "| method | mask | " + " | ".join(sim) + " |", "|" + "---|" * (len(sim) + 2)]
        for n in names:
            for k in iou_keys:
                cells = [_f(best[s][n].get(k), ".2f") if n in best[s] else "-" for s in sim]
                if any(c != "-" for c in cells):
                    out.append(f"| {n} | {k[4:]} | " + " | ".join(cells) + " |")
        out.append("")
    if acc.get("noref"):
        out += [
            "Real capture without ground truth (`uhsr`): STD and CPBD of the 8-bit frame. CPBD "
            "rewards noise: read it beside STD and the PSNR table, never alone.",
            "",
            "| method | STD | CPBD | ms/frame |",
            "|---|---|---|---|",
        ]
        for r in acc["noref"]:
            out.append(f"| {r['method']} | {_f(r.get('std'), '.1f')} | {_f(r.get('cpbd'), '.3f')}"
                       f" | {_f(r.get('ms_per_frame'), '.1f')} |")
        out.append("")
    out += ["![PSNR per scene](bench/psnr.png)", "",
            "![run time against error](bench/pareto.png)", ""]
    return out


def throughput_section(tp: dict[str, Any]) -> list[str]:
    goals = tp.get("goals", {})
    out = ["## Throughput", "", "`cfsr bench --throughput` on the demo scene (400 x 250); ratios "
           "are to the sensor's real time (40,000 frames/s).", "",
           "| measure | result | goal |", "|---|---|---|"]
    rtf = tp.get("realtime_factor", {})
    acq = tp.get("acquisition") or {}
    if _ok(rtf.get("acquisition")):
        lost = acq.get("lost_frames")
        span = ""
        if _ok(acq.get("realtime_factor_min")) and _ok(acq.get("realtime_factor_max")):
            span = f" (runs {acq['realtime_factor_min']:.2f}-{acq['realtime_factor_max']:.2f}x)"
        src = (acq.get("end_to_end") or {}).get("source") or acq.get("source", "")
        out.append(f"| acquisition -> ring: {src} | {rtf['acquisition']:.2f}x real "
                   f"time{span}, {lost if lost is not None else '?'} frames lost | "
                   f"{goals.get('acquisition', '')} |")
    drv = acq.get("driver") or {}
    if _ok(drv.get("realtime_factor")):
        out.append(f"| acquisition, the driver alone | {drv['realtime_factor']:.1f}x real time | |")
    if _ok(rtf.get("streaming_state")):
        out.append(f"| streaming per-pixel state on packed bytes | {rtf['streaming_state']:.2f}x "
                   f"real time | {goals.get('streaming_state', '')} |")
    for name, m in sorted((tp.get("methods") or {}).items(), key=lambda kv: _rank(kv[0])):
        if _ok(m.get("fps")):
            out.append(f"| {name} display frames | {m['fps']:.1f} fps "
                       f"({_f(m.get('ms_per_frame'), '.1f')} ms) | {goals.get(name, '')} |")
    out.append("")
    pool = tp.get("pool") or {}
    if pool.get("splits"):
        out += [f"{pool.get('method', 'cfsr').upper()} on a pool of processes, each on its own "
                "output step (processes x threads per process):", "",
                "| processes x threads | fps | ms per frame | resident MB per process |",
                "|---|---|---|---|"]
        for r in pool["splits"]:
            out.append(f"| {r.get('workers')} x {r.get('threads')} | {_f(r.get('fps'), '.1f')} | "
                       f"{_f(r.get('ms_per_frame'), '.1f')} | "
                       f"{_f(r.get('rss_mb_per_worker'), '.0f')} |")
        fc = (pool.get("forecast") or {}).get("fps") or {}
        if fc:
            out += ["", "Forecast for bigger machines from the widest single-thread split "
                    "(not a measurement): " + ", ".join(
                        f"{c} cores {_f(v, '.0f')} fps" for c, v in sorted(
                            fc.items(), key=lambda kv: int(kv[0]))) + "."]
        out.append("")
    live = tp.get("live") or {}
    runs = [r for r in live.get("runs", []) if "error" not in r]
    busy = any("busy" in r for r in runs)  # the live part's runs beside CPU-bound processes
    if runs:
        out += [f"The live service on the demo, replayed at real time (frames published per "
                f"second over {_f(live.get('seconds'), '.0f')} s, max_fps "
                f"{_f(live.get('max_fps'), '.0f')}; CFSR's tier auto picks full or fast per "
                "frame):", "",
                "| method | tier | processes x threads | fps | full / fast frames | compute ms | "
                "latency ms | dropped late / out of order |" + _LIVE_BUSY_HEAD[0] * busy,
                "|---|---|---|---|---|---|---|---|" + _LIVE_BUSY_HEAD[1] * busy]
        for r in runs:
            out.append(f"| {r['method']} | {r.get('quality') or ''} | {r['workers']} x "
                       f"{r['threads']} | {_f(r.get('fps'), '.1f')} | {r.get('full_frames')} / "
                       f"{r.get('fast_frames')} | {_f(r.get('compute_ms'), '.0f')} | "
                       f"{_f(r.get('latency_ms'), '.0f')} | {r.get('dropped_late')} / "
                       f"{r.get('dropped_order')} |" + (_live_busy_cells(r) if busy else ""))
        out.append("")
    dense = tp.get("dense") or {}
    if dense:
        out += ["Dense output (one stream, outputs `stride` steps apart, work carried from one "
                "to the next) against the same method's isolated frame:", "",
                "| method | stride (steps) | ms per frame | isolated ms | cheaper |",
                "|---|---|---|---|---|"]
        for name, d in dense.items():
            out.append(f"| {name} | {d.get('stride')} | {_f(d.get('ms_per_frame'), '.1f')} | "
                       f"{_f(d.get('isolated_ms_per_frame'), '.1f')} | "
                       f"{_f(d.get('speedup'), '.2f')}x |")
        out.append("")
    sc = tp.get("scaling") or {}
    if sc:
        out += ["Threads (numba and OpenCV pools at 1 and 2 threads; the parallel fraction p by "
                "Amdahl's law and what it predicts, not a measurement on more cores):", "",
                "| method | ms at 1 thread | ms at 2 | p | predicted x at 8 | at 16 |",
                "|---|---|---|---|---|---|"]
        for name in _order(list(sc)):
            s = sc[name]
            ms = s.get("ms_per_frame", {})
            pr = s.get("predicted_speedup", {})
            out.append(f"| {name} | {_f(ms.get('1'), '.2f')} | {_f(ms.get('2'), '.2f')} | "
                       f"{_f(s.get('parallel_fraction'), '.2f')} | {_f(pr.get('8'), '.1f')} | "
                       f"{_f(pr.get('16'), '.1f')} |")
        out.append("")
    return out


def sweep_section(sw: dict[str, Any]) -> list[str]:
    rows = sw.get("rows", [])
    scen = _distinct(rows, "scenario")
    out = _table_head(
        "Cost follows the scene",
        "`cfsr bench --sweep`: CFSR with `adaptive` on (skip what the scene does not need) "
        "and off, as the moving part of the scene grows; TFP for scale.",
        ("scene", "moving", "TFP ms", "CFSR adaptive ms", "always-full ms", "speed-up",
         "PSNR adaptive - full (dB)"))
    for s in scen:
        sub = [r for r in rows if r["scenario"] == s]
        tfp = next((r for r in sub if r["method"] == "tfp"), None)
        ad = next((r for r in sub if r["method"] == "cfsr" and r.get("adaptive")
                   and r.get("static_gate") is not False), None)
        full = next((r for r in sub if r["method"] == "cfsr" and r.get("adaptive") is False),
                    None)
        sp = (full["ms_per_frame"] / ad["ms_per_frame"]) if ad and full else None
        dp = (ad["psnr_all"] - full["psnr_all"]) if ad and full else None
        frac = sub[0].get("motion_fraction")
        ms = [_f(r and r["ms_per_frame"], ".1f") for r in (tfp, ad, full)]
        out.append(f"| {s} | {_f(100 * frac if _ok(frac) else None, '.0f')} % | "
                   + " | ".join(ms) + f" | {_f(sp, '.1f')}x | {_f(dp, '+.3f')} |")
    out.append("")
    return out


def tiers_section(ti: dict[str, Any]) -> list[str]:
    rows = [r for r in ti.get("tiers", []) if _ok(r.get("psnr_all"))]
    labels = _distinct(rows, "tier")
    out = _table_head(
        "Quality tiers",
        "`cfsr bench --tiers`: CFSR's `full` tier, its `fast` tier and the other settings "
        "tried for it, against CSR, on every simulated scene (1,400 steps, outputs at "
        "492, 700 and 892); CPU ms per isolated frame on one numba thread, on the scene "
        "named. A setting keeps the bars when it loses at most 0.5 dB (whole frame) and "
        "1.0 dB (motion region) against `full` on every scene.",
        ("setting", "CPU ms (x full)", "worst loss against full, whole / motion (scene)",
         "bars"))
    for lab in labels:
        sub = [r for r in rows if r["tier"] == lab]
        cost = next((r for r in sub if _ok(r.get("ms_per_frame"))), None)
        ms = (f"{cost['ms_per_frame']:.0f} ({_f(cost.get('x_full_cost'), '.2f')}, "
              f"{cost['scene']})" if cost else "-")
        if lab == "full" or not sub or "d_all" not in sub[0]:
            out.append(f"| {lab} | {ms} | - | - |")
            continue
        wa = min(sub, key=lambda r: r["d_all"])
        motion = [r for r in sub if _ok(r.get("d_motion"))]
        wm = min(motion, key=lambda r: r["d_motion"]) if motion else None
        fails = [r["scene"] for r in sub if not r.get("within_bars")]
        bars = "kept" if not fails else "fails on " + ", ".join(fails)
        if lab == "csr":
            bars = "for scale"
        worst = (f"{-wa['d_all']:.2f} ({wa['scene']}) / "
                 + (f"{-wm['d_motion']:.2f} ({wm['scene']})" if wm else "-"))
        out.append(f"| {lab} | {ms} | {worst} | {bars} |")
    out += ["", "Per scene, PSNR whole / motion region (dB):", "",
            "| scene | full | fast | CSR |", "|---|---|---|---|"]
    for sc in _distinct(rows, "scene"):
        cell = {r["tier"]: r for r in rows if r["scene"] == sc}
        out.append(f"| {sc} | " + " | ".join(
            f"{_f(cell[t]['psnr_all'], '.2f')} / {_f(cell[t].get('psnr_motion'), '.2f')}"
            if t in cell else "-" for t in ("full", "fast", "csr")) + " |")
    out.append("")
    return out


def compile_section(compiled: dict[str, Any]) -> list[str]:
    def cell(v: dict[str, float]) -> str:
        return f"{v['median']:.1f} ({v['min']:.1f}-{v['max']:.1f})"

    out = _table_head(
        "Compiling the kernels",
        "CPU seconds numba spends on an empty cache (a fresh install), median of "
        f"{compiled['runs']} run(s) with their range, each in a new process: every method together "
        "(the warm-up's order; kernels shared by several methods count under the first), and "
        "each method alone (its first use). Each kernel compiles once per machine: a process "
        "that needs one another process is compiling waits for it and loads the result.",
        ["method", "in the warm-up (CPU s)", "alone (CPU s)", "kernels"])
    for m, row in compiled["alone"].items():
        out.append(f"| {m} | {cell(compiled['in_all_cpu_s'][m])} | {cell(row['cpu_s'])} | "
                   f"{len(row['kernels'])} |")
    out.append(f"| **all** | {cell(compiled['all_cpu_s'])} | | |")
    out += ["", "The costliest kernels (own CPU seconds, median):", "",
            "| kernel | CPU s |", "|---|---|"]
    for k, v in list(compiled["kernels_cpu_s"].items())[:8]:
        out.append(f"| `{k}` | {v:.2f} |")
    out += ["", "A frame after the compile, in the pool's one-thread mode (CPU ms, median of "
            "the runs' medians; a 400 x 250 moving scene):", "",
            "| method | CPU ms per frame |", "|---|---|"]
    for m, f in compiled["frame_cpu_ms_one_thread"].items():
        out.append(f"| {m} | {cell(f)} |")
    if "pool_start_s" in compiled:
        ps = compiled["pool_start_s"]
        out += ["", f"Starting a pool of two one-thread processes on a filled cache (spawn, "
                f"imports, kernels loaded; the wait before its first frame): "
                f"{ps['median']:.2f} s ({ps['min']:.2f}-{ps['max']:.2f}). "
                "`workers=None` weighs a call's work against it (paid once: the pool is reused)."]
    out.append("")
    return out


def _defect_psnr(rows: list[dict[str, Any]], scene: str, method: str) -> str:
    """One table row: a method's whole-frame PSNR on each sensor of a scene, and the change
    against the clean sensor."""
    cell = {r["sensor"]: r.get("psnr_all") for r in rows
            if r["scene"] == scene and r["method"] == method}
    clean = cell.get("clean")

    def vs(key: str) -> str:
        v = cell.get(key)
        return (f"{_f(v, '.2f')} ({_f(v - clean, '+.2f')})" if _ok(v) and _ok(clean)
                else _f(v, ".2f"))

    keys = ("defective", "defective+corrected", "defective+calibrated", "hot+dead",
            "hot+dead+corrected", "clean+corrected", "clean+calibrated")
    return f"| {scene} | {method} | {_f(clean, '.2f')} | " + " | ".join(map(vs, keys)) + " |"


def defects_section(de: dict[str, Any]) -> list[str]:
    rows = de["rows"]
    out = _table_head(
        "Sensor defects",
        "`cfsr bench --defects`: the same content on a clean sensor and on a defective one "
        f"(`{de['noise']}` noise: hot and dead pixels and a threshold spread; `hot+dead`: the "
        "same without the spread), read as recorded, through the defect correction with "
        f"the map found in the first {de['map_steps']:,} steps (`corrected`), and through a "
        "flat-field calibration of the same sensor (`calibrated`: its map and every pixel's "
        "gain, divided out of the output). Whole-frame PSNR (dB) at "
        f"steps {', '.join(map(str, de['times']))}, the change against the clean sensor in "
        "brackets; `clean+corrected` and `clean+calibrated` are the clean sensor through "
        "each.",
        ("scene", "method", "clean", "defective", "corrected", "calibrated", "hot+dead",
         "corrected", "clean+corrected", "clean+calibrated"))
    for scene in _distinct(rows, "scene"):
        for m in _order([r["method"] for r in rows if r["scene"] == scene]):
            out.append(_defect_psnr(rows, scene, m))
    out += ["", "The map against the simulator's true one (hot / dead pixels), as it grows:",
            "", "| scene | steps | hot precision | hot recall | dead precision | dead recall "
            "| flagged on the clean sensor |", "|---|---|---|---|---|---|---|"]
    for scene, m in de["maps"].items():
        for c in m["over_time"]:
            out.append(f"| {scene} ({m['true_hot']} hot, {m['true_dead']} dead) | "
                       f"{c['steps']:,} | {_f(c['hot_precision'], '.3f')} | "
                       f"{_f(c['hot_recall'], '.3f')} | {_f(c['dead_precision'], '.3f')} | "
                       f"{_f(c['dead_recall'], '.3f')} | {m['clean_flags']} |")
    cal = {k: m["calibration"] for k, m in de["maps"].items() if "calibration" in m}
    if cal:
        out += ["", "The flat-field calibration (2,000 steps of uniform light) against the "
                "truth: " + "; ".join(
                    f"{k}: hot {_f(c['hot_precision'], '.3f')} / {_f(c['hot_recall'], '.3f')}, "
                    f"dead {_f(c['dead_precision'], '.3f')} / {_f(c['dead_recall'], '.3f')} "
                    f"(precision / recall), gain error {c['gain_rms_error']:.4f} rms against "
                    f"a spread of {c['true_gain_sd']:.4f}" for k, c in cal.items()) + "."]
    clean = de.get("clean_scenes", [])
    if clean:
        changed = [r for r in clean if r["flags"]]
        out += ["", "Every simulated scene on an ideal sensor, through the correction: pixels "
                "flagged " + ", ".join(f"{r['scene']} {r['flags']}" for r in clean) + ". "
                + ("Where none is flagged the spikes, so every output, are unchanged bit for "
                   "bit." if not changed else "Whole-frame PSNR change where some are: "
                   + "; ".join(r["scene"] + " " + ", ".join(
                       f"{k[:-6]} {v:+.2f} dB" for k, v in r.items() if k.endswith("_dpsnr"))
                       for r in changed) + ".")]
    cost = {k: v for k, v in de["cost"].items() if isinstance(v, dict)}
    new = "copy_ms_per_frame" in next(iter(cost.values()), {})
    out += ["", f"What correcting costs ({de['cost'].get('defects', '-')} flagged pixels, "
            + ("CPU time on one thread in the same run, the method's too), beside each "
               "method's own time per frame: a frame's window corrected in a reconstructor's "
               "buffer as `cfsr reconstruct` streams it (blocks of 1,024 steps), read through "
               "a corrected copy (the library's `corrected(rec)` read window by window), and "
               "corrected in the live worker's buffer (blocks of 256 steps, a frame every "
               "1,280: 30 frames/s); the last column is what keeping the live map costs per "
               "streamed step besides (counting, and a rebuild shared out)." if new else
               "wall time in the same run), beside each method's own time per frame: a "
               "frame's window read offline through a corrected copy, and corrected in the "
               "live buffer (each step of the window read once; counting and map rebuilds "
               "included, per streamed step in the last column)."), "",
            "| method | window (steps) | method ms per frame | offline ms (share) | "
            + ("copy ms (share) | " if new else "")
            + "live ms (share) | "
            + ("map upkeep µs per step |" if new else "live µs per step |"),
            "|---|---|---|---|---|---|" + ("---|" if new else "")]

    def share(ms: Any, frac: Any) -> str:
        return f"{_f(ms, '.3f')} ({_f(100 * frac if _ok(frac) else None, '.1f')} %)"

    for m in _order(list(cost)):
        c = cost[m]
        out.append(f"| {m} | {c['window_steps']} | {_f(c['method_ms_per_frame'], '.1f')} | "
                   f"{share(c['ms_per_frame'], c.get('fraction'))} | "
                   + (f"{share(c['copy_ms_per_frame'], c.get('copy_fraction'))} | "
                      if new else "")
                   + f"{share(c.get('live_ms_per_frame'), c.get('live_fraction'))} | "
                   f"{_f(c.get('upkeep_us_per_step', c.get('live_us_per_step')), '.2f')} |")
    out.append("")
    return out


def compile_table(compiled: dict[str, Any]) -> str:
    """The package's measured table: per method, the kernels it compiles alone and their
    CPU seconds (median), for the progress bars' 'n of N' and estimate."""
    table = {"machine": compiled.get("machine", {}),
             "methods": {m: {"cpu_s": round(row["cpu_s"]["median"], 2),
                             "kernels": row["kernels"]} for m, row in compiled["alone"].items()}}
    if "pool_start_s" in compiled:
        table["pool_start_s"] = round(compiled["pool_start_s"]["median"], 2)
    return json.dumps(table, indent=1, sort_keys=True) + "\n"


#: the live table's columns for a benchmark that also ran beside CPU-bound processes
_LIVE_BUSY_HEAD = (" CPU-bound processes beside | computed frames shown | output fps reported / "
                   "received | replay behind (frames) |", "---|---|---|---|")


def _live_busy_cells(r: dict) -> str:
    """A live run's busy figures: the processes beside it, the share of computed frames
    shown, the output rate the service reported against what a client received, and what a
    paced replay skipped to keep its clock."""
    share = r.get("shown_share")
    return (f" {r.get('busy', 0)} | {'' if share is None else _f(100 * share, '.0f') + ' %'} | "
            f"{_f(r.get('reported_fps'), '.1f')} / {_f(r.get('received_fps'), '.1f')} | "
            f"{(r.get('drops') or {}).get('replay', '')} |")


def render(folder: Path = BENCH) -> str:
    acc, tp, sw = (_load(n, folder) for n in ("accuracy.json", "throughput.json", "sweep.json"))
    out = ["# Results", "",
           "<!-- generated by scripts/results.py from docs/bench/*.json: do not edit by hand -->",
           "",
           "What `cfsr bench` measured. Timings are from one run on the machine named under "
           "each section (a shared machine: identical runs vary by tens of percent); the "
           "accuracy figures do not depend on the machine. How each method works: "
           "[methods.md](methods.md); how the figures came to be what they are: "
           "[history.md](history.md).", ""]
    if acc:
        out += accuracy_section(acc)
        out += [f"Machine: {_machine(acc)}.", ""]
    if tp:
        out += throughput_section(tp)
        out += [f"Machine: {_machine(tp)}.", ""]
    if sw:
        out += sweep_section(sw)
        out += [f"Machine: {_machine(sw)}.", ""]
    ti = _load("tiers.json", folder)
    if ti:
        out += tiers_section(ti)
        out += [f"Machine: {_machine(ti)}.", ""]
    compiled = _load("compile.json", folder)
    if compiled:
        out += compile_section(compiled)
        out += [f"Machine: {_machine(compiled)}.", ""]
    de = _load("defects.json", folder)
    if de:
        out += defects_section(de)
        out += [f"Machine: {_machine(de)}.", ""]
    return "\n".join(out).rstrip() + "\n"


def plots(folder: Path = BENCH) -> list[str]:
    from cfsr.plots import have_matplotlib, plot_metric_bars, plot_pareto

    acc = _load("accuracy.json", folder)
    if not acc or not have_matplotlib():
        return []
    rows = acc["rows"]
    sim = [r for r in rows if not r["scene"].startswith("reds:")]
    best = [r for s in sorted({r["scene"] for r in sim})
            for r in _best_per_method(sim, s).values()]
    bars = [{**r, "method": r["name"]} for r in best]
    return [
        plot_metric_bars(bars, str(folder / "psnr.png"), metric="psnr_all",
                         methods=_order([r["name"] for r in best]),
                         title="PSNR per scene (each method's best setting)"),
        plot_pareto(sim, str(folder / "pareto.png")),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="only compare docs/results.md with what the JSON gives; 1 if stale")
    ap.add_argument("--no-plots", action="store_true", help="write the page only")
    args = ap.parse_args(argv)
    text = render()
    compiled = _load("compile.json", BENCH)
    table = compile_table(compiled) if compiled else None
    if args.check:
        stale = [p for p, t in ((PAGE, text), (TABLE, table))
                 if t is not None and (not p.exists() or p.read_text() != t)]
        for p in stale:
            print(f"{p} is stale: run python scripts/results.py", file=sys.stderr)
        return 1 if stale else 0
    PAGE.write_text(text)
    if table is not None:
        TABLE.write_text(table)
    made = [] if args.no_plots else plots()
    print("\n".join([str(PAGE), *made]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
