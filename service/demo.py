"""The built-in demo recording: simulated on first use, cached under the user cache folder."""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from cfsr.datfile import write_dat
from cfsr_live.replay.pattern import pattern_recording
from cfsr_live.service.settings import cache_dir

__all__ = ["demo_path", "ensure_demo", "DEMO_SCENE"]

log = logging.getLogger("cfsr.demo")

DEMO_SCENE = "disk"
_VERSION = 1


def demo_path(steps: int) -> Path:
    return cache_dir() / f"demo-{DEMO_SCENE}-{steps}-v{_VERSION}" / "demo.dat"


def ensure_demo(steps: int = 6000, *, say: Callable[[str], None] | None = None) -> Path:
    """Return the cached demo ``.dat``, simulating it first if needed (atomic, race-safe).

    Uses :func:`cfsr.simulate.simulate_to_dat` (a rotating textured disk); if that simulator is
    not available in this build, falls back to the small built-in pattern scene.
    """
    target = demo_path(steps)
    if target.exists() and target.with_name(target.name + ".json").exists():
        return target
    target.parent.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".demo-tmp-", dir=target.parent.parent))
    out = tmp / "demo.dat"
    if say:
        say(f"creating the demo recording ({steps} steps, first run only) in {target.parent}")
    try:
        try:
            # deferred: the simulator loads when the demo is first made, not in `cfsr --help`
            from cfsr.simulate import simulate_to_dat
        except ImportError:
            simulate_to_dat = None  # type: ignore[assignment]
        if simulate_to_dat is not None:
            simulate_to_dat(DEMO_SCENE, steps, out, seed=0)
        else:
            log.warning("cfsr.simulate is unavailable; the demo uses the built-in pattern scene")

            write_dat(out, pattern_recording(steps))
        try:
            os.rename(tmp, target.parent)
        except OSError:
            if not target.exists():  # not a lost race: a real failure
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target
