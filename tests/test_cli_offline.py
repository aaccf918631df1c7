"""The offline CLI contract: cfsr reconstruct / info / methods, run as a user would."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

import cfsr
from cfsr.cli import main


@pytest.fixture
def dat(tmp_path):
    rng = np.random.default_rng(0)
    rate = np.linspace(0.05, 0.6, 32)[None, :].repeat(16, 0)
    s = (rng.random((600, 16, 32)) < rate).astype(np.uint8)
    f = tmp_path / "in.dat"
    cfsr.write_dat(f, s, meta={"gain": 0.6})
    return f, s


def test_reconstruct_writes_npy_and_png(dat, tmp_path, capsys):
    f, s = dat
    out = tmp_path / "o"
    rc = main(
        [
            "reconstruct",
            str(f),
            "--method",
            "tfp",
            "--times",
            "300,500",
            "--out",
            str(out),
            "--param",
            "window=64",
            "-q",
        ]
    )
    assert rc == 0
    for t in (300, 500):
        arr = np.load(out / f"t{t}.npy")
        assert arr.dtype == np.float32 and arr.shape == (16, 32)
        np.testing.assert_allclose(arr, cfsr.reconstruct(s, "tfp", [t], window=64)[0])
        png = np.asarray(Image.open(out / f"t{t}.png"))
        assert png.dtype == np.uint8 and png.shape == (16, 32)
    assert "2 frame(s) of tfp" in capsys.readouterr().out


def test_reconstruct_video(dat, tmp_path):
    import cv2

    f, _ = dat
    vid = tmp_path / "v.mp4"
    assert (
        main(
            [
                "reconstruct",
                str(f),
                "-m",
                "tfi",
                "-t",
                "100:400:20",
                "--video",
                str(vid),
                "--no-files",
                "-q",
            ]
        )
        == 0
    )
    cap = cv2.VideoCapture(str(vid))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 15


def test_reconstruct_bad_inputs_give_one_line_errors(dat, tmp_path, capsys):
    f, _ = dat
    assert main(["reconstruct", str(f), "-m", "nope", "-t", "1"]) == 2
    assert "unknown method 'nope'" in capsys.readouterr().err
    assert main(["reconstruct", str(f), "-t", "5000"]) == 2
    assert "outside the recording" in capsys.readouterr().err
    assert main(["reconstruct", str(f), "-t", "5", "-p", "window=abc"]) == 2
    assert "expected int" in capsys.readouterr().err
    bad = tmp_path / "bad.dat"
    bad.write_bytes(bytes(12501))
    assert main(["reconstruct", str(bad), "-t", "0"]) == 2
    err = capsys.readouterr().err
    assert "bad.dat: size 12501 bytes is not a multiple" in err
    assert (
        main(
            ["reconstruct", str(bad), "-t", "0", "--allow-partial", "-q", "-o", str(tmp_path / "p")]
        )
        == 0
    )


def test_info_reports_geometry_rates_and_problems(dat, tmp_path, capsys):
    f, s = dat
    assert main(["info", str(f), "--json", "-q"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["width"] == 32 and info["height"] == 16 and info["n_frames"] == 600
    assert info["duration_s"] == pytest.approx(600 / 40000)
    assert info["mean_rate"] == pytest.approx(s.mean())
    assert info["problems"] == []
    partial = tmp_path / "partial.dat"
    partial.write_bytes(bytes(12500 * 2 + 10))
    assert main(["info", str(partial), "-q"]) == 0
    out = capsys.readouterr().out
    assert "10 trailing bytes" in out and "2 of 2 frames hold no spike" in out


def test_methods_command(capsys):
    assert main(["methods", "--json"]) == 0
    ms = json.loads(capsys.readouterr().out)
    assert "tfi" in ms and "tfp" in ms


def test_console_script_help():
    r = subprocess.run(
        [sys.executable, "-m", "cfsr", "--help"], capture_output=True, text=True, check=True
    )
    for cmd in ("serve", "reconstruct", "info", "simulate", "evaluate", "bench"):
        assert cmd in r.stdout
    r = subprocess.run(
        [sys.executable, "-m", "cfsr", "reconstruct", "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "spikes/step" in r.stdout and "--masks" in r.stdout


def test_reconstruct_masks_written_beside_frames(dat, tmp_path):
    f, s = dat
    out = tmp_path / "m"
    assert (
        main(
            [
                "reconstruct",
                str(f),
                "-m",
                "csr",
                "-t",
                "450",
                "--masks",
                "-o",
                str(out),
                "-q",
                "-p",
                "T=200,max_isi=100",
            ]
        )
        == 0
    )
    mask = np.load(out / "t450_mask_coarse.npy")
    assert mask.dtype == bool and mask.shape == (16, 32)
    _, want = cfsr.reconstruct(s, "csr", [450], return_masks=True, T=200, max_isi=100)
    np.testing.assert_array_equal(mask, want["coarse"][0])
    assert np.asarray(Image.open(out / "t450_mask_coarse.png")).max() in (0, 255)


def test_a_first_reconstruct_shows_its_compile_kernel_by_kernel(capsys):
    """Before a method's first frame, its kernels are compiled (or loaded from the cache) in
    the caller's process with one progress line per kernel: the method, the kernel's rank
    and the CPU seconds, never a frame counter standing still for minutes."""
    import re
    import subprocess
    import sys

    from cfsr.cli._common import compile_first

    # a new process: this one may hold TFI's kernels already (then nothing loads)
    code = ("from cfsr.warmup import warm_up; "
            "warm_up(['tfi'], kernels=lambda line, tracker: print(line, flush=True))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines, "no kernel was compiled or loaded"
    assert all(re.match(r"tfi: kernel \d+(/\d+)?( (compiling|waiting for) \S+)?, "
                        r"[\d.]+( of ~\d+)? CPU s$", ln) for ln in lines), lines
    counts = [int(re.match(r"tfi: kernel (\d+)", ln).group(1)) for ln in lines]
    assert counts == sorted(counts) and counts[-1] >= 1
    compile_first("tfi", quiet=True)  # quiet: nothing on stderr
    assert capsys.readouterr().err == ""


def test_npz_array_chosen_with_key(dat, tmp_path, capsys):
    """An .npz with several 3-D arrays: the error names them and the option that picks one,
    --key picks it, and --key on a .dat is refused in one line."""
    f, s = dat
    two = tmp_path / "two.npz"
    np.savez(two, a=s, b=s[:300])
    assert main(["info", str(two)]) == 2
    err = capsys.readouterr().err
    assert "['a', 'b']" in err and "--key" in err and len(err.strip().splitlines()) == 1
    assert main(["info", str(two), "--key", "b"]) == 0
    assert "300 steps" in capsys.readouterr().out
    assert main(["info", str(two), "--key", "c"]) == 2
    assert "no array 'c'" in capsys.readouterr().err
    assert main(["info", str(f), "--key", "a"]) == 2
    assert "only an .npz" in capsys.readouterr().err
