"""The photometric loss of Real-Time4DGS and OMG4: (1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2 (rt4dgs §3.2).

On the CPU (float32/float64, the fused kernels in use, :mod:`omg4.kernels`) one autograd function computes it with
its backward in numba (:mod:`omg4.optimize.loss_kernels`); elsewhere, and with the reference kernels, the torch form
(:func:`torch_photometric_losses`) runs.
"""

from __future__ import annotations

import torch

from omg4.kernels import runs_cpu_kernels
from omg4.metrics.ssim import ssim_map
from omg4.optimize.loss_kernels import FusedPhotometricLoss


def torch_photometric_losses(images: torch.Tensor, gts: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """[V] loss of each of ``V`` rendered views in torch operations (:func:`photometric_losses`)."""
    l1 = (images - gts).abs().mean((1, 2, 3))
    ssim_per_view = ssim_map(images.permute(0, 3, 1, 2), gts.permute(0, 3, 1, 2)).mean((1, 2, 3))
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim_per_view)


def losses_and_errors(images: torch.Tensor, gts: torch.Tensor, lambda_dssim: float = 0.2
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(losses [V], squared errors [V])``: each view's loss (differentiable in ``images``) and the float64 sum of
    its squared errors with the render clamped to [0, 1] (no gradient; the PSNR's numerator). ``images``, ``gts``:
    [V, H, W, C] (renders not clamped)."""
    if runs_cpu_kernels(images, gts):
        return FusedPhotometricLoss.apply(images, gts, lambda_dssim)
    squared = (images.detach().clamp(0.0, 1.0) - gts).square().sum((1, 2, 3), dtype=torch.float64)
    return torch_photometric_losses(images, gts, lambda_dssim), squared


def photometric_losses(images: torch.Tensor, gts: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """[V] loss of each of ``V`` rendered views at once; ``images``, ``gts``: [V, H, W, 3] (renders not clamped)."""
    return losses_and_errors(images, gts, lambda_dssim)[0]


def photometric_loss(image: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """Loss of one rendered view; ``image``, ``gt``: [H, W, 3] (the render is not clamped)."""
    return photometric_losses(image[None], gt[None], lambda_dssim)[0]
