"""The fused photometric loss (numba, forward and backward) against its torch form and finite differences."""

from __future__ import annotations

import pytest
import torch

from omg4.kernels import using_kernels
from omg4.optimize.loss import losses_and_errors, photometric_losses, torch_photometric_losses
from omg4.optimize.loss_kernels import FusedPhotometricLoss


def _pair(seed, shape, dtype, noise=0.1):
    g = torch.Generator().manual_seed(seed)
    gts = torch.rand(*shape, generator=g, dtype=torch.float64)
    images = gts + noise * torch.randn(*shape, generator=g, dtype=torch.float64)  # some outside [0, 1]
    return images.to(dtype).requires_grad_(True), gts.to(dtype)


@pytest.mark.parametrize("shape", [(2, 40, 33, 3), (1, 7, 5, 3), (3, 12, 19, 1)])
def test_fused_loss_matches_the_torch_form_in_float64(shape):
    images, gts = _pair(0, shape, torch.float64)
    weights = torch.linspace(0.5, 1.5, shape[0], dtype=torch.float64)
    ref = torch_photometric_losses(images, gts, 0.2)
    (ref * weights).sum().backward()
    grad_ref, images.grad = images.grad, None
    fused, squared = FusedPhotometricLoss.apply(images, gts, 0.2)
    (fused * weights).sum().backward()
    assert torch.allclose(fused, ref, rtol=1e-13, atol=0)
    assert torch.allclose(images.grad, grad_ref, rtol=1e-10, atol=1e-15 * float(grad_ref.abs().max()))
    expected = (images.detach().clamp(0, 1) - gts).square().sum((1, 2, 3))
    assert torch.allclose(squared, expected, rtol=1e-12) and not squared.requires_grad


def test_fused_loss_matches_finite_differences():
    images, gts = _pair(1, (2, 9, 8, 3), torch.float64, noise=0.2)
    assert torch.autograd.gradcheck(lambda x: FusedPhotometricLoss.apply(x, gts, 0.3)[0], (images,), eps=1e-6,
                                    atol=1e-8, rtol=1e-6)


def test_float32_loss_within_float32_rounding_of_the_reference():
    images, gts = _pair(2, (2, 48, 64, 3), torch.float32)
    ref64 = torch_photometric_losses(images.detach().double().requires_grad_(True), gts.double(), 0.2)
    fused, _ = FusedPhotometricLoss.apply(images, gts, 0.2)
    assert fused.dtype == torch.float32
    assert torch.allclose(fused.double(), ref64, rtol=2e-6)


def test_the_kernels_serve_cpu_float_tensors_and_the_reference_mode_the_torch_form(monkeypatch):
    images, gts = _pair(3, (1, 16, 16, 3), torch.float32)
    calls = []
    original = FusedPhotometricLoss.apply
    monkeypatch.setattr(FusedPhotometricLoss, "apply", lambda *a: calls.append(1) or original(*a))
    photometric_losses(images, gts)
    assert calls == [1]
    with using_kernels("reference"):
        losses, squared = losses_and_errors(images, gts)
    assert calls == [1] and squared.dtype == torch.float64
    assert torch.allclose(losses, torch_photometric_losses(images, gts), rtol=0, atol=0)
