"""Evaluation: method specs, scores on tiny simulated scenes, REDS, tables, the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cfsr.cli import main
from cfsr.evaluation import (
    MethodSpec,
    default_times,
    evaluate,
    evaluate_reds,
    format_table,
    parse_method_spec,
    split_method_specs,
    summarize,
)
from cfsr.methods import registry

H, W = 48, 64
STEPS = 300


def test_parse_method_spec():
    s = parse_method_spec("tfp:window=32,mode=centred")
    assert s == MethodSpec("tfp:window=32,mode=centred", "tfp", {"window": 32, "mode": "centred"})
    assert parse_method_spec("TFI").label == "tfi"
    assert parse_method_spec("tfp:preset=paper").preset == "paper"
    # defaults from params_by_method are used but do not change the label
    d = parse_method_spec("tfp:mode=centred", {"window": 16})
    assert d.params == {"window": 16, "mode": "centred"} and d.label == "tfp:mode=centred"


@pytest.mark.parametrize(
    "spec, match",
    [
        ("nosuch", "unknown method"),
        ("tfp:width=3", "no parameter 'width'"),
        ("tfp:window=0", "must be >= 1"),
        ("tfp:mode=sideways", "must be one of"),
        ("tfp:window", "KEY=VALUE"),
        ("", "empty"),
    ],
)
def test_parse_method_spec_errors(spec, match):
    with pytest.raises(ValueError, match=match):
        parse_method_spec(spec)


def test_split_method_specs():
    assert split_method_specs("tfi,tfp:window=32,mode=centred,tfp:window=16") == [
        "tfi",
        "tfp:window=32,mode=centred",
        "tfp:window=16",
    ]
    assert split_method_specs(["tfi", "tfp:window=8 tfp:window=4;tfp"]) == [
        "tfi",
        "tfp:window=8",
        "tfp:window=4",
        "tfp",
    ]
    with pytest.raises(ValueError, match="before any method"):
        split_method_specs("window=3,tfi")


def test_default_times():
    assert default_times(1200) == [480, 690, 900]
    assert all(0 <= t < 10 for t in default_times(10))


@pytest.fixture(scope="module")
def rows():
    return evaluate(
        ["tfi", "tfp:window=32,mode=centred", "tfp:window=16"],
        ["disk", "static"],
        steps=STEPS,
        times=[120, 180],
        height=H,
        width=W,
    )


def test_evaluate_rows_are_finite(rows):
    assert [(r["method"], r["scene"]) for r in rows] == [
        ("tfi", "disk"),
        ("tfp:window=32,mode=centred", "disk"),
        ("tfp:window=16", "disk"),
        ("tfi", "static"),
        ("tfp:window=32,mode=centred", "static"),
        ("tfp:window=16", "static"),
    ]
    for r in rows:
        assert r["times"] == [120, 180] and r["steps"] == STEPS
        assert r["rate_scale"] == pytest.approx(0.5)
        for k in ("psnr_all", "ssim", "ms_per_frame"):
            assert isinstance(r[k], float) and math.isfinite(r[k]), (k, r)
        assert 5 < r["psnr_all"] < 60 and -1 <= r["ssim"] <= 1
        if r["scene"] == "disk":
            assert math.isfinite(r["psnr_motion"]) and math.isfinite(r["ssim_motion"])
            assert r["motion_fraction"] > 0
        else:
            assert r["psnr_motion"] is None and r["ssim_motion"] is None
            assert r["motion_fraction"] == 0
    json.dumps(rows)  # JSON-ready


def test_evaluate_orders_methods_sensibly(rows):
    by = {(r["method"], r["scene"]): r for r in rows}
    # on a static scene a 32-step count beats a 16-step count, which beats nothing
    assert (
        by["tfp:window=32,mode=centred", "static"]["psnr_all"]
        > by["tfp:window=16", "static"]["psnr_all"]
    )


def test_evaluate_same_method_twice_and_params_by_method():
    rows = evaluate(
        ["tfp", "tfp:window=8"],
        "static",
        steps=200,
        times=[100],
        height=H,
        width=W,
        params_by_method={"tfp": {"window": 64, "mode": "centred"}},
    )
    assert rows[0]["params"] == {"window": 64, "mode": "centred"}
    assert rows[1]["params"] == {"window": 8, "mode": "centred"}


def test_evaluate_reports_iou_of_every_mask(monkeypatch):
    from cfsr.methods.registry import Method, Output

    def compute(window, center, start, p):
        rate = window[max(0, center - 15) : center + 16].mean(0).astype(np.float32)
        moving = np.zeros(rate.shape, bool)
        moving[H // 4 : 3 * H // 4, W // 4 : 3 * W // 4] = True
        return Output(rate, {"coarse": moving, "none": np.zeros(rate.shape, bool)})

    fake = Method(
        "fakemask",
        "test method with masks",
        {},
        lambda p: (15, 15),
        compute,
        masks=("coarse", "none"),
    )
    monkeypatch.setitem(registry._REGISTRY, "fakemask", fake)
    rows = evaluate(["fakemask"], ["disk", "static"], steps=200, times=[100], height=H, width=W)
    disk, static = rows
    assert 0.1 < disk["iou_coarse"] < 1 and disk["iou_none"] == 0.0
    assert static["iou_none"] == 1.0 and static["iou_coarse"] == 0.0
    assert "IoU coarse" in format_table(rows)


def test_evaluate_bad_inputs():
    with pytest.raises(ValueError, match="unknown scene"):
        evaluate(["tfi"], ["moon"], steps=100, height=H, width=W)
    with pytest.raises(ValueError, match="outside the simulated run"):
        evaluate(["tfi"], ["disk"], steps=100, times=[100], height=H, width=W)
    with pytest.raises(ValueError, match="given twice"):
        evaluate(["tfi", "TFI"], ["disk"], steps=100, height=H, width=W)


def test_format_table_and_summary(rows):
    text = format_table(rows)
    lines = text.splitlines()
    assert lines[0].split()[:3] == ["method", "scene", "PSNR"]
    assert len(lines) == 2 + len(rows)
    assert "-" in lines[-1].split()  # no motion on the static scene
    means = summarize(rows)
    assert [m["method"] for m in means] == ["tfi", "tfp:window=32,mode=centred", "tfp:window=16"]
    assert means[0]["psnr_all"] == pytest.approx(
        np.mean([rows[0]["psnr_all"], rows[3]["psnr_all"]])
    )
    assert format_table([]) == "(no results)"


@pytest.mark.data
def test_evaluate_reds(reds_files):
    folder = reds_files[0][0].parent.parent
    rows = evaluate_reds(folder, ["tfi", "tfp:window=41,mode=centred"])
    files = [r for r in rows if r["scene"] != "mean"]
    means = {r["method"]: r for r in rows if r["scene"] == "mean"}
    assert len(files) == 2 * len(reds_files)
    # published anchors (Spike-Zoo, same brightness rule): TFI 25.1 dB, TFP 28.2 dB
    assert 20 < means["tfi"]["psnr_all"] < 30
    assert 22 < means["tfp:window=41,mode=centred"]["psnr_all"] < 32
    assert means["tfp:window=41,mode=centred"]["psnr_all"] > means["tfi"]["psnr_all"]


def test_cli_evaluate(tmp_path, capsys):
    out = tmp_path / "rows.json"
    rc = main(
        [
            "evaluate",
            "-m",
            "tfi,tfp:window=32,mode=centred",
            "--scenes",
            "car,static",
            "--steps",
            "240",
            "--times",
            "100,140",
            "--height",
            str(H),
            "--width",
            str(W),
            "--json",
            str(out),
            "-q",
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "tfp:window=32,mode=centred" in text and "mean over scenes" in text
    data = json.loads(out.read_text())
    assert len(data["rows"]) == 4


def test_cli_evaluate_unknown_method(capsys):
    rc = main(["evaluate", "-m", "tfz", "--steps", "100", "-q"])
    assert rc == 2
    assert "unknown method 'tfz'" in capsys.readouterr().err
