"""``cfsr bench`` smoke tests (the README's --quick form). No timing is asserted: the figures
are ratios a person reads; here we check they are produced, finite and well-formed."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cfsr.bench import format_rows, pareto_front
from cfsr.cli import main


def test_pareto_front():
    rows = [
        {"ms_per_frame": 1.0, "psnr_all": 20.0},
        {"ms_per_frame": 2.0, "psnr_all": 19.0},  # dominated
        {"ms_per_frame": 3.0, "psnr_all": 25.0},
        {"ms_per_frame": 4.0, "psnr_all": None},
    ]
    assert [r["ms_per_frame"] for r in pareto_front(rows)] == [1.0, 3.0]
    assert "-" in format_rows(rows, [("psnr_all", "PSNR", ".1f")])


@pytest.mark.slow
def test_bench_quick_accuracy(tmp_path, capsys):
    assert main(["bench", "--quick", "--no-data", "-q", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "accuracy.json").read_text())
    names = {r["name"] for r in res["rows"]}
    assert {"tfi", "tfp", "csr", "cfsr"} <= names
    for r in res["rows"]:
        assert math.isfinite(r["psnr_all"]) and r["ms_per_frame"] > 0
    assert (tmp_path / "pareto.png").stat().st_size > 10_000
    out = capsys.readouterr().out
    assert "PSNR all" in out and "pareto.png" in out


def test_bench_without_matplotlib_skips_the_plot(tmp_path, capsys, monkeypatch):
    """No cfsr[bench]: the run still gives its tables and JSON, and says in one line that the
    plot was skipped and what to install (it does not refuse to start)."""
    import cfsr.plots

    monkeypatch.setattr(cfsr.plots, "have_matplotlib", lambda: False)
    args = ["bench", "--quick", "--no-data", "-q", "--methods", "tfp", "--scenes", "static",
            "--steps", "400", "--out", str(tmp_path)]
    assert main(args) == 0
    out = capsys.readouterr().out
    skipped = [ln for ln in out.splitlines() if "plot skipped" in ln]
    assert len(skipped) == 1 and "cfsr[bench]" in skipped[0]
    assert (tmp_path / "accuracy.json").exists() and not (tmp_path / "pareto.png").exists()


def test_plot_colours_are_fixed_per_method(tmp_path):
    """A method keeps its colour across plots and variants; an unknown name keeps one too."""
    pytest.importorskip("matplotlib", reason="the plots need cfsr[bench]")
    from PIL import Image

    from cfsr.plots import METHOD_COLOURS, method_colour, plot_metric_bars, plot_pareto

    assert method_colour("cfsr:fast") == method_colour("cfsr") == METHOD_COLOURS["cfsr"]
    assert len(set(METHOD_COLOURS.values())) == len(METHOD_COLOURS)
    assert method_colour("newmethod") == method_colour("newmethod:x=1")
    rows = [
        {"method": m, "name": m.partition(":")[0], "scene": sc, "ms_per_frame": ms,
         "psnr_all": db}
        for sc in ("disk", "a scene with a long name")
        for m, ms, db in (("tfp", 1.0, 25.0), ("cfsr", 40.0, 31.0), ("cfsr:fast", 20.0, 30.0),
                          ("csr", 5.0, 29.0))
    ]
    png = plot_pareto(rows, str(tmp_path / "p.png"))
    bars = plot_metric_bars(rows, str(tmp_path / "b.png"), methods=["tfp", "csr", "cfsr"])
    for path in (png, bars):
        with Image.open(path) as im:
            rgb = np.asarray(im.convert("RGB"))
        # the method's own colour is in the picture: no colour map re-assigned it
        want = np.array([int(METHOD_COLOURS["cfsr"][i:i + 2], 16) for i in (1, 3, 5)])
        assert (np.abs(rgb.astype(int) - want).sum(axis=2) < 6).any(), path


@pytest.fixture
def few_timings(monkeypatch):
    """Every timing of the benchmark at its least: one warm-up and one timed call (what a
    figure is made of; how long each runs is the benchmark's own concern, not the suite's)."""
    import cfsr.bench

    timed = cfsr.bench.time_call
    monkeypatch.setattr(cfsr.bench, "time_call",
                        lambda fn, **_: timed(fn, min_time=0.0, max_reps=1))


@pytest.fixture
def smoke_sizes(monkeypatch, few_timings):
    """``bench --quick`` at the least that still runs every part: timings of 1 call each,
    2 pool frames per split, 1.5 s of acquisition (its runs: 0.5 s each at the least), live
    runs of 3 s, 2 CFSR dense frames. The figures mean nothing at these sizes (the
    benchmark itself keeps its own); the JSON's parts and shape are what is checked."""
    from cfsr.cli import _throughput

    monkeypatch.setattr(_throughput, "QUICK", _throughput.QUICK._replace(
        min_time=0.0, pool_frames=2, acquisition_s=1.5, live_s=3.0, live_settle_s=0.5,
        dense=(("tfstp", 1, 16), ("cfsr", 32, 2))))
    # the live run's repeat beside CPU-bound processes, where the live layer has one: it
    # measures a busy machine, which the suite's host already is
    import cfsr_live.service.livebench as livebench

    if hasattr(livebench, "BUSY_CONFIGS"):
        monkeypatch.setattr(livebench, "BUSY_CONFIGS", ())


