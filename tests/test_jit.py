"""How cfsr's kernels compile (cfsr._jit): one compile per kernel across processes, a cache
stamp that follows the modules a kernel is built from, and the compile activity that
progress bars and the pool's watchdog read."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from cfsr import _jit

# Scripts' first lines: every compile in them starts SECONDS late, so that a compile is
# long enough to be seen (by another process, or by the heartbeat) for sure.
_SLOW_COMPILES = textwrap.dedent(
    """
    import json, sys, time
    from numba.core import event
    import cfsr._jit  # its listener first: the sleep below is inside a compile it sees

    class Slow(event.Listener):
        def on_start(self, ev):
            time.sleep(SECONDS)
        def on_end(self, ev):
            pass

    event.register("numba:compile", Slow())
    """
)

# A kernel module outside the package, compiled slowly on purpose, so two processes started
# together overlap on it.
_SLOW_KERNEL = _SLOW_COMPILES.replace("SECONDS", "1.5") + textwrap.dedent(
    """
    from cfsr._jit import njit, activity, on_compile

    events = []
    on_compile(lambda kind, act: events.append(kind))

    @njit
    def triple(x):
        return 3 * x

    sys.stdout.write(sys.argv[1] + " ready\\n"); sys.stdout.flush()
    sys.stdin.readline()  # both start compiling at the same moment
    assert triple(7) == 21
    a = activity()
    print(json.dumps({"compiled": a.compiled, "loaded": a.loaded, "events": events}))
    """
)


def test_two_processes_compile_a_kernel_once(tmp_path):
    """Two processes that need the same uncached kernel at once: one compiles it, the other
    waits for that compile and loads the result (never two compiles of one kernel)."""
    src = tmp_path / "slowkern.py"
    src.write_text(_SLOW_KERNEL)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    procs = [
        subprocess.Popen([sys.executable, str(src), str(k)], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
        for k in range(2)
    ]
    for p in procs:
        assert p.stdout.readline().endswith("ready\n")
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    got = []
    for p in procs:
        out, _ = p.communicate(timeout=120)
        assert p.returncode == 0, out
        got.append(json.loads(out.strip().splitlines()[-1]))
    assert sorted(g["compiled"] for g in got) == [0, 1], got
    loader = next(g for g in got if g["compiled"] == 0)
    assert loader["loaded"] == 1 and "wait" in loader["events"], got


def _package(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        (root / name).write_text(textwrap.dedent(text))


def test_the_stamp_follows_the_modules_a_kernel_is_built_from(tmp_path, monkeypatch):
    """An edit to a module whose kernel a caller embeds (or whose constant it freezes)
    changes the caller's stamp; an edit to an unrelated module does not, so only the kernels
    built from the edited code compile again."""
    _package(tmp_path, {
        "caller.py": """
            from cfsr._jit import njit
            from cfsr.helper import helper
            @njit
            def k(x):
                return helper(x)
            """,
        "helper.py": """
            from cfsr._jit import njit
            from cfsr.consts import SCALE
            @njit
            def helper(x):
                return SCALE * x
            """,
        "consts.py": "SCALE = 2\n",
        "other.py": "from cfsr._jit import njit\n",
    })
    monkeypatch.setattr(_jit, "_ROOT", tmp_path)

    def stamp() -> bytes:
        _jit._imports.cache_clear()
        _jit._stamp.cache_clear()
        return _jit._stamp(tmp_path / "caller.py")

    first = stamp()
    assert stamp() == first
    (tmp_path / "other.py").write_text("from cfsr._jit import njit\nX = 1\n")
    assert stamp() == first, "an unrelated module changed the stamp"
    (tmp_path / "consts.py").write_text("SCALE = 3\n")  # reached through a kernel module
    second = stamp()
    assert second != first
    (tmp_path / "helper.py").write_text((tmp_path / "helper.py").read_text() + "\n# edit\n")
    assert stamp() != second


_LOAD_MIX64 = textwrap.dedent(
    """
    import json, numpy as np
    import cfsr, cfsr._splitmix as m
    from cfsr._jit import activity
    m.mix64(np.uint64(1))
    a = activity()
    print(json.dumps({"file": cfsr.__file__, "compiled": a.compiled, "loaded": a.loaded}))
    """
)


def test_copies_of_the_same_code_at_other_paths_share_one_compile(tmp_path):
    """The same sources at another path (a wheel's venv beside its checkout) load the kernel
    the first copy compiled instead of compiling it again; a copy whose code differs compiles
    its own, beside it, and the first copy's entry still loads after that."""
    import shutil

    ignore = shutil.ignore_patterns("__pycache__")
    for name in ("a", "b", "edited"):
        shutil.copytree(Path(_jit.__file__).parent, tmp_path / name / "cfsr", ignore=ignore)
    helper = tmp_path / "edited" / "cfsr" / "_splitmix.py"
    helper.write_text(helper.read_text() + "\n# an edit\n")

    def run(name: str) -> tuple[int, int]:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
               "PYTHONPATH": str(tmp_path / name)}
        r = subprocess.run([sys.executable, "-c", _LOAD_MIX64], capture_output=True,
                           text=True, timeout=120, env=env, cwd=tmp_path)
        assert r.returncode == 0, r.stderr[-3000:]
        got = json.loads(r.stdout.strip().splitlines()[-1])
        assert got["file"] == str(tmp_path / name / "cfsr" / "__init__.py"), got
        return got["compiled"], got["loaded"]

    assert run("a") == (1, 0)
    assert run("b") == (0, 1), "an identical copy at another path compiled again"
    assert run("edited") == (1, 0), "a copy with other code loaded the first copy's kernel"
    assert run("a") == (0, 1)


