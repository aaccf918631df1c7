"""What a change costs: CFSR's ms per frame at several commits, measured in turn.

Usage: ``python scripts/commit_costs.py REV [REV ...] [--rounds N] [--scenes disk,fan]
[--method cfsr] [--min-time S] [--paired [--pairs N]]``

Each revision is checked out once (``git worktree``, in the system's temporary folder) and
timed in its own Python process with its own numba cache (the first round of a new checkout
compiles for a few minutes), by its own ``cfsr.bench.method_fps``: the newest step of a
4096-step simulated scene through the streaming reconstructor, as ``cfsr bench --throughput``
times its demo disk scene. The revisions run one after the other in every round, so a host
that slows down or speeds up meets all of them; the table gives each revision's median over
the rounds and its change against the first revision. On a shared 2-vCPU host single rounds
spread by 10-40 %: take 9 rounds or more before reading a few percent.

``--paired`` loads every revision in one process instead (each revision's ``cfsr`` package is
copied out of git and renamed ``cfsr_<sha>``, its imports rewritten) and times their frames in
turn, one call each per pair, on the same simulated spikes (this checkout's simulator): a
host that slows down meets every revision within one pair, and the median of the per-pair
ratios to the first revision, with its interquartile range, resolves a few percent that
single rounds do not (measured: the separate-process rounds of one commit ranged 84-141 ms
on the disk in one run). The order of the revisions turns from pair to pair, so none always
runs first or right after the same one. The first pair of a new revision compiles it
(minutes; its numba cache is kept beside the copy).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = """
import json, sys
from cfsr._bits import pack_frames
from cfsr.bench import method_fps
from cfsr.layout import Layout
from cfsr.simulate import simulate
method, scenes, min_time = sys.argv[1], sys.argv[2].split(","), float(sys.argv[3])
out = {}
for scene in scenes:
    sim = simulate(scene, 4096, seed=0, height=250, width=400)
    r = method_fps(pack_frames(sim.spikes), Layout(400, 250), method, min_time=min_time)
    out[scene] = r["ms_per_frame"]
print(json.dumps(out))
"""


def checkout(rev: str) -> Path:
    """A worktree of ``rev`` (kept between runs, so numba's cache in it is reused)."""
    sha = subprocess.check_output(["git", "rev-parse", rev], cwd=ROOT, text=True).strip()
    where = Path(tempfile.gettempdir()) / "cfsr-commit-costs" / sha[:12]
    if not (where / "cfsr").is_dir():
        where.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            ["git", "worktree", "add", "--detach", str(where), sha],
            cwd=ROOT,
            check=True,
            capture_output=True,
        )
    return where


_CHILD_PAIRED = """
import json, statistics, sys, time, importlib
from cfsr._bits import pack_frames
from cfsr._heap import keep_freed_memory
from cfsr.simulate import simulate
keep_freed_memory()  # as the cfsr command line does
method, scenes, pairs = sys.argv[1], sys.argv[2].split(","), int(sys.argv[3])
names = sys.argv[4:]
mods = [(importlib.import_module(n + ".streaming"), importlib.import_module(n + ".layout"))
        for n in names]
out = {}
for scene in scenes:
    packed = pack_frames(simulate(scene, 4096, seed=0, height=250, width=400).spikes)
    runs = []
    for st, lay in mods:
        sr = st.StreamingReconstructor(method, lay.Layout(400, 250), slack=len(packed))
        sr.push(packed, 0)
        t = sr.latest_step()
        for _ in range(3):  # compile, warm up
            sr.compute(t)
        runs.append((sr, t))
    ms = [[] for _ in runs]
    for i in range(pairs):
        # the order turns every pair: no revision always runs first or after the same one
        for k in [(i + j) % len(runs) for j in range(len(runs))]:
            sr, t = runs[k]
            if hasattr(sr, "memo"):
                sr.memo.clear()
            t0 = time.perf_counter()
            sr.compute(t)
            ms[k].append((time.perf_counter() - t0) * 1e3)
    out[scene] = ms
print(json.dumps(out))
"""

# the import forms that name the package: ``from cfsr.x``, ``import cfsr``, and ``"cfsr.x"``
# strings (importlib, entry-point groups); not ``"cfsr"`` alone (the method's name)
_IMPORT = re.compile(r"""(\bfrom\s+|\bimport\s+)cfsr\b|(["'])cfsr(?=\.)""")


