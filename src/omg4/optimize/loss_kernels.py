"""The photometric loss (1 − λ)·L1 + λ·(1 − SSIM) of a batch of views as numba kernels, forward and backward
(rt4dgs §3.2; the SSIM of :mod:`omg4.metrics.ssim`: 11×11 Gaussian window, σ = 1.5, zero padding of 5).

The 2-D window is the outer product of a normalized 1-D Gaussian ``g``, so each of the five local statistics
``μx, μy, E[x²], E[y²], E[xy]`` is a blur along the rows then along the columns (22 taps instead of 121). Per pixel
and channel, with ``σx² = E[x²] − μx²``, ``σxy = E[xy] − μx μy``, ``A1 = 2 μx μy + C1``, ``A2 = 2 σxy + C2``,
``B1 = μx² + μy² + C1``, ``B2 = σx² + σy² + C2`` and ``S = A1 A2 / (B1 B2)``:

    ∂S/∂μx   = 2 (μy (A2 − A1) − μx S (B2 − B1)) / (B1 B2)
    ∂S/∂E[x²] = −S / B2,      ∂S/∂E[xy] = 2 A1 / (B1 B2)

and, the zero-padded blur being its own adjoint, ``∂L/∂x = blur(G_μ) + 2x·blur(G_xx) + y·blur(G_xy) +
(1 − λ)·sign(x − y)/n`` with ``G_• = −λ/n · ∂S/∂•`` (n = H·W·C). The forward keeps the three ``∂S`` maps, so the
backward is three blurs. Work runs in the images' dtype, sums in float64; the statistics are computed per view and
channel in one task each.

The torch form (:func:`omg4.optimize.loss.torch_photometric_losses`) is the reference these kernels are tested
against and what other devices run.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange, uintp
from torch.autograd.function import once_differentiable

from omg4.kernels import FAST_MATH, as_numpy, keeping_torch_threads  # also points numba's cache where it can write
from omg4.metrics.ssim import C1, C2

WINDOW = 11
SIGMA = 1.5
RADIUS = WINDOW // 2


def window_1d(dtype) -> np.ndarray:
    """The normalized 1-D Gaussian whose outer product is :func:`omg4.metrics.ssim.gaussian_window`."""
    coords = np.arange(WINDOW, dtype=np.float64) - RADIUS
    g = np.exp(-(coords ** 2) / (2.0 * SIGMA ** 2))
    return (g / g.sum()).astype(dtype)


@njit(cache=True, fastmath=FAST_MATH, inline="always")
def _blur_rows(src, dst, g):
    """``dst[h, w] = Σ_k g[k] src[h, w + k − 5]`` with zeros outside (one plane ``[H, W]``)."""
    height, width = src.shape
    for h in range(height):
        s = src[h]
        d = dst[h]
        for w in range(width):
            d[w] = 0.0
        for k in range(WINDOW):
            off = k - RADIUS
            lo = max(0, -off)
            hi = min(width, width - off)
            gk = g[k]
            for w in range(lo, hi):  # unsigned indices: no wraparound test, so the loop vectorizes
                d[uintp(w)] += gk * s[uintp(w + off)]


@njit(cache=True, fastmath=FAST_MATH, inline="always")
def _blur_columns(src, dst, g):
    """``dst[h, w] = Σ_k g[k] src[h + k − 5, w]`` with zeros outside (one plane ``[H, W]``)."""
    height, width = src.shape
    for h in range(height):
        d = dst[h]
        for w in range(width):
            d[w] = 0.0
        for k in range(WINDOW):
            r = h + k - RADIUS
            if r < 0 or r >= height:
                continue
            s = src[r]
            gk = g[k]
            for w in range(width):
                d[w] += gk * s[w]


@njit(cache=True, fastmath=FAST_MATH, inline="always")
def _blur(src, tmp, dst, g):
    _blur_rows(src, tmp, g)
    _blur_columns(tmp, dst, g)


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def loss_forward(images, gts, g, lambda_dssim, c1, c2, losses, sq_errors, d_mu, d_xx, d_xy):
    """Per view ``v``: ``losses[v]`` (the loss), ``sq_errors[v]`` (Σ (clamp(x, 0, 1) − y)², for the PSNR), and the
    maps ``d_mu, d_xx, d_xy [V, C, H, W]`` = ∂S/∂μx, ∂S/∂E[x²], ∂S/∂E[xy]. ``images``, ``gts``: [V, H, W, C]."""
    num_views, height, width, channels = images.shape
    n = height * width * channels
    l1 = np.zeros((num_views, channels))
    ssim = np.zeros((num_views, channels))
    sq = np.zeros((num_views, channels))
    for task in prange(num_views * channels):
        v, c = task // channels, task % channels
        x = np.empty((height, width), images.dtype)
        y = np.empty((height, width), images.dtype)
        for h in range(height):
            for w in range(width):
                x[h, w] = images[v, h, w, c]
                y[h, w] = gts[v, h, w, c]
        tmp = np.empty((height, width), images.dtype)
        prod = np.empty((height, width), images.dtype)
        stats = np.empty((5, height, width), images.dtype)  # μx, μy, E[x²], E[y²], E[xy]
        _blur(x, tmp, stats[0], g)
        _blur(y, tmp, stats[1], g)
        for i, (a, b) in enumerate(((x, x), (y, y), (x, y))):
            for h in range(height):
                for w in range(width):
                    prod[h, w] = a[h, w] * b[h, w]
            _blur(prod, tmp, stats[2 + i], g)
        mu_x, mu_y, e_xx, e_yy, e_xy = stats[0], stats[1], stats[2], stats[3], stats[4]
        s_l1 = 0.0
        s_ssim = 0.0
        s_sq = 0.0
        for h in range(height):
            for w in range(width):
                mx, my = mu_x[h, w], mu_y[h, w]
                a1 = 2.0 * mx * my + c1
                a2 = 2.0 * (e_xy[h, w] - mx * my) + c2
                b1 = mx * mx + my * my + c1
                b2 = (e_xx[h, w] - mx * mx) + (e_yy[h, w] - my * my) + c2
                den = 1.0 / (b1 * b2)
                s = a1 * a2 * den
                s_ssim += s
                d_mu[v, c, h, w] = 2.0 * (my * (a2 - a1) - mx * s * (b2 - b1)) * den
                d_xx[v, c, h, w] = -s / b2
                d_xy[v, c, h, w] = 2.0 * a1 * den
                diff = x[h, w] - y[h, w]
                s_l1 += abs(diff)
                clamped = min(max(x[h, w], 0.0), 1.0) - y[h, w]
                s_sq += clamped * clamped
        l1[v, c] = s_l1
        ssim[v, c] = s_ssim
        sq[v, c] = s_sq
    for v in range(num_views):
        losses[v] = (1.0 - lambda_dssim) * l1[v].sum() / n + lambda_dssim * (1.0 - ssim[v].sum() / n)
        sq_errors[v] = sq[v].sum()


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def loss_backward(images, gts, g, lambda_dssim, grad_losses, d_mu, d_xx, d_xy, grad_images):
    """``grad_images [V, H, W, C]`` = ∂(Σ_v grad_losses[v]·losses[v])/∂images from :func:`loss_forward`'s maps."""
    num_views, height, width, channels = images.shape
    n = height * width * channels
    for task in prange(num_views * channels):
        v, c = task // channels, task % channels
        scale = -lambda_dssim * grad_losses[v] / n
        l1_scale = (1.0 - lambda_dssim) * grad_losses[v] / n
        tmp = np.empty((height, width), images.dtype)
        src = np.empty((height, width), images.dtype)
        blurred = np.empty((3, height, width), images.dtype)  # blur(G_μ), blur(G_xx), blur(G_xy)
        for i, d_map in enumerate((d_mu, d_xx, d_xy)):
            for h in range(height):
                for w in range(width):
                    src[h, w] = scale * d_map[v, c, h, w]
            _blur(src, tmp, blurred[i], g)
        b_mu, b_xx, b_xy = blurred[0], blurred[1], blurred[2]
        for h in range(height):
            for w in range(width):
                x = images[v, h, w, c]
                y = gts[v, h, w, c]
                diff = x - y
                sign = 1.0 if diff > 0 else (-1.0 if diff < 0 else 0.0)
                grad_images[v, h, w, c] = b_mu[h, w] + 2.0 * x * b_xx[h, w] + y * b_xy[h, w] + l1_scale * sign


