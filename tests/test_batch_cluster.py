"""Batch reconstruction over a folder, split in chunks, on a local Dask cluster, equals one
process exactly."""

from __future__ import annotations

import numpy as np
import pytest

import cfsr
from cfsr.batch import plan_chunks
from cfsr.cli import main


def test_plan_chunks():
    assert plan_chunks([5, 1, 2, 9, 30, 31], 10) == [(1, 2, 5, 9), (30, 31)]
    with pytest.raises(ValueError):
        plan_chunks([1], 0)


@pytest.fixture
def folder(tmp_path):
    rng = np.random.default_rng(1)
    d = tmp_path / "recs"
    d.mkdir()
    for name in ("a", "b"):
        rate = rng.uniform(0.05, 0.6, (8, 16))
        cfsr.write_dat(d / f"{name}.dat", (rng.random((900, 8, 16)) < rate).astype(np.uint8))
    return d


def test_folder_on_local_cluster_equals_single_process(folder, tmp_path):
    args = ["reconstruct", str(folder), "-m", "tfi", "-t", "0::50", "-q", "-p", "max_isi=60"]
    assert main(args + ["-o", str(tmp_path / "single")]) == 0
    assert main(args + ["-o", str(tmp_path / "multi"), "--cluster", "--chunk-steps", "200"]) == 0
    for name in ("a", "b"):
        files = sorted((tmp_path / "single" / name).glob("t*.npy"))
        assert len(files) == 18
        for f in files:
            np.testing.assert_array_equal(np.load(f), np.load(tmp_path / "multi" / name / f.name))
        # and the same numbers as the library's whole-array path
        rec = cfsr.read_dat(folder / f"{name}.dat")
        np.testing.assert_array_equal(
            np.load(tmp_path / "single" / name / "t450.npy"),
            cfsr.reconstruct(rec, "tfi", [450], max_isi=60)[0],
        )
