"""Where the compile wait goes: CPU seconds numba spends compiling each kernel of a warm-up.

Usage: ``NUMBA_CACHE_DIR=$(mktemp -d) python scripts/compile_profile.py [methods]``
(methods: comma-separated, default all, in the warm-up's order). Run it with an empty numba
cache, or it measures cache loads. Prints each method's CPU seconds, then the kernels by
exclusive CPU seconds (a kernel's own compile, without the kernels it calls that compile
separately) and the total. ``cfsr bench --compile`` measures the same, each run in a new
process on an empty cache, with the medians of three runs.
"""

from __future__ import annotations

import sys

from cfsr.warmup import compile_profile


def main() -> None:
    methods = sys.argv[1].split(",") if len(sys.argv) > 1 else None
    prof = compile_profile(methods)
    print(" ".join(f"{k} {v['cpu_s']:.1f} s" for k, v in prof["methods"].items()))
    print(f"{'own s':>7}  kernel")
    for name, own in sorted(prof["kernels"].items(), key=lambda kv: -kv[1])[:20]:
        print(f"{own:7.2f}  {name}")
    print(f"total {prof['cpu_s']:.1f} CPU s")


if __name__ == "__main__":
    main()