class FusedPhotometricLoss(torch.autograd.Function):
    """(images [V, H, W, C], gts [V, H, W, C], λ) → (losses [V], Σ squared errors of the clamped images [V]); the
    second output carries no gradient (it gives the batch's PSNR)."""

    @staticmethod
    def forward(ctx, images, gts, lambda_dssim):
        x, y = as_numpy(images), as_numpy(gts)
        num_views, height, width, channels = x.shape
        g = window_1d(x.dtype)
        losses, sq_errors = np.empty(num_views, x.dtype), np.empty(num_views, np.float64)
        maps = tuple(np.empty((num_views, channels, height, width), x.dtype) for _ in range(3))
        with keeping_torch_threads():
            loss_forward(x, y, g, lambda_dssim, C1, C2, losses, sq_errors, *maps)
        ctx.arrays = (x, y, g, lambda_dssim, maps)
        sq = torch.from_numpy(sq_errors)
        ctx.mark_non_differentiable(sq)
        return torch.from_numpy(losses), sq

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_losses, _grad_sq):
        x, y, g, lambda_dssim, maps = ctx.arrays
        grad = np.empty_like(x)
        with keeping_torch_threads():
            loss_backward(x, y, g, lambda_dssim, as_numpy(grad_losses.to(torch.float64)), *maps, grad)
        return torch.from_numpy(grad), None, None


__all__ = ["FusedPhotometricLoss", "loss_backward", "loss_forward", "window_1d"]
