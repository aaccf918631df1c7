"""Kernel warm-up: ``cfsr warmup`` and the background compilation of a first ``cfsr serve``
(a fresh install's first CSR/CFSR frame should not wait on the compiler), with progress kernel
by kernel."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import time

import numpy as np
from livehelpers import wait_until

import cfsr
from cfsr import warmup
from cfsr_live.service import kernel_warmup
from cfsr_live.service.kernel_warmup import RECONSTRUCTION_NICE, KernelWarmup

# the package, not the function cfsr.methods() that shadows it as an attribute of cfsr
REGISTRY = importlib.import_module("cfsr.methods")


def _cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cfsr", "warmup", *args],
        capture_output=True, text=True, timeout=600, env={**os.environ, **(env or {})},
    )


def test_warm_up_runs_each_method_and_marks_a_complete_warm_up(tmp_path, monkeypatch):
    # two registered methods only, and the marker in tmp_path: a complete warm-up of them
    real = REGISTRY.methods()
    monkeypatch.setattr(warmup, "registered", lambda: {k: real[k] for k in ("tfi", "tfp")})
    marker = tmp_path / "cfsr-warm-x"
    monkeypatch.setattr(warmup, "marker_path", lambda: marker)
    seen = []
    took = warmup.warm_up(progress=lambda name, s: seen.append(name))
    assert list(took) == seen == ["tfi", "tfp"] and all(s > 0 for s in took.values())
    assert marker.exists() and "tfi=" in marker.read_text()
    assert warmup.is_warm()
    marker.unlink()
    warmup.warm_up(["tfi"])  # a partial warm-up is not a warm machine
    assert not marker.exists() and not warmup.is_warm()


def test_marker_follows_the_code(monkeypatch):
    a = warmup._fingerprint()
    assert a == warmup._fingerprint()
    monkeypatch.setattr(cfsr, "__version__", "0+other", raising=False)
    assert warmup._fingerprint() != a  # another version (or changed sources): not warm


def test_cli_lines_and_errors(tmp_path):
    """``--lines`` on an empty cache: each method's kernels, one '# ' line per kernel
    compiled (its method, rank and CPU seconds), then 'NAME SECONDS' when the method is
    ready; a wrong name is one line and exit 2."""
    import re

    r = _cli("--lines", "--methods", "tfp,tfi", env={"NUMBA_CACHE_DIR": str(tmp_path)})
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    done = [ln.split() for ln in lines if not ln.startswith("# ")]
    assert [d[0] for d in done] == ["tfp", "tfi"]
    assert all(re.fullmatch(r"\d+\.\d{3}", d[1]) for d in done), done
    # kernel lines come before their method's line, name it, and count up from 1
    for name in ("tfp", "tfi"):
        end = lines.index(next(ln for ln in lines if ln.startswith(f"{name} ")))
        start = max((i + 1 for i, ln in enumerate(lines[:end]) if not ln.startswith("# ")),
                    default=0)
        ks = [re.match(rf"# {name}: kernel (\d+)", ln) for ln in lines[start:end]]
        assert ks and all(ks), lines[start:end]
        counts = [int(k.group(1)) for k in ks]
        assert counts == sorted(counts) and counts[-1] >= 1, counts
    bad = _cli("--methods", "nope")
    assert bad.returncode == 2 and "unknown method 'nope'" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1
    assert "once per install" in subprocess.run(
        [sys.executable, "-m", "cfsr", "--help"], capture_output=True, text=True
    ).stdout


def test_background_warm_up_reports_progress_and_finishes(monkeypatch):
    monkeypatch.setenv("CFSR_WARMUP", "1")
    monkeypatch.setattr(kernel_warmup, "is_warm", lambda: False)
    k = KernelWarmup()
    k.start(first="tfi", methods=["tfp", "tfi"])
    st = k.status()
    assert st.state == "compiling" and st.pending == ["tfi", "tfp"]  # the worker's method first
    try:
        wait_until(lambda: k.status().state != "compiling", timeout=300, what="warm-up to end")
    finally:
        k.stop()
    st = k.status()
    assert st.state == "done", st
    assert st.ready == ["tfi", "tfp"] and st.pending == [] and st.elapsed_s > 0


def test_background_warm_up_runs_at_the_pools_priority_and_stops_with_the_server(
    tmp_path, monkeypatch
):
    monkeypatch.setenv("CFSR_WARMUP", "1")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))  # nothing cached: CFSR compiles
    monkeypatch.setattr(kernel_warmup, "is_warm", lambda: False)
    k = KernelWarmup()
    k.start(methods=["cfsr"])
    proc = k._proc
    assert proc is not None
    try:
        # the pool's priority: never below a pool process waiting for a compile lock this
        # process holds
        assert os.getpriority(os.PRIO_PROCESS, proc.pid) == RECONSTRUCTION_NICE
        time.sleep(0.5)
        assert proc.poll() is None and k.status().state == "compiling"
    finally:
        k.stop()
    assert proc.poll() is not None and k.status().state == "stopped"


def test_cached_kernels_or_disabled_warm_up_start_nothing(monkeypatch):
    monkeypatch.setenv("CFSR_WARMUP", "1")
    monkeypatch.setattr(kernel_warmup, "is_warm", lambda: True)
    k = KernelWarmup()
    k.start()
    assert k._proc is None and k.status().state == "ready"
    assert set(k.status().ready) == set(REGISTRY.methods())
    monkeypatch.setenv("CFSR_WARMUP", "0")
    k = KernelWarmup()
    k.start()
    assert k._proc is None and k.status().state == "off"


def test_warm_up_compiles_what_a_real_frame_uses(tmp_path):
    """After a warm-up on its small scene, a fresh process's first frame of a 400 x 250 file
    finds every kernel cached: numba compiles nothing more (its cache folder gains no file)."""
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    assert _cli("--lines", "--methods", "tfa", env=env).returncode == 0
    before = sorted(p.name for p in (tmp_path / "cache").rglob("*"))
    rng = np.random.default_rng(0)
    spikes = (rng.random((600, 250, 400)) < 0.2).astype(np.uint8)
    cfsr.write_dat(tmp_path / "r.dat", spikes)
    r = subprocess.run(
        [sys.executable, "-m", "cfsr", "reconstruct", str(tmp_path / "r.dat"), "-m", "tfa",
         "-t", "300", "--out", str(tmp_path / "o"), "-q"],
        capture_output=True, text=True, timeout=600, env={**os.environ, **env},
    )
    assert r.returncode == 0, r.stderr
    after = sorted(p.name for p in (tmp_path / "cache").rglob("*"))
    assert after == before


def test_first_serve_compiles_in_the_background_and_stops_it_with_the_server(tmp_path):
    """A server with nothing cached starts the warm-up, says so, reports it in /api/status,
    and leaves no warm-up process behind when it stops."""
    from livehelpers import LiveServer, write_pattern

    rec = write_pattern(tmp_path / "p.dat", 2048)
    env = {"CFSR_WARMUP": "1", "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    srv = LiveServer(["--replay", str(rec), "--data-dir", str(tmp_path / "d")], env=env).start()
    try:
        st = srv.wait_for(lambda s: s["kernels"]["pid"], 60, "a warm-up process")["kernels"]
        assert st["state"] == "compiling" and st["pending"][0] == "tfp"  # the worker's first
        pid = st["pid"]
        assert os.getpriority(os.PRIO_PROCESS, pid) == RECONSTRUCTION_NICE
        assert "compiling the methods' kernels in the background" in srv.output()
    finally:
        srv.stop()
    wait_until(lambda: not os.path.exists(f"/proc/{pid}"), 10, "the warm-up process to end")


def test_if_needed_does_nothing_once_this_code_was_warmed(tmp_path):
    """``cfsr warmup --if-needed`` (what ``./tasks`` runs before an offline command or the
    benchmark) returns at once when a complete warm-up of this code left its marker in
    numba's cache folder."""
    env = {"NUMBA_CACHE_DIR": str(tmp_path)}
    (tmp_path / f"cfsr-warm-{warmup._fingerprint()}").write_text("tfi=0.1\n")
    r = _cli("--if-needed", "--lines", env=env)
    assert r.returncode == 0 and r.stdout == "", (r.stdout, r.stderr)
    assert not any(p.suffix == ".nbi" for p in tmp_path.rglob("*"))  # nothing compiled
    # named methods are an explicit request: they run whatever the marker says
    r = _cli("--if-needed", "--lines", "--methods", "tfi", env=env)
    done = [ln for ln in r.stdout.splitlines() if not ln.startswith("# ")]
    assert r.returncode == 0 and [ln.split()[0] for ln in done] == ["tfi"], r.stderr


def test_cache_dir_is_where_numba_writes_the_kernels(tmp_path):
    """Without ``NUMBA_CACHE_DIR`` the marker goes where numba's own locator caches cfsr's
    kernels (the package's ``__pycache__`` in a writable install), so a warm-up is seen again."""
    code = "from cfsr.warmup import cache_dir; print(cache_dir())"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=120, check=True).stdout.strip()
    pkg = os.path.dirname(cfsr.__file__)
    if os.access(pkg, os.W_OK):
        assert out == os.path.join(pkg, "__pycache__")
    env["NUMBA_CACHE_DIR"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=120, check=True).stdout.strip()
    assert out == str(tmp_path)
