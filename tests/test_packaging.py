"""The installed wheel is the product: what ``pip install cfsr`` and ``pip install cfsr[live]``
give a user, in fresh virtual environments outside the source tree, run from a folder that is
not the checkout (fixtures ``base_install`` / ``live_install`` in conftest.py)."""

from __future__ import annotations

import json
import subprocess
import zipfile
from pathlib import Path

import httpx
import pytest
from livehelpers import LiveServer, write_pattern, ws_frames
from wheelenv import REPO, clean_env, project_version, run_cli

pytestmark = [pytest.mark.packaging, pytest.mark.timeout(1200)]

#: what the base install must neither import nor even have installed
LIVE_AND_EXTRA_MODULES = ("fastapi", "starlette", "uvicorn", "websockets", "usb",
                          "prometheus_client", "dask", "distributed", "matplotlib")


def _one_line_error(r: subprocess.CompletedProcess, *needles: str) -> str:
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def test_wheel_holds_the_viewer_and_registers_the_live_commands(wheel_file):
    with zipfile.ZipFile(wheel_file) as z:
        names = set(z.namelist())
        eps = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        entry_points = z.read(eps).decode()
        meta = z.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    for f in ("index.html", "app.js", "style.css"):
        assert f"cfsr_live/viewer/{f}" in names
    assert "cfsr/cli/__init__.py" in names and "cfsr/__main__.py" in names
    # two top-level names: the library and the application, no generic ones
    # (service, driver, replay, shm, viewer would collide with other packages)
    top = {n.split("/")[0] for n in names if ".dist-info/" not in n}
    assert top == {"cfsr", "cfsr_live"}, top
    # every module of the tree's layers is in the wheel, under its mapped name
    for layer, under in (("cfsr", "cfsr"), ("service", "cfsr_live/service"),
                         ("driver", "cfsr_live/driver"), ("replay", "cfsr_live/replay"),
                         ("shm", "cfsr_live/shm"), ("viewer", "cfsr_live/viewer")):
        for f in (REPO / layer).rglob("*.py"):
            assert f"{under}/{f.relative_to(REPO / layer).as_posix()}" in names, f
    assert "[cfsr.commands]" in entry_points
    assert "serve = cfsr_live.service.commands.serve" in entry_points
    assert "record = cfsr_live.service.commands.record" in entry_points
    assert "cfsr = cfsr.cli:main" in entry_points
    for extra in ("live", "cluster", "bench", "all"):
        assert f"Provides-Extra: {extra}" in meta
    assert f"Version: {project_version()}" in meta


