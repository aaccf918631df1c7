"""Bad configuration requests never take the service down (issue 12).

* every method parameter has a documented range, checked once at the boundary
  (:meth:`cfsr.methods.registry.Param.check`), with the window-like ones bounded by what the
  reconstructor's ring may hold;
* NaN and Infinity are refused everywhere (a 422 naming them, never a 500);
* ``PUT /api/config`` answers with the worker's verdict: a configuration the worker cannot
  apply is a 422, the stored configuration stays, and frames keep coming.

The service tests run the real app (``create_app`` + TestClient) with its real worker process
on a small replayed recording.
"""

from __future__ import annotations

import math
import time

import pytest
from livehelpers import wait_until

from cfsr.methods import get_method, methods, resolve_params
from cfsr.methods.registry import MAX_UNPACKED_STEPS, MAX_WINDOW_STEPS, Param


# -- the parameter ranges --------------------------------------------------------------------
def test_tfstp_largest_warmup_fits_its_window_limit():
    # the state may start a grid step before t - warmup, so warmup's range leaves room for it
    m = get_method("tfstp")
    top = m.params["warmup"].maximum
    p = resolve_params(m, {"warmup": top})  # a method's window takes resolved parameters
    assert p["warmup"] == top
    assert sum(m.window(p)) <= m.max_span


def test_every_parameter_has_a_documented_range():
    for name, d in methods().items():
        m = get_method(name)
        assert d["max_window_steps"] == m.max_span
        # methods that unpack their window (TFSTP also when it has no state to continue)
        unpacks = m.compute_packed is None or name == "tfstp"
        assert m.max_span == (MAX_UNPACKED_STEPS if unpacks else MAX_WINDOW_STEPS)
        for key, p in m.params.items():
            info = d["params"][key]
            if isinstance(p.default, bool):
                assert info["range"] == "true|false"
            elif isinstance(p.default, str):
                assert p.choices and p.default in p.choices and info["choices"]
            else:
                assert p.minimum is not None and p.maximum is not None, f"{name}.{key}"
                assert p.minimum <= p.default <= p.maximum, f"{name}.{key}"
                assert (info["minimum"], info["maximum"]) == (p.minimum, p.maximum)
                assert info["range"] == p.range_text and ".." in p.range_text
                if p.unit == "steps" and key not in ("D", "F"):  # window-like (not tau)
                    assert p.maximum <= m.max_span, f"{name}.{key} reaches past the ring"


def test_the_live_tier_is_the_configs_own_field():
    """CFSR's live tier (auto, full, fast) is the live configuration's field, the one place
    ``auto`` lives; the method's ``quality`` parameter follows it, and a tier given among the
    parameters is refused naming the field (API, settings, command line)."""
    import argparse

    from cfsr_live.service.commands import serve
    from cfsr_live.service.config import ConfigChange, LiveConfig

    c = LiveConfig.make("cfsr")
    assert c.quality == "auto" and c.method.params["quality"] == "full"  # auto runs from full
    assert c.public()["quality"] == "auto" and "quality" not in c.public()["params"]
    fast = c.changed(ConfigChange(quality="fast"))
    assert fast.quality == "fast" and fast.method.params["quality"] == "fast"
    assert fast.changed(ConfigChange(max_fps=10)).method.params["quality"] == "fast"  # kept
    tfp = fast.changed(ConfigChange(method="tfp"))
    assert tfp.public()["quality"] is None  # a method without tiers
    assert tfp.changed(ConfigChange(method="cfsr")).quality == "auto"  # a new method: auto
    assert LiveConfig.make("cfsr", quality="fast").method.params["quality"] == "fast"
    for q in ("auto", "fast"):
        with pytest.raises(ValueError, match="configuration's own field 'quality'"):
            ConfigChange(params={"quality": q})
        with pytest.raises(ValueError, match="configuration's own field 'quality'"):
            LiveConfig.make("cfsr", {"quality": q})
    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    assert serve.build_settings(p.parse_args([])).quality == "auto"
    assert serve.build_settings(p.parse_args(["--quality", "fast"])).quality == "fast"
    with pytest.raises(SystemExit):
        p.parse_args(["--quality", "best"])


