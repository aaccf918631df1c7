"""The defect map in a recording's sidecar and on the command line (info, reconstruct)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cfsr.cli import main
from cfsr.datfile import SpikeFileError, read_dat, sidecar_path
from cfsr.defects import map_of
from cfsr.simulate import Scene, simulate_to_dat

H, W = 48, 64


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A flat grey wall (rate 0.25) seen by a sensor with hot and dead pixels, 2,400 steps."""
    path = tmp_path_factory.mktemp("made") / "defects.dat"
    simulate_to_dat(Scene("flat", np.full((H, W), 0.5, np.float32)), 2400, path, seed=5,
                    gt_every=1200, noise="hot_fraction=0.004,hot_rate=0.5,dead_fraction=0.004")
    return path


@pytest.fixture
def dat(made, tmp_path):
    """A copy of :func:`made` (with its sidecar and ground truth) that a test may change."""
    for f in made.parent.iterdir():
        shutil.copy(f, tmp_path / f.name)
    return tmp_path / made.name


def _truth(dat):
    from cfsr.simulate import load_ground_truth

    gt = load_ground_truth(dat)
    return gt.hot_map, gt.dead_map


def test_info_counts_saves_and_exports_the_map_and_a_replay_reads_it_back(dat, tmp_path,
                                                                        capsys):
    hot, dead = _truth(dat)
    cal = tmp_path / "cal.json"
    assert main(["info", str(dat), "--json", "-q", "--save-defects",
                 "--export-defects", str(cal)]) == 0
    info = json.loads(capsys.readouterr().out)["defects"]
    assert (info["hot"], info["dead"], info["steps"]) == (hot.sum(), dead.sum(), 2000)
    assert info["sidecar"] is None and len(info["written"]) == 2
    got = map_of(read_dat(dat))  # from the sidecar, checked on read
    assert got is not None and np.array_equal(got.hot, hot) and np.array_equal(got.dead, dead)
    assert json.loads(cal.read_text())["hot"] == got.to_dict()["hot"]
    assert main(["info", str(dat), "-q"]) == 0
    out = capsys.readouterr().out
    assert f"{hot.sum()} hot, {dead.sum()} dead pixels" in out
    assert "the sidecar's map" in out


def test_reconstruct_corrects_with_the_sidecars_map_or_when_asked(dat, tmp_path):
    hot, dead = _truth(dat)
    bad = hot | dead

    def rate(name, *opt):
        out = tmp_path / name
        assert main(["reconstruct", str(dat), "-m", "tfp", "-t", "2200", "-p", "window=160",
                     "-o", str(out), "-q", *opt]) == 0
        return np.load(out / "t2200.npy")

    off, auto = rate("off", "--defects", "off"), rate("auto", "--defects", "auto")
    assert np.abs(off[bad] - 0.25).max() > 0.2
    assert np.abs(auto[bad] - 0.25).max() < 0.03
    assert np.array_equal(auto[~bad], off[~bad])
    # by default the sidecar's map, and a recording without one is read as it is
    assert np.array_equal(rate("plain"), off)
    assert main(["info", str(dat), "-q", "--save-defects"]) == 0
    assert np.array_equal(rate("saved"), auto)


@pytest.mark.parametrize("defects, what", [
    ({"width": W, "height": H, "hot": [H * W]}, "outside"),
    ({"width": W + 8, "height": H, "hot": []}, "the recording"),
    ("everything", "JSON object"),
])
def test_a_bad_map_in_a_sidecar_is_refused_with_its_file_and_key(dat, defects, what):
    side = sidecar_path(dat)
    meta = json.loads(side.read_text())
    meta["defects"] = defects
    side.write_text(json.dumps(meta))
    with pytest.raises(SpikeFileError, match=f"defects.*{what}|{what}") as ei:
        read_dat(dat)
    assert str(side) in str(ei.value)
