"""Where the compile wait goes: CPU seconds numba spends compiling each kernel of a warm-up.

Usage: ``NUMBA_CACHE_DIR=$(mktemp -d) python scripts/compile_profile.py [methods]``
(methods: comma-separated, default all, in the warm-up's order). Run it with an empty numba
cache, or it measures cache loads. Prints each method's wall seconds (as ``cfsr warmup``
reports them), then the kernels by exclusive CPU seconds (a kernel's own compile, without the
kernels it calls that compile separately) and the total.
"""

from __future__ import annotations

import collections
import sys
import time

from numba.core import event

from cfsr.warmup import warm_up


class _Compiles(event.Listener):
    """Exclusive and inclusive CPU seconds of every ``numba:compile`` event, by function."""

    def __init__(self) -> None:
        self.stack: list[list] = []
        self.own: collections.Counter[str] = collections.Counter()
        self.total: collections.Counter[str] = collections.Counter()

    def on_start(self, ev: event.Event) -> None:
        fn = ev.data["dispatcher"].py_func
        self.stack.append([f"{fn.__module__}.{fn.__qualname__}", time.process_time(), 0.0])

    def on_end(self, ev: event.Event) -> None:
        name, t0, inner = self.stack.pop()
        took = time.process_time() - t0
        self.total[name] += took
        self.own[name] += took - inner
        if self.stack:
            self.stack[-1][2] += took


def main() -> None:
    methods = sys.argv[1].split(",") if len(sys.argv) > 1 else None
    rec = _Compiles()
    event.register("numba:compile", rec)
    per_method = warm_up(methods)
    print(" ".join(f"{k} {v:.1f} s" for k, v in per_method.items()))
    print(f"{'own s':>7} {'with callees':>12}  kernel")
    for name, own in rec.own.most_common(20):
        print(f"{own:7.2f} {rec.total[name]:12.2f}  {name}")
    print(f"total {sum(rec.own.values()):.1f} CPU s of compiling")


if __name__ == "__main__":
    main()