def test_method_listing_shows_ranges():
    tfp = methods()["tfp"]["params"]
    assert tfp["window"]["range"] == f"1..{MAX_WINDOW_STEPS} steps"
    assert tfp["mode"]["range"] == "trailing|centred"
    assert methods()["tfi"]["params"]["max_isi"]["maximum"] == MAX_WINDOW_STEPS // 2


def test_a_parameter_without_bounds_cannot_be_declared():
    with pytest.raises(ValueError, match="minimum and maximum"):
        Param(160, "steps", "window length")
    with pytest.raises(ValueError, match="outside"):
        Param(5, "steps", "x", minimum=10, maximum=20)
    with pytest.raises(ValueError, match="choices"):
        Param("a", "", "mode")


@pytest.mark.parametrize(
    "method, params, words",
    [
        ("tfp", {"window": 1_000_000_000}, ["window", "1000000000", "1..40000 steps"]),
        ("tfp", {"window": 100_000}, ["window", "100000", "1..40000"]),
        ("tfp", {"window": 0}, ["window", "1..40000"]),
        ("tfi", {"max_isi": 30_000}, ["max_isi", "30000", "1..20000"]),
        ("csr", {"T": 10**9}, ["T=", "2..20000"]),
        ("tfstp", {"warmup": 100_000}, ["warmup", "1..3200"]),
        ("cfsr", {"mog_ratio": 1.5}, ["mog_ratio", "1.5", "0..1"]),
        ("cfsr", {"tfp_mode": "sideways"}, ["tfp_mode", "sideways", "trailing"]),
        ("cfsr", {"adaptive": 2}, ["adaptive", "true|false"]),
        ("tfp", {"window": True}, ["window", "expected int"]),
        ("tfp", {"window": 10**400}, ["window", "expected int"]),
    ],
)
def test_out_of_range_names_parameter_value_and_range(method, params, words):
    with pytest.raises(ValueError) as exc:
        resolve_params(get_method(method), params)
    for w in words:
        assert w in str(exc.value), (w, str(exc.value))


@pytest.mark.parametrize(
    "method, key, value",
    [
        ("cfsr", "phi", math.nan),
        ("cfsr", "mog_ratio", math.nan),
        ("tfstp", "u0", math.nan),
        ("cfsr", "phi0", math.inf),
        ("tfp", "window", math.nan),
        ("tfp", "window", -math.inf),
        ("tfp", "window", "NaN"),
        ("snm", "motion_sigma", "inf"),
    ],
)
def test_non_finite_values_are_refused(method, key, value):
    with pytest.raises(ValueError, match=f"{key}=.*finite"):
        resolve_params(get_method(method), {key: value})


def test_parameters_in_range_can_still_ask_for_too_long_a_window():
    """CFSR's history reaches mog_frames * mog_stride steps back: each in range, the product
    past the ring."""
    with pytest.raises(ValueError, match=r"at most 40000 steps.*mog_frames=200, mog_stride=300"):
        resolve_params(get_method("cfsr"), {"mog_frames": 200, "mog_stride": 300})
    # one-sided objects read 248 steps after t (PatchMatch's reach), the still pixels
    # still_reach (380); two-sided ones (the default) also read the mirrored history:
    # (frames - 1) * stride + mog_window - 1 after t
    with pytest.raises(ValueError, match=r"40298 steps before t and 248 after"):
        resolve_params(get_method("cfsr"), {"mog_frames": 4, "mog_stride": 13_333,
                                            "mog_sides": "past", "still_reach": 0})
    with pytest.raises(ValueError, match=r"40298 steps before t and 380 after"):
        resolve_params(get_method("cfsr"),
                       {"mog_frames": 4, "mog_stride": 13_333, "mog_sides": "past"})
    with pytest.raises(ValueError, match=r"40298 steps before t and 383 after"):  # 5*64 + 63
        resolve_params(get_method("cfsr"), {"mog_frames": 4, "mog_stride": 13_333,
                                            "mog_future_frames": 6, "mog_future_stride": 64})
    with pytest.raises(ValueError, match=r"40298 steps before t and 463 after"):  # 2*200 + 63
        resolve_params(get_method("cfsr"), {"mog_frames": 4, "mog_stride": 13_333,
                                            "mog_future_frames": 3, "mog_future_stride": 200})
    # elsewhere any one window-like value at its maximum fits (CFSR adds several reaches up:
    # PatchMatch's pm_step * pm_count beyond max_isi, the MOG history before T)
    for name in ("tfp", "tfi", "csr", "tfa", "tfstp", "snm"):
        m = get_method(name)
        for key, p in m.params.items():
            if p.unit == "steps" and key not in ("D", "F"):
                before, after = m.window(resolve_params(m, {key: p.maximum}))
                assert before + after <= m.max_span, (name, key)
    csr = get_method("csr")
    before, after = csr.window(resolve_params(csr, {"T": 20_000, "max_isi": 20_000}))
    assert before + after == MAX_WINDOW_STEPS  # each side at its maximum: still in


