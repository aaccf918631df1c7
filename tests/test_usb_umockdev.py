"""The umockdev USB tier, run from the normal test command.

umockdev's preload must be in place when a process starts, so the cases in
``tests/usb/umock_cases.py`` run in one subprocess under ``umockdev-wrapper``; each case is
reported here as its own test. The service itself also runs on the emulated camera (paced at
40,000 frames/s) and is checked over HTTP and WebSocket, an unplug included.

On a developer machine without umockdev these skip; under ``CI=true`` they fail (see
``tests/conftest.py``). Debian packages: ``umockdev libumockdev0 libusb-1.0-0``.
"""

from __future__ import annotations

import ctypes.util
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest
from conftest import require_tier
from livehelpers import REPO, LiveServer, wait_until, write_pattern, ws_frames

pytestmark = [pytest.mark.usb, pytest.mark.timeout(600)]

CASES = [
    "test_enumeration_and_descriptors",
    "test_kernel_rules_packet_alignment_and_usbfs_limit",
    "test_driver_byte_exact_from_dat",
    "test_paced_40k_frames_per_second_for_5s_without_loss[camera0]",
    "test_fault_then_recovery[stall-stalls-256]",
    "test_fault_then_recovery[overflow-overflows-256]",
    "test_fault_then_recovery[short-short_blocks-256]",
    "test_fault_then_recovery[corrupt-crc_errors-256]",
    "test_fault_then_recovery[corrupt_header-bad_headers-256]",
    "test_fault_then_recovery[timeout-timeouts-0]",
    "test_unplug_then_replug[unplug-camera0]",
    "test_unplug_then_replug[unplug_eio-camera0]",
]


def _tier_ok() -> tuple[bool, str]:
    if shutil.which("umockdev-wrapper") is None:
        return False, "umockdev-wrapper not found (apt-get install umockdev libumockdev0)"
    for lib in ("umockdev", "usb-1.0", "gobject-2.0"):
        if ctypes.util.find_library(lib) is None:
            return False, f"lib{lib} not found (apt-get install umockdev libumockdev0 libusb-1.0-0)"
    try:
        import usb.core  # noqa: F401
    except ImportError as exc:
        return False, f"pyusb missing: {exc}"
    return True, ""


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".cache" / "numba"))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return env


@pytest.fixture(scope="module")
def umock_results(tmp_path_factory):
    ok, why = _tier_ok()
    require_tier("umockdev", ok, why)
    out = tmp_path_factory.mktemp("umock")
    junit = out / "junit.xml"
    cmd = ["umockdev-wrapper", sys.executable, "-m", "pytest", "-q", "-rA",
           "-p", "no:cacheprovider", "-o", "addopts=", f"--junitxml={junit}",
           "--basetemp", str(out / "tmp"), str(REPO / "tests" / "usb" / "umock_cases.py")]
    r = subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=540)
    log = r.stdout[-8000:] + r.stderr[-4000:]
    if not junit.exists():
        require_tier("umockdev", False, f"the umockdev run produced no report:\n{log}")
    results = {}
    for tc in ET.parse(junit).getroot().iter("testcase"):
        name = tc.get("name")
        bad = tc.find("failure") if tc.find("failure") is not None else tc.find("error")
        skipped = tc.find("skipped")
        if bad is not None:
            results[name] = ("failed", (bad.get("message") or "") + "\n" + (bad.text or ""))
        elif skipped is not None:
            results[name] = ("skipped", skipped.get("message") or "")
        else:
            results[name] = ("passed", "")
    return results, log


@pytest.mark.parametrize("case", CASES)
def test_umockdev_case(umock_results, case):
    results, log = umock_results
    assert case in results, f"case {case} did not run:\n{log}"
    status, msg = results[case]
    if status == "skipped":
        require_tier("umockdev", False, msg)
    assert status == "passed", msg[-4000:]


def test_no_unexpected_umockdev_cases(umock_results):
    results, log = umock_results
    extra = {k: v[0] for k, v in results.items() if k not in CASES}
    assert all(v == "passed" for v in extra.values()), extra


def test_service_on_emulated_usb_camera(tmp_path):
    """``cfsr serve --usb`` against the emulated camera at 40,000 frames/s: frames over the
    WebSocket, figures in /api/status, no replay controls (capability checked), an unplug
    survived with the loss counted exactly as the camera counts it."""
    ok, why = _tier_ok()
    require_tier("umockdev", ok, why)
    dat = write_pattern(tmp_path / "cam.dat", 2000)
    state = tmp_path / "camera-state.json"
    launcher = [
        "umockdev-wrapper", sys.executable, str(REPO / "tests" / "usb" /
                                                "run_service_with_camera.py"),
        "--dat", str(dat), "--paced", "--state-file", str(state),
        "--faults", "9.0:unplug:0.5", "--", "serve",
    ]
    with LiveServer(["--usb", "--data-dir", str(tmp_path / "data")], env=_env(),
                    command=launcher) as s:
        st = s.wait_for(lambda x: x["source"]["state"] == "streaming" and x["output_fps"] > 0
                        and x["input_steps_per_s"] > 0, what="USB streaming")
        assert st["source"]["kind"] == "usb" and st["source"]["capabilities"] == ["camera"]
        assert st["source"]["counters"]["device"]["connected"] is True
        f = ws_frames(s, 3)
        assert f[-1]["image"].shape == (250, 400)
        assert s.get("/api/replay").status_code == 409  # a camera has no replay controls
        assert s.post("/api/replay/seek", json={"position": 5}).status_code == 409
        r = s.post("/api/record", json={"action": "start", "name": "usbtake",
                                         "max_frames": 4096})
        assert r.status_code == 200
        wait_until(lambda: not s.get("/api/record").json().get("recording"), 30,
                   "the recording to stop at max_frames", interval=0.1)
        rec = s.get("/api/record").json()
        assert rec["frames"] == 4096
        # the scheduled unplug (9 s after the camera appeared): the service stays up,
        # reconnects, and counts exactly the frames the camera could not deliver
        st = s.wait_for(lambda x: x["source"]["counters"].get("reconnects", 0) >= 1
                        and x["source"]["state"] == "streaming", timeout=60,
                        what="reconnect after unplug")
        assert s.get("/healthz").status_code == 200
        cam: dict = {}

        def loss_accounted() -> bool:
            nonlocal cam, st
            cam = json.loads(state.read_text())
            st = s.status()
            return cam["expected_loss"] == st["drops"]["usb"] and cam["faults_pending"] == 0

        try:
            wait_until(loss_accounted, 20, "the camera's loss in drops.usb")
        except AssertionError:
            pass  # the asserts below say what differs
        assert "unplug" in cam["events"] and "replug" in cam["events"]
        assert st["drops"]["usb"] == cam["expected_loss"] > 0
        assert st["source"]["counters"]["disconnects"] == 1
        assert ws_frames(s, 2)
        metrics = s.get("/metrics").text
        assert 'cfsr_source_events_total{kind="reconnects"} 1.0' in metrics
    from cfsr.datfile import read_dat

    out = read_dat(tmp_path / "data" / "recordings" / "usbtake.dat")
    assert out.n_frames == 4096 and out.meta["source"]["kind"] == "usb"
