"""EWA projection vs gsplat 1.5.3's pure-torch ``_fully_fused_projection`` (runs on CPU)."""

from __future__ import annotations

import pytest
import torch
from dense_reference import random_scene

from omg4.render.projection import fov_clamp_limits, max_radius, project_gaussians

gsplat_torch = pytest.importorskip("gsplat.cuda._torch_impl")


def _wide_scene(seed=0, n=400):
    """Gaussians spread to 3× the field of view with large covariances: the Jacobian clamp is active."""
    sc = random_scene(seed, n, 48, 36, scale=0.6)
    g = torch.Generator().manual_seed(seed + 100)
    R, t = sc.viewmat[:3, :3], sc.viewmat[:3, 3]
    pc = sc.means @ R.T + t
    spread = torch.rand(n, 2, generator=g, dtype=torch.float64) * 3 - 1  # x/z, y/z in [-1, 2]·FoV
    pc[:, 0] = (spread[:, 0] * sc.width - sc.K[0, 2]) / sc.K[0, 0] * pc[:, 2]
    pc[:, 1] = (spread[:, 1] * sc.height - sc.K[1, 2]) / sc.K[1, 1] * pc[:, 2]
    pc[:20, 2] = torch.linspace(-1.0, 0.19, 20, dtype=torch.float64)  # behind the camera / before near
    sc.means = (pc - t) @ R
    return sc