def test_a_failed_compile_releases_its_lock(tmp_path, monkeypatch):
    """A kernel whose compile fails leaves no lock held, so the next process is not blocked
    for the life of this one."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    code = textwrap.dedent(
        """
        import fcntl, glob, os, sys
        from cfsr._jit import njit

        @njit
        def bad(x):
            return x.no_such_attribute

        try:
            bad(1)
        except Exception:
            pass
        locks = glob.glob(os.path.join(os.environ["NUMBA_CACHE_DIR"], "**", "*.lock"),
                          recursive=True)
        assert locks, "no lock file was made"
        for path in locks:
            fd = os.open(path, os.O_RDWR)
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # raises if still held
        print("free")
        """
    )
    script = tmp_path / "failing.py"
    script.write_text(code)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.strip() == "free", r.stderr


def test_activity_counts_compiles_and_the_beat_reports_them(tmp_path, monkeypatch):
    """The compile activity a progress bar and the pool's heartbeat read: a kernel compiled
    here is counted, with its name, and the beat sends while a compile runs."""
    code = _SLOW_COMPILES.replace("SECONDS", "0.5") + textwrap.dedent(
        """
        from cfsr._jit import njit, activity
        from cfsr.procs import start_compile_beat

        beats = []
        start_compile_beat(beats.append, every=0.1)

        @njit
        def add(a, b):
            return a + b

        add(1, 2)
        time.sleep(0.3)
        a = activity()
        print(json.dumps({"compiled": a.compiled, "done": list(a.done), "busy": a.busy,
                          "beats": [b.kernel for b in beats]}))
        """
    )
    script = tmp_path / "act.py"
    script.write_text(code)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                       timeout=120, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["compiled"] == 1 and not got["busy"]
    assert got["done"] == ["__main__.add"]
    # beats while compiling name the kernel; the last one says the compile ended
    assert "__main__.add" in got["beats"] and got["beats"][-1] is None, got["beats"]


@pytest.mark.parametrize("option", [{"parallel": True}, {"fastmath": True}])
def test_njit_passes_numba_options_and_caches(option):
    f = _jit.njit(**option)(lambda x: x + 1)
    assert f(1) == 2
    assert isinstance(f._cache, _jit._KernelCache)