def test_base_install_is_the_library_and_offline_cli(base_install, tmp_path):
    bindir = base_install
    py = str(bindir / "python")
    # the optional stacks are not even installed
    probe = ("import importlib.util, json; print(json.dumps([m for m in "
             f"{LIVE_AND_EXTRA_MODULES!r} if importlib.util.find_spec(m) is not None]))")
    r = subprocess.run([py, "-c", probe], capture_output=True, text=True, cwd=tmp_path,
                       env=clean_env(bindir), check=True)
    assert json.loads(r.stdout) == []

    # import cfsr + a reconstruction load none of them
    code = (
        "import sys, numpy as np, cfsr\n"
        "x = (np.random.default_rng(0).random((300, 16, 24)) < 0.2).astype(np.uint8)\n"
        "out = cfsr.reconstruct(x, 'tfp', [200], window=32)\n"
        "assert out.shape == (1, 16, 24)\n"
        f"bad = [m for m in {LIVE_AND_EXTRA_MODULES!r} if m in sys.modules]\n"
        "print(cfsr.__file__); assert not bad, bad\n"
    )
    r = subprocess.run([py, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                       env=clean_env(bindir))
    assert r.returncode == 0, r.stderr
    assert str(REPO) not in r.stdout  # the installed copy, not the checkout

    r = run_cli(bindir, ["--version"], tmp_path)
    assert r.returncode == 0 and r.stdout.strip() == f"cfsr {project_version()}"
    r = subprocess.run([py, "-m", "cfsr", "--version"], capture_output=True, text=True,
                       cwd=tmp_path, env=clean_env(bindir))
    assert r.stdout.strip() == f"cfsr {project_version()}"

    # the offline commands work
    r = run_cli(bindir, ["simulate", "disk", "--steps", "400", "-o", "disk.dat", "--height",
                         "60", "--width", "80"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "disk.dat").exists() and (tmp_path / "disk.dat.json").exists()
    r = run_cli(bindir, ["reconstruct", "disk.dat", "-m", "tfp", "-t", "200,300", "--out", "out",
                         "-q"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "out" / "t300.npy").exists() and (tmp_path / "out" / "t300.png").exists()
    r = run_cli(bindir, ["info", "disk.dat", "--json"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["n_frames"] == 400
    r = run_cli(bindir, ["methods"], tmp_path)
    assert r.returncode == 0 and "cfsr" in r.stdout
    # record from a file needs only the base install
    r = run_cli(bindir, ["record", "--replay", "disk.dat", "--frames", "100", "-o", "rec.dat"],
                tmp_path)
    assert r.returncode == 0, r.stderr

    # commands whose extra is missing say which one, in one line, before doing any work
    _one_line_error(run_cli(bindir, ["serve"], tmp_path), "cfsr serve", "cfsr[live]", "fastapi")
    _one_line_error(run_cli(bindir, ["record", "--usb", "--frames", "10", "-o", "u.dat"],
                            tmp_path), "cfsr[live]")
    _one_line_error(run_cli(bindir, ["reconstruct", "disk.dat", "-t", "300", "--cluster"],
                            tmp_path), "cfsr[cluster]")
    # the benchmark runs without its plotting extra: tables and JSON, and one line on the plot
    r = run_cli(bindir, ["bench", "--quick", "--no-data", "-q", "--methods", "tfp", "--scenes",
                         "static", "--steps", "400", "--out", "b"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert [ln for ln in r.stdout.splitlines() if "plot skipped" in ln and "cfsr[bench]" in ln]
    r = run_cli(bindir, ["--help"], tmp_path)
    assert "serve" in r.stdout and "cfsr[live]" in r.stdout


def test_live_install_serves_viewer_ws_and_mjpeg(live_install, tmp_path):
    bindir = live_install
    r = run_cli(bindir, ["--version"], tmp_path)
    assert r.stdout.strip() == f"cfsr {project_version()}"
    dat = write_pattern(tmp_path / "data" / "pattern.dat", 3000)
    work = tmp_path / "elsewhere"
    work.mkdir()
    with LiveServer(["--replay", str(dat), "--data-dir", str(tmp_path / "data")],
                    command=[str(bindir / "cfsr"), "serve"], cwd=work,
                    env=clean_env(bindir)) as s:
        page = httpx.get(s.url + "/", timeout=30)
        assert page.status_code == 200 and "<title>CFSR live viewer</title>" in page.text
        assert httpx.get(s.url + "/app.js", timeout=30).status_code == 200
        # binary frames over the WebSocket
        frames = ws_frames(s, 2, timeout=120)
        assert len(frames) == 2 and frames[0]["image"].shape == (250, 400)
        # JPEGs over MJPEG
        data = b""
        with httpx.stream("GET", s.url + "/stream.mjpg", timeout=60) as resp:
            assert resp.status_code == 200
            assert resp.headers["content-type"].startswith("multipart/x-mixed-replace")
            for chunk in resp.iter_bytes():
                data += chunk
                if data.count(b"\xff\xd9") >= 2:
                    break
        assert data.count(b"\xff\xd8\xff") >= 2
        out = s.output()
    assert "viewer at http://127.0.0.1:" in out
    assert "missing" not in out


def test_live_install_refuses_to_start_without_its_viewer(live_install, tmp_path):
    bindir = live_install
    r = subprocess.run([str(bindir / "python"), "-c",
                        "import cfsr_live.service.app as a; print(a.viewer_dir())"],
                       capture_output=True, text=True, check=True, cwd=tmp_path,
                       env=clean_env(bindir))
    page = Path(r.stdout.strip()) / "index.html"
    assert page.is_file() and str(REPO) not in str(page)
    hidden = page.with_name("index.html.hidden")
    page.rename(hidden)
    try:
        r = run_cli(bindir, ["serve", "--port", "1", "--data-dir", str(tmp_path / "d")],
                    tmp_path, timeout=120)
        _one_line_error(r, "viewer", "missing")
        assert "viewer at" not in r.stdout
    finally:
        hidden.rename(page)
