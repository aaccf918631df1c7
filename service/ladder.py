"""The ladder: what the live worker shows while the first frame under a config waits on numba's
compiler (a first use on a machine). TFP, computed by the worker itself, at once; then the
method's rung (CSR for CFSR, whose kernels compile in seconds) from an idle pool process; each
labelled in the status (``fallback``) and only while that compile lasts. A first frame that is
merely slow (no compile) keeps the last frame of the chosen method on screen.
"""

from __future__ import annotations

import functools
import time
from typing import Any

from cfsr.config import MethodConfig
from cfsr.methods.registry import get_method
from cfsr.warmup import measured_compile
from cfsr_live.service.pacing import FrameTask
from cfsr_live.service.status import CompileProgress
from cfsr_live.service.worker_messages import RUNG_CODES, Compiling

__all__ = ["FALLBACK_AFTER_S", "LADDER", "STAND_IN_FPS", "LadderSteps", "rung_config"]

#: the rung of the ladder shown while a method's first frame waits on its compile, computed
#: by an idle pool process (TFP, the first rung, is computed by the worker itself)
LADDER = {"cfsr": "csr"}
#: most stand-in frames a second (TFP, CSR) while a first frame compiles: enough to see the
#: scene move, and the CPU goes to the compile the user waits for
STAND_IN_FPS = 5.0


#: seconds the first frame under a config may be pending before the worker shows frames of a
#: ready method (TFP) meanwhile: on a first use that frame waits on numba's compiler
FALLBACK_AFTER_S = 1.0


class LadderSteps:
    """The ladder's part of :class:`~cfsr_live.service.frame_worker.FrameWorker` (a mixin:
    it reads the worker's pool, buffer, tasks and config, and publishes through it)."""

    def _compiling_first(self) -> tuple[FrameTask, Any] | None:
        """The pending task of the config and its process's compile report, while the
        config's first frame waits on a compile (or on another process's compile)."""
        if not self._first_pending:
            return None
        for task in self._tasks.values():
            if not task.rung and self._current(task):
                beat = self.pool.compiling(task.process)
                if beat is not None:
                    return task, beat
        return None

    def _submit_rung(self, t: int, now: float) -> bool:
        """While the config's first frame compiles, an idle process computes the method's
        rung of the ladder (CSR for CFSR: its kernels compile in seconds) at the newest step,
        one at a time, so the picture climbs from TFP to CSR before CFSR arrives."""
        rung = LADDER.get(self.config.method.method)
        rec = self.rec
        if rung is None or rec is None or any(k.rung for k in self._tasks.values()):
            return False
        if self._last_shown is not None and t <= self._last_shown:
            return False
        cfg = rung_config(rung)
        before, after = cfg.window
        if t + after >= rec.next_step:
            t = rec.next_step - after - 1
        a, b = max(rec.first_step, t - before), min(rec.next_step, t + after + 1)
        if t < a or (b - a) * rec.layout.frame_bytes > self.pool.region_bytes:
            return False
        self._tag += 1
        k = self.pool.submit(self._tag, cfg, rec.layout, rec.packed(a, b), a, [(a, b, t)])
        self._tasks[self._tag] = FrameTask(
            t, self._arrival_of(t + after), "full", self.config.version, now, k, rung,
            (k, rung) not in self._warm, self._clock, rung=True,
        )
        self._next_out = max(now + 1.0 / min(self.config.max_fps, STAND_IN_FPS),
                             time.monotonic())
        return True

    def _show_rung(self, task: FrameTask, t: int, out: Any, ms: float) -> None:
        """Show a rung's frame while the config's first frame still waits (and it is newer
        than what is shown); the ladder only climbs, so TFP stops once CSR is shown."""
        if not (self._first_pending and self._current(task)):
            return
        if self._last_shown is not None and t <= self._last_shown:
            return
        self._rung = max(self._rung, RUNG_CODES[task.method])
        self.put("fallback", float(self._rung))
        self._publish(t, out, task.method, task.arrival, ms, timed=False)
        self.bump("fallback_frames")

    def _fallback(self) -> bool:
        """While the first frame under the config waits on numba's compiler (its process's
        compile heartbeat says so), show TFP frames, computed here, so the image does not
        freeze: the ladder's first rung, until a higher one (CSR) is shown. A first frame
        that is merely slow (no compile) keeps the last frame of the chosen method."""
        rec = self.rec
        if (
            rec is None
            or not self._first_pending
            or self._first_since is None
            or self.config.method.method == "tfp"
            or self._rung > RUNG_CODES["tfp"]
            or self._compiling_first() is None
        ):
            return False
        now = time.monotonic()
        if now - self._first_since < FALLBACK_AFTER_S or now < self._fallback_next:
            return False
        t = rec.latest_step()
        if t is None or (self._last_shown is not None and t <= self._last_shown):
            return False
        tfp = get_method("tfp")
        fb = rung_config("tfp")
        before, after = fb.window
        t0 = time.perf_counter()
        out = tfp.run_window(
            rec, max(rec.first_step, t - before), min(rec.next_step, t + after + 1), t,
            fb.params,
        )
        ms = (time.perf_counter() - t0) * 1e3
        self._rung = max(self._rung, RUNG_CODES["tfp"])
        self.put("fallback", float(self._rung))
        self._publish(t, out, "tfp", self._arrival_of(t), ms, timed=False)
        self.bump("fallback_frames")
        self._fallback_next = now + 1.0 / min(self.config.max_fps, STAND_IN_FPS)
        return True

    def _report_compile(self) -> None:
        """Tell the supervisor what the config's first frame waits on (each change of
        kernel, count or whole CPU second, and once when no compile holds it any more)."""
        got = self._compiling_first()
        key = None if got is None else (got[1].kernel, got[1].kernels, int(got[1].cpu_s))
        if key == self._compile_key:
            return
        self._compile_key = key
        progress = None
        if got is not None:
            task, beat = got
            table = measured_compile().get("methods", {}).get(task.method, {})
            progress = CompileProgress(
                method=task.method, kernel=beat.kernel, waiting=beat.waiting,
                kernels=beat.kernels, total=len(table.get("kernels", [])) or None,
                cpu_s=beat.cpu_s, estimate_s=table.get("cpu_s"),
            )
        self.evt_q.put(Compiling(progress))


@functools.cache
def rung_config(method: str) -> Any:
    """A rung of the ladder at its default parameters (TFP, the first: cheap, and the
    first a warm-up compiles; CSR for CFSR)."""
    return MethodConfig(method)
