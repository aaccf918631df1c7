"""The .dat format: layout, round trips, sidecar, and every bad-input case."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

import cfsr
from cfsr import Layout, SpikeFileError, read_dat, read_npz, write_dat
from cfsr.datfile import sidecar_path


def rand_spikes(t=37, h=10, w=16, p=0.3, seed=0):
    return (np.random.default_rng(seed).random((t, h, w)) < p).astype(np.uint8)


def test_bit_layout_matches_spikecv(tmp_path):
    # One spike at upright (row 0, col 3): stored row is H-1 (flipud), pixel index
    # (H-1)*W + 3 -> byte p//8, bit p%8 (LSB first). This is SpikeCV's get_spike_matrix rule.
    h, w = 4, 8
    s = np.zeros((1, h, w), np.uint8)
    s[0, 0, 3] = 1
    write_dat(tmp_path / "a.dat", s)
    raw = (tmp_path / "a.dat").read_bytes()
    p = (h - 1) * w + 3
    expect = bytearray(h * w // 8)
    expect[p // 8] = 1 << (p % 8)
    assert raw == bytes(expect)
    # and the reader undoes it, the SpikeCV way (unpackbits little + flipud)
    ref = np.flipud(np.unpackbits(np.frombuffer(raw, np.uint8), bitorder="little").reshape(h, w))
    assert np.array_equal(read_dat(tmp_path / "a.dat", w, h)[0], ref)


@pytest.mark.parametrize(
    "layout",
    [
        Layout(16, 10),
        Layout(16, 10, head_cols=8),
        Layout(16, 10, fliplr=True),
        Layout(16, 10, flipud=False),
        Layout(16, 10, head_cols=16, fliplr=True),
    ],
)
def test_round_trip_bit_exact(tmp_path, layout):
    s = rand_spikes()
    f = tmp_path / "x.dat"
    write_dat(f, s, layout=layout)
    assert f.stat().st_size == s.shape[0] * layout.frame_bytes
    rec = read_dat(f)  # geometry comes back from the sidecar
    assert rec.layout == layout
    assert np.array_equal(rec[:], s)
    assert np.array_equal(rec[5], s[5])
    assert np.array_equal(rec.frames(3, 9), s[3:9])
    # re-encode through a recording and compare bytes
    write_dat(tmp_path / "y.dat", rec)
    assert (tmp_path / "y.dat").read_bytes() == f.read_bytes()


def test_head_columns_variant_416(tmp_path):
    # A 416-wide raw file: drop the 16 head columns on the right.
    s = rand_spikes(5, 250, 416, seed=3)
    raw = np.packbits(s[:, ::-1, :].reshape(5, -1), axis=1, bitorder="little")
    (tmp_path / "r.dat").write_bytes(raw.tobytes())
    rec = read_dat(tmp_path / "r.dat", 400, 250, head_cols=16)
    assert rec.layout.frame_bytes == 13000
    assert np.array_equal(rec[:], s[:, :, :400])


def test_sidecar_written_and_read(tmp_path):
    f = tmp_path / "s.dat"
    write_dat(f, rand_spikes(), meta={"gain": 0.4, "source": "test"})
    side = json.loads(sidecar_path(f).read_text())
    assert side["width"] == 16 and side["height"] == 10 and side["n_frames"] == 37
    assert side["rate_hz"] == 40000 and side["gain"] == 0.4 and side["source"] == "test"
    rec = read_dat(f)
    assert rec.gain == 0.4 and rec.meta["source"] == "test"


def test_memory_mapped_not_loaded(tmp_path):
    f = tmp_path / "big.dat"
    with open(f, "wb") as fh:  # 4000 frames of zeros, sparse file: opening must not read it
        fh.truncate(4000 * 12500)
    rec = read_dat(f)
    assert isinstance(rec.packed_frames, np.memmap)
    assert rec.shape == (4000, 250, 400)
    assert rec[3999].sum() == 0


# --- bad input --------------------------------------------------------------------------


def test_missing_file(tmp_path):
    with pytest.raises(SpikeFileError, match="no such file"):
        read_dat(tmp_path / "nope.dat")


def test_directory(tmp_path):
    with pytest.raises(SpikeFileError, match="directory"):
        read_dat(tmp_path)


def test_empty_file(tmp_path):
    (tmp_path / "e.dat").write_bytes(b"")
    with pytest.raises(SpikeFileError, match=r"e\.dat: empty file"):
        read_dat(tmp_path / "e.dat")


def test_partial_tail_is_an_error_by_default(tmp_path):
    (tmp_path / "p.dat").write_bytes(bytes(12500 * 3 + 100))
    with pytest.raises(
        SpikeFileError,
        match=r"p\.dat: size 37600 bytes is not a multiple of the "
        r"frame size 12500.*allow_partial",
    ):
        read_dat(tmp_path / "p.dat")


def test_partial_tail_dropped_when_allowed(tmp_path):
    (tmp_path / "p.dat").write_bytes(bytes(12500 * 3 + 100))
    with pytest.warns(UserWarning, match="dropping the partial tail"):
        rec = read_dat(tmp_path / "p.dat", allow_partial=True)
    assert rec.n_frames == 3 and rec.meta["dropped_tail_bytes"] == 100


def test_smaller_than_one_frame(tmp_path):
    (tmp_path / "s.dat").write_bytes(bytes(100))
    with pytest.raises(SpikeFileError, match="0 whole frames"):
        read_dat(tmp_path / "s.dat", allow_partial=True)


def test_wrong_geometry(tmp_path):
    (tmp_path / "g.dat").write_bytes(bytes(12500))
    with pytest.raises(SpikeFileError, match="wrong geometry"):
        read_dat(tmp_path / "g.dat", width=-4)
    with pytest.raises(SpikeFileError, match="wrong geometry"):
        read_dat(tmp_path / "g.dat", width=3, height=3)  # 9 bits: not whole bytes
    # a geometry that does not divide the size is reported with both numbers
    with pytest.raises(SpikeFileError, match="frame size 12000"):
        read_dat(tmp_path / "g.dat", width=400, height=240)


def test_unreadable_sidecar(tmp_path):
    (tmp_path / "u.dat").write_bytes(bytes(12500))
    sidecar_path(tmp_path / "u.dat").write_text("{not json")
    with pytest.raises(SpikeFileError, match=r"u\.dat\.json: unreadable sidecar"):
        read_dat(tmp_path / "u.dat")
    sidecar_path(tmp_path / "u.dat").write_text("[1, 2]")
    with pytest.raises(SpikeFileError, match="JSON object"):
        read_dat(tmp_path / "u.dat")


def test_sidecar_with_bad_geometry(tmp_path):
    (tmp_path / "b.dat").write_bytes(bytes(12500))
    sidecar_path(tmp_path / "b.dat").write_text(json.dumps({"width": "wide"}))
    with pytest.raises(SpikeFileError, match="wrong geometry"):
        read_dat(tmp_path / "b.dat")


def test_npz_round_trip_and_errors(tmp_path):
    s = rand_spikes(20, 25, 25)  # 625 pixels: not a whole number of bytes per frame
    np.savez(tmp_path / "a.npz", spk=s, label=np.int64(3))
    rec = read_npz(tmp_path / "a.npz")
    assert rec.shape == (20, 25, 25)
    assert np.array_equal(rec[:], s)
    np.savez(tmp_path / "b.npz", x=s * 3)
    with pytest.raises(SpikeFileError, match="outside 0/1"):
        read_npz(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", a=s, b=s)
    with pytest.raises(SpikeFileError, match="cannot tell which array"):
        read_npz(tmp_path / "c.npz")
    (tmp_path / "d.npz").write_bytes(b"garbage")
    with pytest.raises(SpikeFileError, match="not a readable .npz"):
        read_npz(tmp_path / "d.npz")


def test_import_cfsr_does_not_load_camera_stack():
    import subprocess

    code = (
        "import sys, cfsr; bad = [m for m in ('fastapi', 'usb', 'uvicorn', 'cfsr_live', "
        "'cv2') if m in sys.modules]; print(bad); assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    # a reconstruction loads none of the extras either (here they are installed, so this is
    # about imports; tests/test_packaging.py checks a base install where they are absent)
    code = (
        "import sys, numpy as np, cfsr\n"
        "x = (np.random.default_rng(0).random((300, 16, 24)) < 0.2).astype(np.uint8)\n"
        "cfsr.reconstruct(x, 'tfp', [200], window=32)\n"
        "cfsr.reconstruct(x, 'csr', [200])\n"
        "bad = [m for m in ('fastapi', 'starlette', 'uvicorn', 'websockets', 'usb', "
        "'prometheus_client', 'dask', 'distributed', 'matplotlib', 'cfsr_live') "
        "if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    assert cfsr.__version__


# --- shared data -------------------------------------------------------------------------


@pytest.mark.data
def test_reds_tfp_matches_ground_truth(reds_files):
    from PIL import Image

    for dat, png in reds_files:
        rec = read_dat(dat)
        assert rec.shape == (301, 250, 400)
        gt = np.asarray(Image.open(png).convert("L"), np.float64)
        best_psnr, best_corr, img = -1.0, 0.0, None
        for w in (21, 41):  # fast motion favours short windows on some clips
            cand = np.clip(
                cfsr.reconstruct(rec, "tfp", [150], window=w, mode="centred")[0] / 0.6 * 255, 0, 255
            )
            psnr = 10 * np.log10(255**2 / np.mean((cand - gt) ** 2))
            if psnr > best_psnr:
                best_psnr, img = psnr, cand
                best_corr = np.corrcoef(gt.ravel(), cand.ravel())[0, 1]
        assert best_corr > 0.9, (dat.name, best_corr)
        assert best_psnr > 25, (dat.name, best_psnr)
        # upside down would decorrelate: the orientation is right
        assert np.corrcoef(gt.ravel(), img[::-1].ravel())[0, 1] < 0.5


@pytest.mark.data
def test_uhsr_npz(shared_data):
    rec = read_npz(shared_data / "real" / "uhsr.npz")
    assert rec.shape == (200, 250, 250)
    assert 0.01 < rec[:].mean() < 0.1
