"""The dense reference rasterizer itself: finite differences (float64) and closed forms."""

from __future__ import annotations

import math

import pytest
import torch
from dense_reference import dense_rasterize, random_scene

from omg4.render import rasterize


def _gradcheck(scene, **kw):
    t = scene.tensors(torch.float64)
    names = ("means", "covars", "colors", "opacities", "background")

    def fn(*args):
        r = dense_rasterize(**{**t, **dict(zip(names, args))}, **kw)
        return r.image, r.alpha, r.depth  # every output element: the reference is cheap

    return torch.autograd.gradcheck(fn, tuple(t[n] for n in names), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_dense_reference_matches_finite_differences():
    scene = random_scene(3, 5, 7, 6, scale=0.4)
    assert dense_rasterize(**scene.tensors()).alpha.max() > 0.5  # Gaussians really cover pixels
    assert _gradcheck(scene)


def test_dense_reference_matches_finite_differences_when_saturated():
    scene = random_scene(4, 12, 6, 5, scale=0.6, opacity=(0.97, 1.0), pixel_centres=True)
    assert int((scene.opacities > 0.99).sum()) >= 2  # the alpha cap is active at their centre pixels
    r = dense_rasterize(**scene.tensors(), alpha_max=0.99)
    assert r.n_terminated >= 5  # early termination is exercised
    assert _gradcheck(scene, alpha_max=0.99)


def _axis_scene(dtype=torch.float64):
    """Two isotropic Gaussians on the optical axis; closed-form pixel values."""
    f, cx, cy, W, H = 20.0, 5.0, 4.0, 10, 8
    K = torch.tensor([[f, 0, cx], [0, f, cy], [0, 0, 1]], dtype=dtype)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.05, 0.0, 4.0]], dtype=dtype)
    s = torch.tensor([0.1, 0.3], dtype=dtype)
    covars = torch.eye(3, dtype=dtype)[None] * (s**2)[:, None, None]
    colors = torch.tensor([[1.0, 0.2, 0.0], [0.0, 0.5, 1.0]], dtype=dtype)
    opacities = torch.tensor([0.7, 0.9], dtype=dtype)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    return dict(means=means, covars=covars, colors=colors, opacities=opacities, viewmat=torch.eye(4, dtype=dtype),
                K=K, width=W, height=H, background=bg)


def _closed_form(px, py):
    """Expected (rgb, alpha, depth) at pixel (px, py) of :func:`_axis_scene`, by hand in float64."""
    f, cx, cy, eps = 20.0, 5.0, 4.0, 0.3
    out, T, depth = [0.0, 0.0, 0.0], 1.0, 0.0
    layers = [((0.0, 0.0, 2.0), 0.1, 0.7, (1.0, 0.2, 0.0)), ((0.05, 0.0, 4.0), 0.3, 0.9, (0.0, 0.5, 1.0))]
    for (x, y, z), s, o, c in layers:
        u, v = f * x / z + cx, f * y / z + cy
        # J Σ Jᵀ + eps·I with Σ = s²·I, y = 0: diagonal, J = [[f/z, 0, −f·x/z²], [0, f/z, 0]]
        var = (f * s / z) ** 2 + eps
        var_x = var + (f * x / z / z) ** 2 * s**2
        dx, dy = u - (px + 0.5), v - (py + 0.5)
        alpha = min(0.999, o * math.exp(-0.5 * (dx * dx / var_x + dy * dy / var)))
        if alpha < 1 / 255:
            continue
        out = [a + ci * alpha * T for a, ci in zip(out, c)]
        depth += z * alpha * T
        T *= 1 - alpha
    return [a + T * b for a, b in zip(out, (0.1, 0.2, 0.3))], 1 - T, depth


@pytest.mark.parametrize("pixel", [(5, 4), (4, 4), (6, 3), (2, 6)])
def test_closed_form_two_gaussians(pixel):
    px, py = pixel
    rgb, alpha, depth = _closed_form(px, py)
    for r in (dense_rasterize(**_axis_scene()), rasterize(**_axis_scene(), backend="cpu")):
        assert torch.allclose(r.image[py, px], torch.tensor(rgb, dtype=torch.float64), rtol=1e-12, atol=1e-12)
        assert abs(float(r.alpha[py, px, 0]) - alpha) < 1e-12
        assert abs(float(r.depth[py, px, 0]) - depth) < 1e-12
