"""PSNR against closed forms and a float64 numpy brute force (rt4dgs §6)."""

import math

import numpy as np
import pytest
import torch

from omg4.errors import OMG4Error
from omg4.metrics import psnr, psnr_per_channel_mean


def _gt(shape=(12, 17, 3), seed=0):
    return np.random.default_rng(seed).uniform(0.2, 0.7, size=shape)


@pytest.mark.parametrize("offset", [0.1, 0.02, 0.003])
def test_constant_offset_closed_form(offset):
    gt = _gt()
    assert psnr(gt + offset, gt) == pytest.approx(-20.0 * math.log10(offset), abs=1e-9)
    assert psnr(torch.from_numpy(gt - offset).float(), torch.from_numpy(gt).float()) == pytest.approx(
        -20.0 * math.log10(offset), abs=1e-4)


def test_render_is_clamped_to_unit_range():
    gt = np.full((5, 6, 3), 0.9)
    # 1.4 clamps to 1.0 and -0.3 to 0.0: errors 0.1 and 0.9 on half the pixels each
    img = np.where(np.arange(6)[None, :, None] < 3, 1.4, -0.3) * np.ones((5, 6, 3))
    expected_mse = (0.1**2 + 0.9**2) / 2
    assert psnr(img, gt) == pytest.approx(-10.0 * math.log10(expected_mse), abs=1e-9)


def test_matches_float64_bruteforce_on_random_images():
    rng = np.random.default_rng(1)
    gt = rng.uniform(0, 1, (20, 30, 3))
    img = gt + rng.normal(0, 0.05, gt.shape)
    mse = np.mean((np.clip(img, 0, 1) - gt) ** 2)
    assert psnr(img, gt) == pytest.approx(-10 * np.log10(mse), abs=1e-9)


def test_per_channel_mean_quirk_closed_form():
    gt = _gt()
    offsets = np.array([0.1, 0.01, 0.001])
    img = gt + offsets
    assert psnr_per_channel_mean(img, gt) == pytest.approx(40.0, abs=1e-9)  # mean of 20, 40, 60 dB
    standard = -10 * math.log10(np.mean(offsets**2))
    assert psnr(img, gt) == pytest.approx(standard, abs=1e-9)
    assert standard < 40.0
    chw = np.moveaxis(img, -1, 0), np.moveaxis(gt, -1, 0)
    assert psnr_per_channel_mean(*chw, channel_axis=0) == pytest.approx(40.0, abs=1e-9)


def test_identical_images_give_infinity():
    gt = _gt()
    assert psnr(gt, gt) == math.inf


def test_bad_input_raises_one_line_errors():
    gt = _gt()
    with pytest.raises(OMG4Error, match="shapes differ"):
        psnr(gt[:, :-1], gt)
    bad = gt.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(OMG4Error, match="NaN"):
        psnr(bad, gt)
    with pytest.raises(OMG4Error, match="empty"):
        psnr(np.zeros((0, 3)), np.zeros((0, 3)))