def test_defaults_and_presets_are_unchanged_and_valid():
    for name in methods():
        m = get_method(name)
        assert resolve_params(m) == {k: p.default for k, p in m.params.items()}
        for preset in m.presets:
            before, after = m.window(resolve_params(m, None, preset))
            assert before + after <= m.max_span
    assert resolve_params(get_method("tfp"), {"window": "160"})["window"] == 160
    assert resolve_params(get_method("cfsr"), {"adaptive": "off"})["adaptive"] is False


# -- the service ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """The real app on a replayed pattern recording, with its worker process running."""
    from fastapi.testclient import TestClient

    from cfsr.datfile import write_dat
    from cfsr_live.replay.pattern import pattern_recording
    from cfsr_live.service.app import create_app
    from cfsr_live.service.settings import Settings, SourceSpec

    data = tmp_path_factory.mktemp("cfgsvc")
    path = data / "a.dat"
    write_dat(path, pattern_recording(3000, height=48, width=64))
    settings = Settings(data_dir=data, source=SourceSpec(kind="replay", path=path))
    app = create_app(settings)
    # Host 127.0.0.1: the service answers loopback names only
    with TestClient(app, base_url="http://127.0.0.1:8000") as client:
        rt = app.state.runtime
        assert rt.worker.ready.wait(120), "worker did not start"
        _frame_after(rt, time.monotonic())  # the pipeline runs
        yield client, rt


def _frame_after(rt, since: float, method: str | None = None, timeout: float = 120.0):
    """The first frame published after monotonic time ``since`` (by ``method``), or fail."""
    seq = None

    def newer():
        nonlocal seq
        f = rt.slot.read(since=seq)
        if f is None:
            return None
        seq = f.seq
        return f if f.t_arrival > since and (method is None or f.method == method) else None

    return wait_until(newer, timeout, f"a {method or ''} frame: the worker stopped publishing",
                      interval=0.01)


def test_out_of_range_config_is_422_and_changes_nothing(service):
    client, rt = service
    before = client.get("/api/config").json()
    r = client.put("/api/config", json={"params": {"window": 1_000_000_000}})
    assert r.status_code == 422
    assert "window" in r.text and "1000000000" in r.text and "1..40000" in r.text
    assert client.get("/api/config").json() == before
    # the service goes on: a valid change is applied by the worker and frames follow
    t0 = time.monotonic()
    r = client.put("/api/config", json={"method": "tfi", "params": {}})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["state"] == "applied" and body["method"] == "tfi"
    assert rt.worker.applied_version == body["version"]
    _frame_after(rt, t0, method="tfi")
    r = client.put("/api/config", json={"method": "tfp", "params": {"window": 160}})
    assert r.status_code == 200 and r.json()["params"]["window"] == 160
    _frame_after(rt, time.monotonic(), method="tfp")


def test_tier_among_the_parameters_is_422_naming_its_field(service):
    client, rt = service
    before = client.get("/api/config").json()
    assert before["quality"] is None  # the method in force (tfp) has no tiers
    for q in ("auto", "fast"):
        r = client.put("/api/config", json={"method": "cfsr", "params": {"quality": q}})
        assert r.status_code == 422 and "own field 'quality'" in r.text, r.text
    r = client.put("/api/config", json={"quality": "best"})  # the field takes tiers only
    assert r.status_code == 422 and "quality" in r.text
    assert client.get("/api/config").json() == before


