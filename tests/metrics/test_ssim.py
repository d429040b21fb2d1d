"""3DGS SSIM and MS-SSIM against an independent float64 numpy reference, pytorch-msssim and finite differences."""

import math

import numpy as np
import pytest
import torch

from omg4.errors import OMG4Error
from omg4.metrics import ms_ssim, ssim, ssim_map
from omg4.metrics.ssim import _downsample


def _pair(shape=(37, 45, 3), noise=0.08, seed=0):
    """A smooth image plus a noisy, slightly shifted copy (SSIM well inside (0, 1))."""
    rng = np.random.default_rng(seed)
    h, w, c = shape
    yy, xx = np.mgrid[0:h, 0:w]
    gt = np.stack([0.5 + 0.3 * np.sin(xx / (4 + k) + yy / (6 + k)) for k in range(c)], -1)
    img = np.clip(np.roll(gt, 1, axis=1) + rng.normal(0, noise, gt.shape), 0, 1)
    return img, gt


def _numpy_ssim_map(img, gt):
    """Straightforward float64 3DGS SSIM: 11×11 Gaussian (σ 1.5) weighted sums over zero-padded shifts."""
    g = np.array([math.exp(-((i - 5) ** 2) / (2 * 1.5**2)) for i in range(11)])
    window = np.outer(g, g) / g.sum() ** 2
    h, w, _ = img.shape

    def blur(a):
        padded = np.pad(a, ((5, 5), (5, 5), (0, 0)))
        return sum(window[i, j] * padded[i:i + h, j:j + w] for i in range(11) for j in range(11))

    mx, my = blur(img), blur(gt)
    vx, vy, cxy = blur(img * img) - mx**2, blur(gt * gt) - my**2, blur(img * gt) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))


def test_identical_images_give_one():
    img, _ = _pair()
    value = ssim(torch.tensor(img, dtype=torch.float32), torch.tensor(img, dtype=torch.float32))
    assert value.item() == pytest.approx(1.0, abs=1e-6)


def test_matches_numpy_float64_reference():
    img, gt = _pair()
    expected_map = _numpy_ssim_map(img, gt)  # [H, W, C]
    assert 0.2 < expected_map.mean() < 0.95  # the test pair is neither trivial nor unrelated
    # float64: the whole map agrees to rounding
    got_map = ssim_map(img, gt)[0].permute(1, 2, 0).numpy()
    assert np.abs(got_map - expected_map).max() < 1e-12
    # float32 (training precision): the mean agrees within 1e-5 (E[x²] − μ² cancels in flat regions)
    x, y = torch.tensor(img, dtype=torch.float32), torch.tensor(gt, dtype=torch.float32)
    assert ssim(x, y).item() == pytest.approx(expected_map.mean(), abs=1e-5)


def test_batched_channels_first_layout_matches_per_image():
    pairs = [_pair(seed=s) for s in range(3)]
    xb = torch.tensor(np.stack([np.moveaxis(p[0], -1, 0) for p in pairs]))
    yb = torch.tensor(np.stack([np.moveaxis(p[1], -1, 0) for p in pairs]))
    per_image = [ssim(p[0], p[1]).item() for p in pairs]
    assert ssim(xb, yb).item() == pytest.approx(np.mean(per_image), abs=1e-12)
    gray = ssim(pairs[0][0][..., 0], pairs[0][1][..., 0]).item()
    assert gray == pytest.approx(_numpy_ssim_map(pairs[0][0][..., :1], pairs[0][1][..., :1]).mean(), abs=1e-12)


def test_interior_matches_pytorch_msssim_valid_window():
    pytorch_msssim = pytest.importorskip("pytorch_msssim")
    img, gt = _pair(shape=(40, 52, 3))
    x = torch.tensor(np.moveaxis(img, -1, 0)[None], dtype=torch.float32)
    y = torch.tensor(np.moveaxis(gt, -1, 0)[None], dtype=torch.float32)
    interior = ssim_map(x, y)[..., 5:-5, 5:-5].mean().item()
    reference = pytorch_msssim.ssim(x, y, data_range=1.0, win_size=11, win_sigma=1.5).item()
    assert interior == pytest.approx(reference, abs=1e-5)


def test_gradient_matches_finite_differences():
    img, gt = _pair(shape=(7, 9, 2), noise=0.1)
    x = torch.tensor(img, dtype=torch.float64, requires_grad=True)
    y = torch.tensor(gt, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: ssim(a, y), (x,), eps=1e-6, atol=1e-7)


def test_ssim_decreases_with_noise():
    values = [ssim(*_pair(noise=n, seed=3)).item() for n in (0.0, 0.05, 0.2)]
    assert values[0] > values[1] > values[2]


def test_ms_ssim_matches_pytorch_msssim():
    pytorch_msssim = pytest.importorskip("pytorch_msssim")
    img, gt = _pair(shape=(176, 192, 3), noise=0.05)
    x = torch.tensor(np.moveaxis(img, -1, 0)[None], dtype=torch.float32)
    y = torch.tensor(np.moveaxis(gt, -1, 0)[None], dtype=torch.float32)
    reference = pytorch_msssim.ms_ssim(x, y, data_range=1.0, win_size=11, win_sigma=1.5).item()
    assert ms_ssim(img.astype(np.float32), gt.astype(np.float32)).item() == pytest.approx(reference, abs=1e-5)
    assert ms_ssim(img, img).item() == pytest.approx(1.0, abs=1e-9)


def test_ms_ssim_on_odd_sizes_and_too_small_images():
    img, gt = _pair(shape=(171, 181, 3), noise=0.05)
    value = ms_ssim(img, gt).item()
    assert 0.0 < value < 1.0
    with pytest.raises(OMG4Error, match="at least 161"):
        ms_ssim(img[:160], gt[:160])


def test_downsample_replicates_last_row_and_column():
    x = np.random.default_rng(4).uniform(size=(1, 1, 5, 7))
    padded = np.pad(x, ((0, 0), (0, 0), (0, 1), (0, 1)), mode="edge")
    expected = padded.reshape(1, 1, 3, 2, 4, 2).mean(axis=(3, 5))
    assert np.allclose(_downsample(torch.tensor(x)).numpy(), expected, atol=1e-15)


def test_shape_mismatch_and_bad_rank_raise():
    img, gt = _pair()
    with pytest.raises(OMG4Error, match="shapes differ"):
        ssim(img[:-1], gt)
    with pytest.raises(OMG4Error, match="expected"):
        ssim(img[None, None], gt[None, None])
