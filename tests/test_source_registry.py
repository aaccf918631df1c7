"""The source registry: kinds of source found through the ``cfsr.sources`` entry-point group.

A third party's camera is simulated by a plugin module written to a temporary folder and an
entry point naming it (what ``pip install`` of a camera package would add): it must show in
``GET /api/sources``, open through ``PUT /api/source``, report its own loss counter in the
status' drops, and add its flag to ``cfsr serve`` -- with no file of the service changed.
"""

from __future__ import annotations

import argparse
import logging
import sys
import textwrap
import time
from importlib.metadata import EntryPoint, entry_points

import pytest
from livehelpers import wait_until

from cfsr_live.service import sources

PLUGIN = '''
"""A third party's camera kind (test plugin)."""
from dataclasses import asdict, dataclass

from cfsr_live.driver.source import SourceCounters
from cfsr_live.replay.device import ReplayDevice
from cfsr_live.replay.pattern import pattern_recording
from cfsr_live.service.catalog import CatalogEntry
from cfsr_live.service.settings import SourceSpec
from cfsr_live.service.sources import SourceKind

SERIALS = ("A1", "B2")


@dataclass(frozen=True)
class FakeCamCounters(SourceCounters):
    """The counters of every source and one of this camera's own."""

    link_resets: int = 0


class FakeCamera(ReplayDevice):
    """A camera whose link lost 7 frames over 2 resets of its link."""

    def counters(self):
        base = {**asdict(super().counters()), "lost_frames": 7, "replay_behind_frames": None}
        return FakeCamCounters(**base, link_resets=2)


class FakeCamKind(SourceKind):
    name = "fakecam"
    summary = "a third party's camera"
    order = 25

    def add_select_argument(self, select, command):
        select.add_argument("--fakecam", metavar="SERIAL", help="a fake camera by serial")

    def spec_from_args(self, args):
        serial = getattr(args, "fakecam", None)
        return SourceSpec(kind=self.name, options={"serial": serial}) if serial else None

    def entries(self, catalog):
        return [CatalogEntry(id=f"fakecam:{s}", kind=self.name, name=f"fake camera {s}",
                             width=64, height=48) for s in SERIALS]

    def spec_for(self, catalog, entry):
        return SourceSpec(kind=self.name, options={"serial": entry.id.split(":", 1)[1]})

    def spec_id(self, spec):
        return f"fakecam:{spec.options['serial']}"

    def open(self, spec, options):
        if spec.options["serial"] not in SERIALS:
            raise ValueError(f"no camera with serial {spec.options['serial']}")
        rec = pattern_recording(2000, height=48, width=64)
        return FakeCamera(rec, kind="fakecam", name="fake camera " + spec.options["serial"],
                          **options.given("speed", "loop", "mode", "block_frames"))
'''


def _registry_with(monkeypatch, extra: EntryPoint) -> None:
    """The registry as it loads with the installed kinds and ``extra`` (restored after)."""
    installed = entry_points(group=sources.ENTRY_POINT_GROUP)
    monkeypatch.setattr(sources, "entry_points", lambda group: [*installed, extra])
    monkeypatch.setattr(sources, "_KINDS", {})
    monkeypatch.setattr(sources, "_loaded", False)


@pytest.fixture
def fakecam(tmp_path, monkeypatch):
    """The registry as it is with a camera package installed beside cfsr (restored after)."""
    (tmp_path / "cfsr_fakecam_plugin.py").write_text(textwrap.dedent(PLUGIN))
    monkeypatch.syspath_prepend(str(tmp_path))
    _registry_with(monkeypatch, EntryPoint(name="fakecam",
                                           value="cfsr_fakecam_plugin:FakeCamKind",
                                           group=sources.ENTRY_POINT_GROUP))
    yield
    sys.modules.pop("cfsr_fakecam_plugin", None)


def test_built_in_kinds_are_entry_points():
    # the installed distribution declares them (pyproject.toml); nothing registers them by hand
    names = {ep.name for ep in entry_points(group=sources.ENTRY_POINT_GROUP)}
    assert {"demo", "replay", "usb", "sim"} <= names
    assert [k.name for k in sources.kinds()][:4] == ["demo", "replay", "usb", "sim"]
    with pytest.raises(ValueError, match="unknown source kind 'nope'.*demo"):
        sources.get("nope")


def test_each_kind_opens_a_source_named_as_the_registry_names_the_kind(tmp_path, monkeypatch):
    """One vocabulary of kinds: the source a built-in kind opens says the kind's name in its
    ``info.kind``, which the status and a recording's sidecar show."""
    from cfsr.datfile import write_dat
    from cfsr_live.replay.pattern import pattern_recording
    from cfsr_live.service import demo
    from cfsr_live.service.settings import SourceSpec

    dat = tmp_path / "a.dat"
    write_dat(dat, pattern_recording(300, height=16, width=32))
    monkeypatch.setattr(demo, "ensure_demo", lambda steps, say: dat)
    specs = {"demo": SourceSpec(kind="demo"), "replay": SourceSpec(kind="replay", path=dat),
             "sim": SourceSpec(kind="sim", options={"scene": "pattern"}),
             "usb": SourceSpec(kind="usb")}  # made, not opened: no camera here
    for name, spec in specs.items():
        assert sources.get(name).open(spec, sources.OpenOptions()).info.kind == name


