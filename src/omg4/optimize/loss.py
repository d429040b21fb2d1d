"""The photometric loss of Real-Time4DGS and OMG4: (1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2 (rt4dgs §3.2)."""

from __future__ import annotations

import torch

from omg4.metrics.ssim import ssim_map


def photometric_losses(images: torch.Tensor, gts: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """[V] loss of each of ``V`` rendered views at once; ``images``, ``gts``: [V, H, W, 3] (renders not clamped)."""
    l1 = (images - gts).abs().mean((1, 2, 3))
    ssim_per_view = ssim_map(images.permute(0, 3, 1, 2), gts.permute(0, 3, 1, 2)).mean((1, 2, 3))
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim_per_view)


def photometric_loss(image: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """Loss of one rendered view; ``image``, ``gt``: [H, W, 3] (the render is not clamped)."""
    return photometric_losses(image[None], gt[None], lambda_dssim)[0]