def rename_imports(text: str, name: str) -> str:
    """``text`` (Python source) with every import of the ``cfsr`` package naming ``name``."""
    return _IMPORT.sub(lambda m: (m.group(1) or m.group(2)) + name, text)


def renamed_copy(rev: str) -> tuple[Path, str]:
    """``rev``'s ``cfsr`` package as ``cfsr_<sha>`` in a folder of its own (kept between runs):
    ``(folder to put on sys.path, package name)``."""
    sha = subprocess.check_output(["git", "rev-parse", rev], cwd=ROOT, text=True).strip()[:12]
    name = f"cfsr_{sha}"
    where = Path(tempfile.gettempdir()) / "cfsr-commit-costs" / "paired" / sha
    pkg = where / name
    if not (pkg / "__init__.py").is_file():
        where.mkdir(parents=True, exist_ok=True)
        tar = subprocess.run(
            ["git", "archive", sha, "cfsr"], cwd=ROOT, check=True, capture_output=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(where)], input=tar, check=True)
        (where / "cfsr").rename(pkg)
        for py in pkg.rglob("*.py"):
            py.write_text(rename_imports(py.read_text(), name))
    return where, name


def measure_paired(revs: list[str], method: str, scenes: str, pairs: int) -> dict[str, list]:
    """Per scene, per revision: the ms of each pair (see the module notes)."""
    copies = [renamed_copy(r) for r in revs]
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    # this checkout's cfsr (the simulator) first, then every copy
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [str(w) for w, _ in copies])
    res = subprocess.run(
        [sys.executable, "-c", _CHILD_PAIRED, method, scenes, str(pairs)] + [n for _, n in copies],
        env=env,
        cwd=tempfile.gettempdir(),
        capture_output=True,
        text=True,
    )
    if res.returncode != 0:
        raise SystemExit(f"the paired run failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _quartiles(v: list[float]) -> tuple[float, float, float]:
    q = statistics.quantiles(v, n=4)
    return q[0], statistics.median(v), q[2]


def paired_table(revs: list[str], got: dict[str, list], method: str) -> None:
    for scene, ms in got.items():
        print(f"{scene}: {method} ms per frame over {len(ms[0])} pairs, and per pair / {revs[0]}")
        for rev, v in zip(revs, ms, strict=True):
            q1, med, q3 = _quartiles([a / b for a, b in zip(v, ms[0], strict=True)])
            print(
                f"  {rev:14s} {statistics.median(v):8.1f}  ratio {med:.3f}"
                f" (interquartile {q1:.3f}-{q3:.3f})"
            )


def measure(tree: Path, method: str, scenes: str, min_time: float) -> dict[str, float]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = str(tree)  # ahead of an editable install of another checkout
    res = subprocess.run(
        [sys.executable, "-c", _CHILD, method, scenes, str(min_time)],
        env=env,
        cwd=tempfile.gettempdir(),
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("revs", nargs="+", help="commits to compare; the first is the baseline")
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--scenes", default="disk", help="simulator scenes, comma-separated")
    ap.add_argument("--method", default="cfsr")
    ap.add_argument("--min-time", type=float, default=2.0, help="seconds timed per scene")
    ap.add_argument(
        "--paired", action="store_true", help="every revision in one process, alternating"
    )
    ap.add_argument("--pairs", type=int, default=30, help="with --paired: frames per revision")
    args = ap.parse_args()
    if args.paired:
        paired_table(
            args.revs, measure_paired(args.revs, args.method, args.scenes, args.pairs), args.method
        )
        return
    trees = [checkout(r) for r in args.revs]
    got: dict[str, dict[str, list[float]]] = {r: {} for r in args.revs}
    for k in range(args.rounds):
        for rev, tree in zip(args.revs, trees, strict=True):
            ms = measure(tree, args.method, args.scenes, args.min_time)
            for scene, v in ms.items():
                got[rev].setdefault(scene, []).append(v)
            print(f"round {k + 1}: {rev} {json.dumps(ms)}", file=sys.stderr, flush=True)
    base = args.revs[0]
    for scene in args.scenes.split(","):
        ref = statistics.median(got[base][scene])
        print(f"{scene}: {args.method} ms per frame, median of {args.rounds} rounds")
        for rev in args.revs:
            v = got[rev][scene]
            med = statistics.median(v)
            print(f"  {rev:14s} {med:8.1f}  ({min(v):.1f}-{max(v):.1f})  {med / ref - 1:+7.1%}")


if __name__ == "__main__":
    main()
