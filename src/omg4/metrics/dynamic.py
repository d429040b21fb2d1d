"""Dynamic-region quality: PSNR and SSIM over the pixels that move (beyond the paper).

Most pixels of a multi-view video are static, so full-image PSNR hides how well a model
renders the moving objects. The dynamic region of a test camera is computed from its
ground-truth clip alone, so it is the same for every model evaluated on that scene:

1. the static background estimate is the per-pixel temporal median of the clip (of at most
   :data:`MEDIAN_FRAMES` frames evenly spaced over it);
2. a pixel is dynamic when, in any frame of the clip, any channel differs from that
   median by more than :data:`DYNAMIC_THRESHOLD` (0.1 of the [0, 1] range, ~25/255:
   above video compression noise and flicker, below any object crossing the pixel);
3. the mask is dilated by :data:`DYNAMIC_DILATION` pixels (a square of side 2r + 1), so
   the borders of moving objects, where renders smear, count too.

Masked PSNR is ``-10·log10`` of the mean squared error over the masked pixels and all
channels (render clamped to [0, 1], float64); masked SSIM is the mean of the 3DGS SSIM map
(:func:`omg4.metrics.ssim.ssim_map`, computed on the whole image in float32 like the
full-image SSIM) over the masked pixels.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from omg4.errors import OMG4Error
from omg4.metrics.psnr import ImageLike, tensor_pair
from omg4.metrics.ssim import ssim_map

DYNAMIC_THRESHOLD = 0.1
"""A pixel moves when a frame differs from its temporal median by more than this (any channel)."""

DYNAMIC_DILATION = 2
"""Radius in pixels by which the moving pixels are dilated."""

MEDIAN_FRAMES = 64
"""At most this many frames, evenly spaced over the clip, estimate the static background."""


def dynamic_mask(frames: Sequence[np.ndarray], *, threshold: float = DYNAMIC_THRESHOLD,
                 dilation: int = DYNAMIC_DILATION) -> np.ndarray:
    """[H, W] bool mask of the pixels that move in a clip of one camera.

    Args:
        frames: the clip's ground-truth images, [H, W, C] each in [0, 1]: an array [T, H, W, C] or
            any sequence (read twice, one frame at a time, so a lazy sequence keeps memory bounded).
    Raises:
        OMG4Error: fewer than two frames, or frames of different sizes.
    """
    count = len(frames)
    if count < 2:
        raise OMG4Error("a dynamic-region mask needs a clip of at least two frames")
    step = max(1, math.ceil(count / MEDIAN_FRAMES))
    samples = [np.asarray(frames[i], dtype=np.float32) for i in range(0, count, step)]
    shape = samples[0].shape
    if any(f.shape != shape for f in samples):
        raise OMG4Error("the frames of a clip differ in size")
    median = np.median(np.stack(samples), axis=0)
    del samples
    moving = np.zeros(shape[:2], dtype=bool)
    for i in range(count):
        frame = np.asarray(frames[i], dtype=np.float32)
        if frame.shape != shape:
            raise OMG4Error("the frames of a clip differ in size")
        diff = np.abs(frame - median)
        moving |= (diff.max(axis=-1) if diff.ndim == 3 else diff) > threshold
    if dilation > 0:
        m = torch.from_numpy(moving.astype(np.float32))[None, None]
        moving = F.max_pool2d(m, 2 * dilation + 1, stride=1, padding=dilation)[0, 0].numpy() > 0
    return moving


def _masked_pair(img: ImageLike, gt: ImageLike, mask: np.ndarray | torch.Tensor, dtype: torch.dtype):
    x, y = (v.detach().to(dtype) for v in tensor_pair(img, gt))
    m = torch.as_tensor(mask, device=x.device).bool()
    if m.shape != x.shape[:2]:
        raise OMG4Error(f"mask {tuple(m.shape)} does not match the image {tuple(x.shape[:2])}")
    return x.clamp(0.0, 1.0), y, m


def masked_psnr(img: ImageLike, gt: ImageLike, mask: np.ndarray | torch.Tensor) -> float:
    """PSNR over the pixels of ``mask`` [H, W] (all channels) of [H, W, C] images; NaN for an empty mask."""
    x, y, m = _masked_pair(img, gt, mask, torch.float64)
    if not bool(m.any()):
        return math.nan
    mse = float(((x - y) ** 2)[m].mean())
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def masked_ssim(img: ImageLike, gt: ImageLike, mask: np.ndarray | torch.Tensor) -> float:
    """Mean of the SSIM map over the pixels of ``mask`` [H, W] (all channels); NaN for an empty mask."""
    x, y, m = _masked_pair(img, gt, mask, torch.float32)  # as the full-image SSIM (float64 convolutions are slow)
    if not bool(m.any()):
        return math.nan
    smap = ssim_map(x, y)[0]  # [C, H, W]
    return float(smap[:, m].mean())


__all__ = ["DYNAMIC_THRESHOLD", "DYNAMIC_DILATION", "MEDIAN_FRAMES", "dynamic_mask", "masked_psnr", "masked_ssim"]
