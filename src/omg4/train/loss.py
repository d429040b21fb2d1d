"""The photometric loss of Real-Time4DGS and OMG4: (1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2 (rt4dgs §3.2)."""

from __future__ import annotations

import torch

from omg4.metrics import ssim


def photometric_loss(image: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """Loss of one rendered view; ``image``, ``gt``: [H, W, 3] (the render is not clamped)."""
    l1 = (image - gt).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(image, gt))
