"""The live service's defect correction: the switch in its configuration, the source's own
map (a replay starts corrected), and recordings that keep the map the worker corrects with."""

from __future__ import annotations

import numpy as np
import pytest
from livehelpers import wait_until

from cfsr.api import reconstruct_outputs
from cfsr.config import MethodConfig
from cfsr.datfile import read_dat
from cfsr.defects import DefectMap, GainMap, corrected, map_of
from cfsr.display import to_display
from cfsr.layout import Layout
from cfsr.methods.registry import get_method, resolve_params
from cfsr_live.driver.acquisition import Acquisition
from cfsr_live.replay.device import ReplayDevice
from cfsr_live.replay.pattern import pattern_recording
from cfsr_live.service.config import ConfigChange, LiveConfig, WorkerConfig
from cfsr_live.service.frameslot import FrameSlot
from cfsr_live.service.supervisor import WorkerSupervisor
from cfsr_live.shm.ring import SpikeRing

H, W, N = 24, 32, 6000
GAIN = 0.6


def _given() -> DefectMap:
    hot = np.zeros((H, W), bool)
    dead = np.zeros((H, W), bool)
    hot[5, 7] = dead[12, 20] = True
    g = GainMap(np.linspace(0.8, 1.25, H * W).reshape(H, W), 4000)
    return DefectMap(hot, dead, 4000, "calibration", g)


def test_the_live_config_switches_the_correction_and_shows_it():
    c = LiveConfig.make("tfp")
    assert c.defects is True and c.public()["defects"] is True
    off = c.changed(ConfigChange(defects=False))
    assert off.defects is False and off.public()["defects"] is False
    assert off.changed(ConfigChange(max_fps=10)).defects is False  # kept when not given
    assert off.changed(ConfigChange(defects=True)).defects is True


def test_a_live_recording_keeps_the_workers_map_and_its_replay_starts_corrected(tmp_path):
    from cfsr_live.service.recorder import Recorder

    lay = Layout(W, H)
    given = _given()
    ring = SpikeRing.create(8, 64, lay.frame_bytes, directory=tmp_path)
    rng = np.random.default_rng(0)
    try:
        for name, found in (("kept", given.to_dict()), ("other", {**given.to_dict(), "width": 8})):
            rec = Recorder(ring, tmp_path / f"{name}.dat", lay, rate_hz=40_000.0,
                           defects=lambda found=found: found)
            k = 0

            def fed(rec=rec) -> bool:
                nonlocal k
                ring.write(k * 64, rng.integers(0, 256, (64, lay.frame_bytes), np.uint8))
                k += 1
                return rec.frames >= 128

            wait_until(fed, 30, "the recorder's first blocks", interval=0.01)
            st = rec.stop()
            got = read_dat(tmp_path / f"{name}.dat")
            if name == "kept":
                assert st.error is None, st.error
                m = map_of(got)
                assert np.array_equal(m.hot, given.hot) and np.array_equal(m.dead, given.dead)
                assert np.abs(m.gain.gain - given.gain.gain).max() < 1e-4
                # a replay of it reads corrected spikes: the dead pixel takes a neighbour's
                raw, fixed = got.frames(0, 128), corrected(got).frames(0, 128)
                side = [raw[:, 12 + dy, 20 + dx] for dy, dx in ((0, -1), (0, 1), (-1, 0), (1, 0))]
                assert any(np.array_equal(fixed[:, 12, 20], d) for d in side)  # a donor's
                assert not np.array_equal(fixed[:, 12, 20], raw[:, 12, 20])
            else:  # a map of another geometry is not kept, and the sidecar says why
                assert map_of(got) is None
                assert "defect map not kept" in got.meta["record_error"]
    finally:
        ring.close()


@pytest.fixture(scope="module")
def rec():
    return pattern_recording(N, height=H, width=W, speed_px=0.004)


def _cfg(**kw) -> WorkerConfig:
    return WorkerConfig(MethodConfig("tfp"), gain=GAIN, max_fps=200.0, deterministic=True, **kw)


