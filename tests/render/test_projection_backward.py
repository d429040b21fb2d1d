"""The CPU rasterizer's differentiable projection on the numba kernels (render.api._Projection,
render.projection_kernels) gives the torch projection's values and gradients (OMG4_KERNELS=reference) — in float64 to
rounding, in float32 to float tolerance — for one view and several, Gaussians whose Jacobian is clamped at the field of
view, ones behind the near plane, near-degenerate covariances, one Gaussian and none."""

from __future__ import annotations

import pytest
import torch

from omg4.kernels import using_kernels
from omg4.render import rasterize
from omg4.render.api import rasterize_views

WIDTH, HEIGHT = 64, 48


def camera(dtype, x: float = 0.1):
    viewmat = torch.eye(4, dtype=dtype)
    angle = torch.tensor(0.2 + x, dtype=torch.float64)
    viewmat[0, 0], viewmat[0, 2], viewmat[2, 0], viewmat[2, 2] = angle.cos(), angle.sin(), -angle.sin(), angle.cos()
    viewmat[:3, 3] = torch.tensor([x, -0.2, 3.0], dtype=dtype)
    K = torch.tensor([[60.0, 0, 32], [0, 55.0, 24], [0, 0, 1]], dtype=dtype)
    return viewmat, K


def gaussians(dtype, n: int, seed: int = 0, spread: float = 1.0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * spread
    a = torch.randn(n, 3, 3, generator=g) * 0.08
    covars = a @ a.transpose(1, 2) + 1e-4 * torch.eye(3)
    covars[::7] = covars[::7] + 0.01 * torch.randn(covars[::7].shape, generator=g)  # not quite symmetric
    colors, opacities = torch.rand(n, 3, generator=g), torch.rand(n, generator=g) * 0.9 + 0.05
    return [t.to(dtype) for t in (means, covars, colors, opacities)]


def gradients(render, inputs, seed: int = 1):
    """Image and depth, and the gradients of a fixed random weighting of them, for each kernel choice."""
    out = {}
    for mode in ("fused", "reference"):
        with using_kernels(mode):
            leaves = [t.clone().requires_grad_() for t in inputs]
            r = render(*leaves)
            g = torch.Generator().manual_seed(seed)
            loss = (r.image * torch.rand(r.image.shape, generator=g, dtype=r.image.dtype)).sum() \
                + 0.1 * (r.depth * torch.rand(r.depth.shape, generator=g, dtype=r.depth.dtype)).sum()
            loss.backward()
            out[mode] = (r.image.detach(), r.depth.detach(), r.means2d.grad, *(t.grad for t in leaves))
    return out["fused"], out["reference"]


def assert_close(fused, reference, rtol):
    names = ("image", "depth", "means2d grad", "means grad", "covars grad", "colors grad", "opacities grad")
    for name, a, b in zip(names, fused, reference):
        scale = float(b.abs().max()) if b.numel() else 0.0
        torch.testing.assert_close(a, b, rtol=0, atol=rtol * max(scale, 1.0), msg=name)


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-11), (torch.float32, 1e-5)])
def test_one_view(dtype, rtol):
    viewmat, K = camera(dtype)
    fused, reference = gradients(lambda *t: rasterize(*t, viewmat, K, WIDTH, HEIGHT, backend="cpu"),
                                 gaussians(dtype, 300))
    assert float(reference[3].abs().max()) > 1.0  # the gradients are not all zero
    assert_close(fused, reference, rtol)


def test_several_views_each_row_its_own():
    dtype = torch.float64
    cams = [camera(dtype, x) for x in (0.1, -0.4, 0.5)]
    viewmats, Ks = torch.stack([c[0] for c in cams]), torch.stack([c[1] for c in cams])
    views = torch.arange(240) % 3
    fused, reference = gradients(lambda *t: rasterize_views(*t, views, viewmats, Ks, WIDTH, HEIGHT, backend="cpu"),
                                 gaussians(dtype, 240, seed=2))
    assert_close(fused, reference, 1e-11)


def test_clamped_jacobians_behind_the_camera_and_degenerate_covariances():
    """Spread far beyond the view (the Jacobian's clamp at the field of view, rows behind the near plane), and thin
    covariances whose 2D determinant is barely positive."""
    dtype = torch.float64
    means, covars, colors, opacities = gaussians(dtype, 400, seed=3, spread=4.0)
    covars[::5] = torch.diag_embed(torch.tensor([1e-3, 1e-9, 1e-9], dtype=dtype)).expand(len(covars[::5]), 3, 3)
    # wide Gaussians beside the view: their centres past the clamp (x/z > 1.3 tan of the half field of view),
    # their boxes reaching into the image
    side = torch.linspace(-1.0, 1.0, len(means[1::5]), dtype=dtype)
    means[1::5] = torch.stack([side.sign() * (2.2 + 0.4 * side.abs()), 1.5 * side, torch.full_like(side, 0.3)], dim=1)
    covars[1::5] = 0.3 * torch.eye(3, dtype=dtype)
    viewmat, K = camera(dtype)
    fused, reference = gradients(lambda *t: rasterize(*t, viewmat, K, WIDTH, HEIGHT, backend="cpu"),
                                 [means, covars, colors, opacities], seed=4)
    assert_close(fused, reference, 1e-10)


@pytest.mark.parametrize("n", [0, 1])
def test_none_and_one(n):
    dtype = torch.float64
    means, covars, colors, opacities = gaussians(dtype, max(n, 1), seed=5)
    means[:, 2] = 0.0  # in front of the camera
    inputs = [t[:n] for t in (means, covars, colors, opacities)]
    viewmat, K = camera(dtype)
    fused, reference = gradients(lambda *t: rasterize(*t, viewmat, K, WIDTH, HEIGHT, backend="cpu"), inputs)
    assert_close(fused, reference, 1e-11)