@pytest.mark.slow
def test_bench_quick_throughput_json(tmp_path, smoke_sizes):
    path = tmp_path / "t.json"
    assert (
        main(
            ["bench", "--throughput", "--quick", "-q", "--out", str(tmp_path), "--json", str(path)]
        )
        == 0
    )
    res = json.loads(path.read_text())
    rtf = res["realtime_factor"]
    assert rtf["streaming_state"] > 0
    assert rtf["acquisition"] is not None and rtf["acquisition"] > 0, res["acquisition"]
    acq = res["acquisition"]
    assert acq["lost_frames"] == 0
    # both figures, several runs each: the driver alone and the emulated camera end to end
    for part in ("driver", "end_to_end"):
        fig = acq[part]
        assert fig["n_runs"] == len(fig["runs"]) >= 3, fig
        assert 0 < fig["realtime_factor_min"] <= fig["realtime_factor"] <= fig[
            "realtime_factor_max"]
        assert fig["lost_frames"] == 0 and fig["consumer"]["unaccounted"] == 0
    assert acq["realtime_factor"] == acq["end_to_end"]["realtime_factor"]
    assert "driver alone" in acq["source"]
    for m in ("tfp", "csr", "cfsr"):
        assert res["fps"][m] > 0
        sc = res["scaling"][m]  # cost at 1 and 2 threads (or 1 where numba has one thread)
        assert sc["ms_per_frame"]["1"] > 0
        if "2" in sc["ms_per_frame"]:
            assert 0.0 <= sc["parallel_fraction"] <= 1.0
            assert 1.0 <= sc["predicted_speedup"]["8"] <= 8.0
    # dense output: a recurrent method's frames one step apart continue one state
    d = res["dense"]["tfstp"]
    assert d["stride"] == 1 and d["frames"] > 1 and d["ms_per_frame"] > 0
    assert d["speedup"] == pytest.approx(d["isolated_ms_per_frame"] / d["ms_per_frame"])
    assert res["dense"]["cfsr"]["stride"] == 32
    # the live service's frame rate: a quick run measures CFSR auto and TFP, both publishing
    live = res["live"]["runs"]
    assert [(r["method"], r["quality"], r["workers"]) for r in live] == [
        ("cfsr", "auto", 2), ("tfp", None, 1)], live
    assert all(r["fps"] > 0 and r["real_time_factor"] > 0 for r in live), live


def test_amdahl_parallel_fraction():
    from cfsr.bench import amdahl

    assert amdahl(10.0, 5.0, 2) == pytest.approx(1.0)  # perfectly parallel
    assert amdahl(10.0, 10.0, 2) == 0.0  # serial
    assert amdahl(10.0, 7.5, 2) == pytest.approx(0.5)
    assert amdahl(10.0, 12.0, 2) == 0.0  # slower with more threads: clipped, not negative


@pytest.mark.slow
def test_bench_on_a_local_dask_cluster_gives_the_same_scores(tmp_path):
    base = [
        "bench",
        "--quick",
        "--no-data",
        "-q",
        "--methods",
        "tfi,tfp:window=32",
        "--scenes",
        "disk,car",
        "--steps",
        "700",
    ]
    assert main(base + ["--out", str(tmp_path / "one")]) == 0
    assert main(base + ["--out", str(tmp_path / "many"), "--cluster"]) == 0

    def scores(d):
        rows = json.loads((tmp_path / d / "accuracy.json").read_text())["rows"]
        return {(r["method"], r["scene"]): (r["psnr_all"], r["ssim"]) for r in rows}

    assert scores("one") == scores("many")