def test_source_counters_are_one_typed_record(tmp_path):
    """A source's counters are a frozen record: the loss fields a source lacks are None and
    left out of the status's dict; a snapshot does not change as the source goes on."""
    import dataclasses

    from cfsr_live.driver.source import SourceCounters
    from cfsr_live.driver.usb import UsbCameraSource, UsbCounters
    from cfsr_live.replay.device import ReplayDevice
    from cfsr_live.replay.pattern import pattern_recording

    dev = ReplayDevice(pattern_recording(300, height=16, width=32), mode="unpaced",
                       block_frames=100)
    dev.open()
    before = dev.counters()
    assert dev.read_block() is not None
    after = dev.counters()
    dev.close()
    assert isinstance(after, SourceCounters) and after.lost_frames is None
    assert (before.frames_delivered, after.frames_delivered) == (0, 100)
    assert after.as_dict() == {"frames_delivered": 100, "replay_behind_frames": 0, "loops": 0}
    with pytest.raises(dataclasses.FrozenInstanceError):
        after.frames_delivered = 1  # type: ignore[misc]
    cam = UsbCameraSource().counters()  # a camera has a link: its loss is counted from 0
    assert isinstance(cam, UsbCounters) and cam.lost_frames == 0
    assert cam.replay_behind_frames is None
    assert {"lost_frames", "timeouts", "reconnects"} <= cam.as_dict().keys()


def test_register_twice_is_an_error(fakecam):
    with pytest.raises(ValueError, match="registered twice"):
        sources.register(type(sources.get("fakecam")))
    with pytest.raises(TypeError):
        sources.register(object)


def test_broken_plugin_is_skipped_and_said(monkeypatch, caplog):
    _registry_with(monkeypatch, EntryPoint(name="broken", value="cfsr_no_such_module_xyz:Kind",
                                           group=sources.ENTRY_POINT_GROUP))
    with caplog.at_level(logging.WARNING, logger="cfsr.sources"):
        names = [k.name for k in sources.kinds()]
    assert "broken" not in names and "demo" in names
    assert "cfsr_no_such_module_xyz" in caplog.text


def test_plugin_kind_adds_its_flag_to_serve_and_record(fakecam):
    from cfsr_live.service.commands import record, serve

    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    settings = serve.build_settings(p.parse_args(["--fakecam", "A1"]))
    assert settings.source.kind == "fakecam" and settings.source.id == "fakecam:A1"
    assert serve.build_settings(p.parse_args([])).source.kind == "demo"
    with pytest.raises(SystemExit):  # one source per command line
        p.parse_args(["--fakecam", "A1", "--sim", "pattern"])
    r = argparse.ArgumentParser()
    record.add_arguments(r)
    assert r.parse_args(["--fakecam", "B2", "-o", "x.dat", "--frames", "1"]).fakecam == "B2"


def test_plugin_kind_listed_opened_and_counted_by_the_service(fakecam, tmp_path):
    from fastapi.testclient import TestClient

    from cfsr.datfile import write_dat
    from cfsr_live.replay.pattern import pattern_recording
    from cfsr_live.service.app import create_app
    from cfsr_live.service.settings import Settings, SourceSpec

    data = tmp_path / "data"
    data.mkdir()
    write_dat(data / "a.dat", pattern_recording(1000, height=48, width=64))
    settings = Settings(data_dir=data, source=SourceSpec(kind="replay", path=data / "a.dat"),
                        workers=1)
    app = create_app(settings)
    with TestClient(app, base_url="http://127.0.0.1:8000") as client:
        rt = app.state.runtime
        items = client.get("/api/sources").json()
        ids = [s["id"] for s in items]
        # listed in its kind's order: after the recordings and the USB camera, before the sims
        assert ids.index("usb") < ids.index("fakecam:A1") < ids.index("fakecam:B2") \
            < ids.index("sim:pattern")
        cam = next(s for s in items if s["id"] == "fakecam:A1")
        assert cam["kind"] == "fakecam" and cam["width"] == 64 and not cam["current"]
        assert client.put("/api/source", json={"id": "fakecam:C3"}).status_code == 404

        r = client.put("/api/source", json={"id": "fakecam:A1"})
        assert r.status_code == 200, r.text
        assert r.json()["kind"] == "fakecam" and r.json()["name"] == "fake camera A1"
        st = client.get("/api/status").json()
        assert st["source"]["id"] == "fakecam:A1"
        # its counters' link loss is the status page's, and its own field is shown too
        assert st["source"]["counters"]["link_resets"] == 2 and st["drops"]["usb"] == 7
        assert "replay_behind_frames" not in st["source"]["counters"]  # a camera is not paced
        assert next(s for s in client.get("/api/sources").json()
                    if s["id"] == "fakecam:A1")["current"]
        # frames flow from it through the worker
        since = time.monotonic()
        wait_until(lambda: (f := rt.slot.read()) is not None and f.t_arrival > since
                   and f.image.shape == (48, 64), 120, "a frame from the fake camera",
                   interval=0.05)
        # and back to a recording: a built-in kind's source reports no link loss
        r = client.put("/api/source", json={"id": "file:a.dat"})
        assert r.status_code == 200, r.text
        assert client.get("/api/status").json()["source"]["kind"] == "replay"


def test_plugin_kind_records(fakecam, tmp_path, capsys):
    from cfsr.datfile import read_dat, read_sidecar
    from cfsr_live.service.commands import record

    p = argparse.ArgumentParser()
    record.add_arguments(p)
    out = tmp_path / "cam.dat"
    assert record.run(p.parse_args(["--fakecam", "B2", "--frames", "300", "-o", str(out)])) == 0
    assert read_dat(out).shape == (300, 48, 64)
    assert read_sidecar(out)["source"]["kind"] == "fakecam"
    assert "from fake camera B2" in capsys.readouterr().out
