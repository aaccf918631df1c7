"""What a change costs: CFSR's ms per frame at several commits, measured in turn.

Usage: ``python scripts/commit_costs.py REV [REV ...] [--rounds N] [--scenes disk,fan]
[--method cfsr] [--min-time S]``

Each revision is checked out once (``git worktree``, in the system's temporary folder) and
timed in its own Python process with its own numba cache (the first round of a new checkout
compiles for a few minutes), by its own ``cfsr.bench.method_fps``: the newest step of a
4096-step simulated scene through the streaming reconstructor, as ``cfsr bench --throughput``
times its demo disk scene. The revisions run one after the other in every round, so a host
that slows down or speeds up meets all of them; the table gives each revision's median over
the rounds and its change against the first revision. On a shared 2-vCPU host single rounds
spread by 10-20 %: take 9 rounds or more before reading a few percent.
"""

from __future__ import annotations

import argparse
import json
import os
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
    args = ap.parse_args()
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
            print(
                f"  {rev:14s} {med:8.1f}  ({min(v):.1f}-{max(v):.1f})  {med / ref - 1:+7.1%}"
            )


if __name__ == "__main__":
    main()