@pytest.fixture(scope="module")
def pipeline(rec):
    dev = ReplayDevice(rec, mode="unpaced", loop=True, block_frames=64)
    dev.open()
    ring = SpikeRing.create(8, 64, rec.layout.frame_bytes, blocking=True)
    slot = FrameSlot.create(max_pixels=H * W)
    sup = WorkerSupervisor(slot, _cfg(defect_map=_given().to_dict()))
    sup.start(str(ring.path), rec.layout)
    assert sup.ready.wait(120), "worker did not start"
    acq = Acquisition(dev, ring)
    acq.start()
    yield sup, slot
    acq.stop()
    sup.stop()
    ring.close()
    slot.close()


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal but for a pixel's rounding (the pool's rate and this process's may differ in the
    last bit, and the gain moves which pixels sit on a half level); a missed correction
    differs by tens of levels over hundreds of pixels."""
    d = np.abs(a.astype(int) - b)
    return int(d.max()) <= 1 and int((d > 0).sum()) <= 3


def _shown(sup, slot, want, before_switch=None, n: int = 3) -> None:
    """``n`` frames shown by the worker equal the offline frames of ``want`` (a recording,
    corrected or not) at their steps (windows across the replay's loop seam skipped); frames
    of ``before_switch`` (the previous configuration, still in flight) may come first."""
    m = get_method("tfp")
    before, after = m.window(resolve_params(m))
    seen, seq = [], None

    def shown(source, t: int) -> np.ndarray:
        return to_display(reconstruct_outputs(source, "tfp", [t])[0].rate, GAIN)

    def broken() -> tuple[int, int]:  # a torn read or a gap clips the worker's next windows
        st = sup.stats()
        return st.gaps, st.ring_torn

    lost = broken()

    def enough() -> bool:
        nonlocal seq, lost
        f = slot.read(since=seq)
        if f is None:
            return False
        seq, t = f.seq, f.step % N
        if before <= t < N - after:
            if _close(f.image, shown(want, t)):
                seen.append(t)
            elif broken() != lost:
                lost = broken()  # not comparable with the file: its window was cut
            else:
                d = np.abs(f.image.astype(int) - shown(want, t))
                assert not seen and before_switch is not None, (
                    f"step {f.step} differs: {int(d.max())} levels at {int((d > 0).sum())} "
                    f"pixels, seen {seen}, gaps/torn {lost}")
                assert _close(f.image, shown(before_switch, t)), f"step {f.step}"
        return len(seen) >= n

    wait_until(enough, 120, lambda: f"{n} frames to compare (got {len(seen)})", interval=0.002)


def test_the_worker_corrects_with_the_sources_map_reports_it_and_can_be_switched_off(
        rec, pipeline):
    sup, slot = pipeline
    given = _given()
    fixed = corrected(rec, given)
    _shown(sup, slot, fixed)
    wait_until(lambda: sup.defect_map is not None, 30, "the worker's map")
    assert sup.defect_map == given.to_dict()
    d = sup.status(40_000.0).status.defects
    assert (d.state, d.hot, d.dead, d.gain) == ("given", 1, 1, True)
    v = sup.configure(_cfg(defect_map=given.to_dict(), defects=False))
    assert sup.wait_config(v, 120) == ("applied", None)
    _shown(sup, slot, rec, before_switch=fixed)
    wait_until(lambda: sup.status(40_000.0).status.defects.state == "off", 30, "state off")


def test_the_service_replays_a_recordings_map_switches_it_and_records_it(tmp_path):
    """End to end: a replayed recording whose sidecar holds a calibration is corrected from
    its first frame (status ``given``, with its gain); ``PUT /api/config {"defects": false}``
    turns the correction off and the status says so; a recording made meanwhile keeps the
    map in its sidecar."""
    from fastapi.testclient import TestClient

    from cfsr.datfile import write_dat
    from cfsr_live.service.app import create_app
    from cfsr_live.service.settings import Settings, SourceSpec

    path = tmp_path / "cal.dat"
    given = _given()
    write_dat(path, pattern_recording(3000, height=H, width=W),
              meta={"defects": given.to_dict()})
    app = create_app(Settings(data_dir=tmp_path, source=SourceSpec(kind="replay", path=path)))
    with TestClient(app, base_url="http://127.0.0.1:8000") as client:
        rt = app.state.runtime
        assert rt.worker.ready.wait(120), "worker did not start"

        def defects() -> dict:
            return client.get("/api/status").json()["worker"]["defects"]

        wait_until(lambda: defects()["state"] == "given", 60, lambda: f"given ({defects()})")
        assert (defects()["hot"], defects()["dead"], defects()["gain"]) == (1, 1, True)
        assert client.get("/api/config").json()["defects"] is True
        r = client.post("/api/record", json={"action": "start", "name": "kept"})
        assert r.status_code == 200, r.text
        wait_until(lambda: client.get("/api/record").json()["frames"] > 0, 60, "frames")
        r = client.put("/api/config", json={"defects": False})
        assert r.status_code == 200 and r.json()["defects"] is False, r.text
        wait_until(lambda: defects()["state"] == "off", 60, lambda: f"off ({defects()})")
        assert client.get("/api/config").json()["defects"] is False
        r = client.post("/api/record", json={"action": "stop"})
        assert r.status_code == 200, r.text
        m = map_of(read_dat(tmp_path / "recordings" / "kept.dat"))
        assert m is not None and np.array_equal(m.hot, given.hot) and m.gain is not None
