"""SSIM as the 3DGS family computes it, and the standard multi-scale SSIM.

Image layouts (both functions, and :func:`ssim_map`):

* a 3-D input is one channels-last image ``[H, W, C]`` (what the renderer returns);
* a 4-D input is a channels-first batch ``[B, C, H, W]``;
* a 2-D input is one grayscale image ``[H, W]``.

Inputs may be torch tensors or numpy arrays; the computation runs in torch in the
promoted dtype of the two inputs, on the render's device, and is differentiable.

:func:`ssim` follows Real-Time4DGS / OMG4 ``utils/loss_utils.py: ssim`` (rt4dgs §3.2,
data §3): 11×11 Gaussian window with σ = 1.5, zero padding of 5 pixels
(so the map has the image's size and its border sees zeros), C1 = 0.01², C2 = 0.03², and
the mean of the SSIM map over pixels, channels and batch. The window is applied as one
depthwise 11×11 ``conv2d`` over the five stacked statistics (x, y, x², y², xy): on CPU
oneDNN's depthwise kernel beat two separable 1-D passes in interleaved runs (e.g. 213 vs
301 ms at 1352×1014 on 2 shared cores; ``benchmarks/speed/metrics.py``).

:func:`ms_ssim` is the standard MS-SSIM of Wang, Simoncelli & Bovik (2003) with the
five-scale weights (0.0448, 0.2856, 0.3001, 0.2363, 0.1333), valid (unpadded) Gaussian
windows as in ``pytorch-msssim``, and 2×2 average downsampling; on an odd side the last
row/column is replicated first (the reference MATLAB code's symmetric boundary).
Contrast terms are clamped at 0 before the fractional powers, as ``pytorch-msssim``
does, so that negative correlations cannot produce NaN.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from omg4.errors import OMG4Error
from omg4.metrics.psnr import ImageLike, tensor_pair

C1 = 0.01**2
C2 = 0.03**2
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)


def gaussian_window(size: int = 11, sigma: float = 1.5, *, dtype: torch.dtype = torch.float32,
                    device: torch.device | str = "cpu") -> torch.Tensor:
    """Normalized 2-D Gaussian window ``[size, size]``: the outer product of the 1-D
    Gaussian ``exp(-(i - size//2)² / 2σ²) / Σ`` with itself (3DGS ``create_window``)."""
    coords = torch.arange(size, dtype=torch.float64, device="cpu") - size // 2
    g = torch.exp(-(coords**2) / (2.0 * sigma**2))
    g = g / g.sum()
    return torch.outer(g, g).to(dtype=dtype, device=device)


def image_pair_bchw(img: ImageLike, gt: ImageLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as ``[B, C, H, W]`` tensors of a common floating dtype on ``img``'s device.

    Accepts the layouts of the module doc (``[H, W]``, ``[H, W, C]``, ``[B, C, H, W]``);
    raises :class:`OMG4Error` on other ranks or when the shapes differ.
    """
    x, y = tensor_pair(img, gt)
    dtype = torch.promote_types(torch.promote_types(x.dtype, y.dtype), torch.float32)
    x, y = x.to(dtype), y.to(dtype)
    if x.ndim == 2:
        return x[None, None], y[None, None]
    if x.ndim == 3:
        return x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None]
    if x.ndim == 4:
        return x, y
    raise OMG4Error(f"expected [H, W], [H, W, C] or [B, C, H, W] images, got shape {tuple(x.shape)}")


def _local_stats(x: torch.Tensor, y: torch.Tensor, window: torch.Tensor, padding: int):
    """Gaussian-weighted local means, variances and covariance of ``x``, ``y``: [B, C, H', W'] each."""
    channels = x.shape[1]
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [B, 5C, H, W]
    kernel = window.expand(5 * channels, 1, *window.shape)
    blurred = F.conv2d(stacked, kernel, padding=padding, groups=5 * channels)
    mu_x, mu_y, e_xx, e_yy, e_xy = blurred.split(channels, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    return mu_xx, mu_yy, mu_xy, e_xx - mu_xx, e_yy - mu_yy, e_xy - mu_xy


def _ssim_cs_maps(x: torch.Tensor, y: torch.Tensor, window: torch.Tensor, padding: int):
    """(SSIM map, contrast-structure map), each [B, C, H', W'] (Wang et al. 2004, eq. 13)."""
    mu_xx, mu_yy, mu_xy, var_x, var_y, cov_xy = _local_stats(x, y, window, padding)
    cs = (2.0 * cov_xy + C2) / (var_x + var_y + C2)
    luminance = (2.0 * mu_xy + C1) / (mu_xx + mu_yy + C1)
    return luminance * cs, cs


def ssim_map(img: ImageLike, gt: ImageLike, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """3DGS SSIM map ``[B, C, H, W]`` (zero padding, same size as the input; see module doc)."""
    x, y = image_pair_bchw(img, gt)
    window = gaussian_window(window_size, sigma, dtype=x.dtype, device=x.device)
    return _ssim_cs_maps(x, y, window, window_size // 2)[0]


def ssim(img: ImageLike, gt: ImageLike, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """3DGS-style SSIM (rt4dgs §3.2): the mean of :func:`ssim_map`; a differentiable 0-dim tensor.

    Args:
        img: ``[H, W, C]``, ``[B, C, H, W]`` or ``[H, W]`` rendered image (not clamped:
            the training loss uses ``1 - ssim(render, gt)`` on the raw render).
        gt: ground truth of the same shape, in [0, 1].
    """
    return ssim_map(img, gt, window_size, sigma).mean()


def _downsample(x: torch.Tensor) -> torch.Tensor:
    """2×2 average pooling ``[B, C, H, W] -> [B, C, ⌈H/2⌉, ⌈W/2⌉]``, replicating the last row/column on odd sides."""
    pad_w, pad_h = x.shape[-1] % 2, x.shape[-2] % 2
    if pad_w or pad_h:
        x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
    return F.avg_pool2d(x, kernel_size=2)


def ms_ssim(img: ImageLike, gt: ImageLike, window_size: int = 11, sigma: float = 1.5,
            weights: tuple[float, ...] = MS_SSIM_WEIGHTS) -> torch.Tensor:
    """Multi-scale SSIM (Wang et al. 2003) as a 0-dim tensor; see the module doc for the variant.

    Per batch item and channel: ``Π_{j<M} cs_j^{w_j} · ssim_M^{w_M}`` with the mean contrast
    term ``cs_j`` of scale ``j`` and the mean SSIM of the coarsest scale ``M``; the result is
    averaged over batch and channels. The smaller image side must be at least
    ``(window_size - 1)·2^(M-1) + 1`` (161 for the defaults) so that the coarsest scale
    still holds one full window; smaller images raise :class:`OMG4Error`.
    """
    x, y = image_pair_bchw(img, gt)
    scales = len(weights)
    min_side = (window_size - 1) * 2 ** (scales - 1) + 1
    if min(x.shape[-2:]) < min_side:
        raise OMG4Error(f"MS-SSIM with {scales} scales needs images of at least {min_side} pixels per side, "
                        f"got {tuple(x.shape[-2:])}")
    window = gaussian_window(window_size, sigma, dtype=x.dtype, device=x.device)
    w = torch.as_tensor(weights, dtype=x.dtype, device=x.device)
    factors = []
    for scale in range(scales):
        ssim_full, cs = _ssim_cs_maps(x, y, window, padding=0)
        if scale < scales - 1:
            factors.append(torch.relu(cs.mean(dim=(2, 3))))
            x, y = _downsample(x), _downsample(y)
    factors.append(torch.relu(ssim_full.mean(dim=(2, 3))))
    terms = torch.stack(factors) ** w.view(-1, 1, 1)  # [scales, B, C]
    return terms.prod(dim=0).mean()
