"""Peak signal-to-noise ratio of images in [0, 1].

The standard PSNR is ``-10·log10(MSE)`` with the MSE taken over all pixels and channels
(rt4dgs §6, "Standard"; omg4 §10: ``20·log10(1/sqrt(mse))`` on the render
clamped to [0, 1]). Real-Time4DGS's ``utils/image_utils.py: psnr`` instead averages the
per-channel PSNRs of a [3, H, W] image, which is never below the standard value;
:func:`psnr_per_channel_mean` reproduces that quirk for parity only.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from omg4.errors import OMG4Error

ImageLike = torch.Tensor | np.ndarray


def tensor_pair(img: ImageLike, gt: ImageLike) -> tuple[torch.Tensor, torch.Tensor]:
    """``img`` as a tensor where it lives (numpy on the CPU, never torch's default device) and ``gt``
    on the same device; images of different shapes are a one-line :class:`OMG4Error`."""
    x = img if isinstance(img, torch.Tensor) else torch.from_numpy(np.asarray(img))
    y = torch.as_tensor(gt, device=x.device)
    if x.shape != y.shape:
        raise OMG4Error(f"image shapes differ: rendered {tuple(x.shape)} vs ground truth {tuple(y.shape)}")
    return x, y


def _pair(img: ImageLike, gt: ImageLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as detached float64 tensors on ``img``'s device, the render clamped to [0, 1]."""
    x, y = (v.detach() for v in tensor_pair(img, gt))
    if x.numel() == 0:
        raise OMG4Error("cannot compute PSNR of an empty image")
    return x.to(torch.float64).clamp(0.0, 1.0), y.to(torch.float64)


def _psnr_from_mse(mse: float) -> float:
    if not math.isfinite(mse):
        raise OMG4Error("image contains NaN or Inf values; PSNR is undefined")
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def psnr(img: ImageLike, gt: ImageLike) -> float:
    """Standard PSNR in dB over all pixels and channels (rt4dgs §6).

    Args:
        img: rendered image, any shape (e.g. [H, W, 3]); clamped to [0, 1] first.
        gt: ground-truth image in [0, 1], same shape.

    Returns ``-10·log10(mean((clamp(img) - gt)²))`` computed in float64; ``inf`` for
    identical images. Raises :class:`OMG4Error` on a shape mismatch or non-finite values.
    """
    x, y = _pair(img, gt)
    return _psnr_from_mse(float(((x - y) ** 2).mean()))


def psnr_per_channel_mean(img: ImageLike, gt: ImageLike, channel_axis: int = -1) -> float:
    """Official Real-Time4DGS PSNR quirk: the mean over channels of per-channel PSNRs (rt4dgs §6).

    For parity with published Real-Time4DGS numbers only; it is never below
    :func:`psnr` (Jensen's inequality on ``-log``). ``channel_axis`` names the channel
    dimension (-1 for [H, W, C], 0 for the official [C, H, W]).
    """
    x, y = _pair(img, gt)
    dims = [d for d in range(x.ndim) if d != channel_axis % x.ndim]
    per_channel = ((x - y) ** 2).mean(dim=dims)
    return float(np.mean([_psnr_from_mse(float(m)) for m in per_channel]))