@pytest.mark.slow
def test_bench_quick_sweep(tmp_path, capsys, few_timings):
    assert main(["bench", "--sweep", "--quick", "-q", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "sweep.json").read_text())
    by: dict[str, list] = {}
    for r in res["rows"]:
        by.setdefault(r["scenario"], []).append(r)
    assert list(by) == ["static", "~10% moving", "~30% moving", "full motion"]
    for scene, rs in by.items():
        # tfp, adaptive, adaptive with the tiles off, with the gate off, always-full
        assert len(rs) == 5, scene
        for r in rs:
            assert r["ms_per_frame"] > 0 and math.isfinite(r["psnr_all"])
            if r["method"] == "cfsr":
                # the bar: the adaptive pipeline's error within 0.1 dB of the full one
                assert abs(r["psnr_delta_vs_full"]) <= 0.1, (scene, r)
    gates = [
        (r["adaptive"], r["static_gate"], r["tile_gate"])
        for r in by["static"]
        if r["method"] == "cfsr"
    ]
    on, off = True, False
    assert gates == [(on, on, on), (on, on, off), (on, off, off), (off, off, off)]
    static = [r for r in by["static"] if r["method"] == "cfsr"]
    assert all(r["psnr_delta_vs_full"] == 0.0 and r["fine_fraction"] == 0.0 for r in static)
    assert "worst frame" in capsys.readouterr().out


def _fake_run(rtf: float, lost: int = 0, cpu: float | None = 1.0) -> dict:
    return {"realtime_factor": rtf, "lost_frames": lost,
            "cpu_ms_per_block": {"driver": cpu, "process": 2.0},
            "consumer": {"frames": 10, "gaps": 0, "unaccounted": 0}}


def test_summarize_runs_reports_median_spread_and_summed_loss():
    from cfsr_live.service.benchmarks import summarize_runs

    runs = [_fake_run(3.0), _fake_run(1.0, lost=2, cpu=None), _fake_run(2.0, cpu=3.0)]
    s = summarize_runs(runs, "somewhere")
    assert (s["realtime_factor"], s["realtime_factor_min"], s["realtime_factor_max"]) == (
        2.0, 1.0, 3.0)
    assert s["frames_per_s"] == 80_000 and s["n_runs"] == 3 and len(s["runs"]) == 3
    assert s["lost_frames"] == 2 and s["consumer"]["frames"] == 30
    assert s["cpu_ms_per_block"] == {"driver": 2.0, "process": 2.0}  # runs without a value skip
    assert s["source"] == "somewhere" and s["cpu_bound_realtime_factor"] is None
    runs[0]["cpu_bound_realtime_factor"], runs[2]["cpu_bound_realtime_factor"] = 4.0, 6.0
    assert summarize_runs(runs, "x")["cpu_bound_realtime_factor"] == 5.0
    with pytest.raises(ValueError, match="no runs"):
        summarize_runs([], "x")


def test_driver_throughput_measures_the_driver_alone_with_zero_loss():
    pytest.importorskip("usb.core")
    from cfsr_live.replay.pattern import pattern_recording
    from cfsr_live.service.benchmarks import driver_throughput

    res = driver_throughput(seconds=1.0, runs=2, recording=pattern_recording(512))
    assert res["n_runs"] == 2 and "no emulator" in res["source"]
    for run in res["runs"]:
        assert run["realtime_factor"] > 0 and run["frames"] > 0 and run["blocks"] > 0
        assert run["lost"] == {"driver_index_gaps": 0, "device_dropped": 0, "ring": 0}
        assert run["consumer"]["gaps"] == 0 and run["consumer"]["unaccounted"] == 0
        cpu = run["cpu_ms_per_block"]
        assert cpu["driver"] is not None and cpu["driver"] > 0  # the driver's own thread
        assert cpu["emulator"] is None  # no emulator runs here
        assert 0 <= cpu["transport_copy"] <= cpu["driver"]
        assert run["cpu_bound_realtime_factor"] > 0
    assert res["lost_frames"] == 0