def test_config_the_worker_rejects_is_422_and_not_stored(service, monkeypatch):
    """The web process accepts it but the worker cannot apply it (as when its buffer cannot
    be allocated): the caller gets the worker's reason, the stored config and the running
    reconstruction stay."""
    import importlib

    # (``cfsr.methods`` is also the name of a function: import the module by its path)
    registry = importlib.import_module("cfsr.methods.registry")
    client, rt = service
    before = client.get("/api/config").json()
    applied = rt.worker.applied_version

    def lenient(method, params=None, preset=None):  # the web side lets it through
        return {**{k: p.default for k, p in method.params.items()}, **(params or {})}

    monkeypatch.setattr(registry, "resolve_params", lenient)
    # and the router's strict check (Param.check) with it
    monkeypatch.setattr(registry.Param, "check", lambda self, value, *a, **k: value)
    r = client.put("/api/config", json={"params": {"window": 1_000_000_000}})
    monkeypatch.undo()
    assert r.status_code == 422, r.text
    assert "rejected by the worker" in r.text and "window" in r.text
    assert client.get("/api/config").json() == before
    assert rt.worker.applied_version == applied
    assert rt.worker.config.method.params == before["params"]  # a restart would use the good one
    st = client.get("/api/status").json()["worker"]
    assert st["config_version"] == st["applied_version"] == applied
    assert any("window" in e["message"] for e in st["last_errors"])
    _frame_after(rt, time.monotonic(), method=before["method"])


def test_slow_worker_answer_is_202_pending_then_applied(service, monkeypatch):
    client, rt = service
    monkeypatch.setattr(rt, "config_ack_timeout_s", 0.0)
    r = client.put("/api/config", json={"method": "tfp", "params": {"window": 120}})
    assert r.status_code == 202, r.text
    body = r.json()
    assert body["state"] == "pending" and body["params"]["window"] == 120
    wait_until(lambda: rt.worker.applied_version >= body["version"], 30,
               "the worker's late answer", interval=0.02)
    assert rt.worker.applied_version == body["version"]
    assert client.get("/api/config").json()["params"]["window"] == 120
    monkeypatch.undo()
    assert client.put("/api/config", json={"params": {"window": 160}}).status_code == 200


@pytest.mark.parametrize(
    "path, body",
    [
        ("/api/config", '{"max_fps": NaN}'),
        ("/api/config", '{"max_fps": Infinity}'),
        ("/api/config", '{"max_fps": 1e999}'),
        ("/api/config", '{"display": {"gain_mode": "fixed", "gain": NaN}}'),
        ("/api/config", '{"display": NaN}'),
        ("/api/config", '{"params": {"window": NaN}}'),
        ("/api/config", '{"params": {"phi": NaN}, "method": "cfsr"}'),
        ("/api/config", '{"params": {"window": -Infinity}}'),
        ("/api/config", "NaN"),
    ],
)
def test_non_finite_json_is_422_not_500(service, path, body):
    client, rt = service
    before = client.get("/api/config").json()
    r = client.put(path, content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422, (r.status_code, r.text)
    assert client.get("/api/config").json() == before


@pytest.mark.parametrize(
    "method, path, body",
    [
        ("put", "/api/replay", '{"speed": NaN}'),
        ("put", "/api/replay", '{"speed": Infinity}'),
        ("post", "/api/replay/seek", '{"seconds": NaN}'),
        ("post", "/api/replay/seek", '{"seconds": Infinity}'),
        ("post", "/api/replay/seek", '{"seconds": 1e308}'),
        ("post", "/api/replay/seek", '{"position": 1e999}'),
    ],
)
def test_non_finite_replay_controls_are_422(service, method, path, body):
    client, rt = service
    r = client.request(method, path, content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422, (r.status_code, r.text)
    assert client.get("/api/replay").json()["speed"] == 1.0


def test_model_level_checks_without_the_json_guard():
    """The models refuse non-finite floats themselves (for callers that build them from
    Python values) and their error can still be rendered as JSON."""
    import json

    from pydantic import ValidationError

    from cfsr_live.service.models import ConfigUpdate, DisplayConfig, ReplayUpdate, SeekRequest

    for model, field in [
        (ConfigUpdate, "max_fps"),
        (DisplayConfig, "gain"),
        (ReplayUpdate, "speed"),
        (SeekRequest, "seconds"),
    ]:
        for bad in (math.nan, math.inf, -math.inf):
            with pytest.raises(ValidationError) as exc:
                model(**{field: bad})
            json.dumps(exc.value.errors(include_url=False), allow_nan=False)
