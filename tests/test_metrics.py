"""Metrics: PSNR/SSIM against known values and scikit-image, STD, CPBD, mask IoU."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from skimage import data
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from cfsr.metrics import cpbd, mask_iou, psnr, ssim, std_metric


@pytest.fixture(scope="module")
def camera() -> np.ndarray:
    import cv2

    return cv2.resize(data.camera(), (400, 250), interpolation=cv2.INTER_AREA).astype(np.float64)


def test_psnr_of_known_mse():
    ref = np.zeros((8, 8))
    img = np.full((8, 8), 10.0)  # MSE = 100
    assert psnr(ref, img) == pytest.approx(10 * math.log10(255**2 / 100))
    assert psnr(ref, img, data_range=1.0) == pytest.approx(-20.0)


def test_psnr_matches_skimage(camera):
    rng = np.random.default_rng(0)
    noisy = np.clip(camera + rng.normal(0, 12, camera.shape), 0, 255)
    assert psnr(camera, noisy) == pytest.approx(
        peak_signal_noise_ratio(camera, noisy, data_range=255)
    )
    assert psnr(camera.astype(np.uint8), noisy.astype(np.uint8)) == pytest.approx(
        peak_signal_noise_ratio(camera.astype(np.uint8), noisy.astype(np.uint8))
    )


def test_psnr_identical_is_inf_and_mask_restricts():
    a = np.arange(64.0).reshape(8, 8)
    assert psnr(a, a) == math.inf
    b = a.copy()
    b[:4] += 5.0  # error only in the top half
    top = np.zeros((8, 8), bool)
    top[:4] = True
    assert psnr(a, b, mask=~top) == math.inf
    assert psnr(a, b, mask=top) == pytest.approx(10 * math.log10(255**2 / 25))
    assert psnr(a, b) == pytest.approx(10 * math.log10(255**2 / 12.5))


def test_ssim_identical_and_constant():
    a = np.random.default_rng(1).uniform(0, 255, (32, 32))
    assert ssim(a, a) == pytest.approx(1.0)
    c = np.full((16, 16), 42.0)
    assert ssim(c, c) == pytest.approx(1.0)
    assert math.isfinite(ssim(c, c + 1.0))
    assert ssim(a, a, mask=a > 128) == pytest.approx(1.0)


def test_ssim_matches_skimage(camera):
    blurred = gaussian_filter(camera, 1.5)
    assert ssim(camera, blurred) == pytest.approx(
        structural_similarity(camera, blurred, data_range=255)
    )
    assert ssim(camera, blurred, gaussian_weights=True) == pytest.approx(
        structural_similarity(
            camera,
            blurred,
            data_range=255,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
        )
    )
    # an all-true mask is the whole frame
    assert ssim(camera, blurred, mask=np.ones(camera.shape, bool)) == pytest.approx(
        ssim(camera, blurred)
    )


def test_ssim_mask_is_mean_of_map_over_mask(camera):
    blurred = gaussian_filter(camera, 2.0)
    _, smap = structural_similarity(camera, blurred, data_range=255, full=True)
    mask = np.zeros(camera.shape, bool)
    mask[50:120, 100:300] = True
    assert ssim(camera, blurred, mask=mask) == pytest.approx(smap[mask].mean())


@pytest.mark.parametrize("fn", [psnr, ssim])
def test_empty_mask_and_bad_inputs_raise(fn):
    a = np.zeros((16, 16))
    with pytest.raises(ValueError, match="mask selects no pixels"):
        fn(a, a, mask=np.zeros((16, 16), bool))
    with pytest.raises(ValueError, match="differ in shape"):
        fn(a, np.zeros((16, 15)))
    with pytest.raises(ValueError, match="NaN"):
        fn(a, np.full((16, 16), np.nan))
    with pytest.raises(ValueError, match="data_range"):
        fn(a, a, data_range=0)
    with pytest.raises(ValueError, match="mask shape"):
        fn(a, a, mask=np.ones((4, 4), bool))


def test_mask_iou():
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    assert mask_iou(a, b) == 1.0  # both empty: perfect agreement
    b[0, 0] = True
    assert mask_iou(a, b) == 0.0
    a[0, :2] = True
    assert mask_iou(a, b) == pytest.approx(0.5)
    assert mask_iou(a, a) == 1.0
    with pytest.raises(ValueError, match="differ in shape"):
        mask_iou(a, b[:2])


def test_std_metric():
    assert std_metric(np.array([[0, 255], [0, 255]], np.uint8)) == pytest.approx(127.5)
    assert std_metric(np.full((5, 5), 17.0)) == 0.0
    img = np.random.default_rng(2).uniform(0, 255, (20, 30))
    assert std_metric(img) == pytest.approx(np.std(img))
    with pytest.raises(ValueError, match="2-D"):
        std_metric(np.zeros((2, 2, 3)))


def test_cpbd_falls_as_blur_grows(camera):
    scores = [cpbd(gaussian_filter(camera, s) if s else camera) for s in (0, 1, 2, 3, 5)]
    assert all(0.0 <= v <= 1.0 for v in scores)
    assert scores[0] > 0.5  # a sharp photograph
    assert scores[0] > scores[1] > scores[2] > scores[3] - 1e-12
    assert scores[3] >= scores[4]
    assert scores[4] < 0.05


def test_cpbd_uint8_equals_float(camera):
    u8 = camera.astype(np.uint8)
    assert cpbd(u8) == pytest.approx(cpbd(u8.astype(np.float64)))


def test_cpbd_rewards_noise(camera):
    # documented caveat: noise reads as sharp edges
    noisy = np.clip(camera + np.random.default_rng(0).normal(0, 20, camera.shape), 0, 255)
    assert cpbd(noisy) > cpbd(camera)


def test_cpbd_defined_for_degenerate_images():
    assert cpbd(np.full((128, 128), 100.0)) == 0.0  # no edges
    assert cpbd(np.zeros((32, 32))) == 0.0  # smaller than one 64 x 64 block
    with pytest.raises(ValueError, match="0..255"):
        cpbd(np.full((64, 64), 300.0))