def _gsplat(sc, means, covars, near=0.2):
    radii, means2d, depths, conics, _ = gsplat_torch._fully_fused_projection(
        means, covars, sc.viewmat.to(means.dtype)[None], sc.K.to(means.dtype)[None], sc.width, sc.height,
        eps2d=0.3, near_plane=near)
    return radii[0], means2d[0], depths[0], conics[0]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_projection_matches_gsplat_torch(dtype):
    sc = _wide_scene()
    means = sc.means.to(dtype).requires_grad_()
    covars = sc.covars.to(dtype).requires_grad_()
    p = project_gaussians(means, covars, sc.viewmat.to(dtype), sc.K.to(dtype), sc.width, sc.height)
    means_g = sc.means.to(dtype).requires_grad_()
    covars_g = sc.covars.to(dtype).requires_grad_()
    radii_g, means2d_g, depths_g, conics_g = _gsplat(sc, means_g, covars_g)

    vis = p.visible
    assert torch.equal(p.radii, radii_g)
    assert 50 < int(vis.sum()) < len(vis)
    lim_xn, lim_xp, _, _ = fov_clamp_limits(sc.K, sc.width, sc.height)
    pc = sc.means @ sc.viewmat[:3, :3].T + sc.viewmat[:3, 3]
    clamped = (pc[:, 0] / pc[:, 2] < -lim_xn) | (pc[:, 0] / pc[:, 2] > lim_xp)
    assert int((clamped & vis).sum()) >= 5  # the clamp matters for visible Gaussians
    tol = dict(rtol=1e-12, atol=1e-9) if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(p.means2d[vis], means2d_g[vis], **tol)
    torch.testing.assert_close(p.depths, depths_g, **tol)
    torch.testing.assert_close(p.conics[vis], conics_g[vis], rtol=tol["rtol"], atol=tol["rtol"])
    z_ok = (depths_g >= 0.2).detach()
    assert torch.all(p.means2d[~vis] == 0) and torch.all(p.conics[~z_ok] == 0)

    g = torch.Generator().manual_seed(7)
    w2, w3, wd = (torch.randn(s, generator=g, dtype=torch.float64).to(dtype) for s in ((len(vis), 2), (len(vis), 3),
                                                                                        (len(vis),)))
    mask = vis.to(dtype)
    loss = lambda m2, c, d: ((m2 * w2).sum(-1) * mask + (c * w3).sum(-1) * mask * 100 + d * wd * mask).sum()
    loss(p.means2d, p.conics, p.depths).backward()
    loss(means2d_g, conics_g, depths_g).backward()
    gtol = dict(rtol=1e-10, atol=1e-10) if dtype == torch.float64 else dict(rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(means.grad, means_g.grad, **gtol)
    torch.testing.assert_close(covars.grad, covars_g.grad, **gtol)
    assert means.grad[~vis].abs().max() == 0 and torch.isfinite(covars.grad).all()


def test_near_far_culling_and_safe_gradients():
    sc = _wide_scene(seed=1)
    means = sc.means.clone().requires_grad_()
    p = project_gaussians(means, sc.covars, sc.viewmat, sc.K, sc.width, sc.height, near=0.2, far=4.0)
    z = (sc.means @ sc.viewmat[:3, :3].T + sc.viewmat[:3, 3])[:, 2]
    assert not p.visible[(z < 0.2) | (z > 4.0)].any()
    (p.means2d.sum() + p.conics.sum()).backward()
    assert torch.isfinite(means.grad).all()
    culled = (z < 0.2) | (z > 4.0)
    assert culled.sum() >= 20 and torch.all(means.grad[culled] == 0)
    assert means.grad[~culled].abs().sum() > 0


def test_opacity_aware_radii():
    sc = random_scene(5, 300, 40, 30, scale=0.2, opacity=(0.0, 1.0))
    p = project_gaussians(sc.means, sc.covars, sc.viewmat, sc.K, sc.width, sc.height, opacities=sc.opacities)
    radii_g, means2d_g, _, conics_g = _gsplat(sc, sc.means, sc.covars)
    a, b, c = conics_g.unbind(-1)
    det = a * c - b * b
    cov_diag = torch.stack([c / det, a / det], -1)  # inverse of the conic
    extend = torch.sqrt(2 * torch.log(sc.opacities * 255)).clamp(max=3.33)
    expected = torch.ceil(extend[:, None] * torch.sqrt(cov_diag))
    keep = (radii_g > 0).all(-1) & (sc.opacities >= 1 / 255)
    m, r = means2d_g, expected
    keep &= (m[:, 0] + r[:, 0] > 0) & (m[:, 0] - r[:, 0] < sc.width) & (m[:, 1] + r[:, 1] > 0) & (
        m[:, 1] - r[:, 1] < sc.height)
    assert int((sc.opacities < 1 / 255).sum()) >= 1
    assert torch.equal(p.visible, keep)
    assert torch.equal(p.radii[keep], expected[keep].int())
    assert torch.all(p.radii[keep] < radii_g[keep] + 1)  # never larger than the 3.33σ box
    assert torch.equal(max_radius(p.radii), p.radii.max(-1).values)


@pytest.mark.parametrize("grad", [True, False], ids=["torch projection", "numba projection"])
def test_a_box_that_ends_exactly_at_an_image_edge_is_culled(grad):
    """gsplat's rule, written out: a Gaussian is culled when mean ± radius lies at or beyond an image edge, i.e.
    it is kept only while mean + radius > 0 and mean − radius < size on both axes. Positions are exact binary
    fractions, so the projected means land exactly on the edges (K: f = 64, principal point at the origin)."""
    from omg4.render import rasterize

    width, height, step = 32, 24, 2.0 ** -6
    K = torch.tensor([[64.0, 0.0, 0.0], [0.0, 64.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    covar = 1e-6 * torch.eye(3, dtype=torch.float64)  # the 0.3 px² dilation dominates: a box of radius 2 anywhere
    radius = 2.0
    inside = {"x": 16.0, "y": 12.0}
    cases = []
    for axis, size in (("x", width), ("y", height)):
        for edge, outward in ((-radius, -1.0), (size + radius, 1.0)):
            for shift, kept in ((0.0, False), (-outward * step, True)):  # on the edge; a 64th of a pixel inside
                pixel = dict(inside, **{axis: edge + shift})
                cases.append(([pixel["x"] / 64.0, pixel["y"] / 64.0, 1.0], kept))
    means = torch.tensor([c for c, _ in cases], dtype=torch.float64)
    covars = covar.expand(len(cases), 3, 3).clone()
    if grad:
        radii = project_gaussians(means, covars, viewmat, K, width, height).radii.amax(-1)
    else:  # no gradient: the rasterizer projects in numba and reports the larger radius of each box
        radii = rasterize(means, covars, torch.ones(len(cases), 3, dtype=torch.float64),
                          torch.full((len(cases),), 0.9, dtype=torch.float64), viewmat, K, width, height,
                          backend="cpu").radii
    assert radii.tolist() == [2 if kept else 0 for _, kept in cases]
