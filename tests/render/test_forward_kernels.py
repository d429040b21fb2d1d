"""The gradient-free render path (numba projection, binning and pixel boxes) against the differentiable torch path.

A render that needs no gradient projects in :mod:`omg4.render.forward_kernels` instead of with
:func:`project_gaussians`; it must give the same projection — visible set, radii, values within the input
precision (bit for bit in float32 where rounding decides) — hence the same tile lists and boxes from
:func:`bin_gaussians` (tested against gsplat's reference in ``test_rasterizer_binning.py``) and the same
images, for one view and several, on scenes that exercise the near/far cull, the Jacobian clamp, tiny
opacities and off-screen Gaussians.
"""

from __future__ import annotations

import pytest
import torch
from dense_reference import dense_rasterize, random_scene

from omg4.render import rasterize
from omg4.render.api import bin_gaussians, project_and_bin, rasterize_views
from omg4.render.binning import sigma_cutoff
from omg4.render.projection import RADIUS_MAX, fov_clamp_limits, project_gaussians

WIDTH, HEIGHT = 48, 36


def _scene(seed: int, n: int = 500):
    """Gaussians spread to 3× the field of view, some behind the camera or before the near plane, some with
    opacities below 1/255 (culled) or just above it (boxes shrink), some covariances huge."""
    sc = random_scene(seed, n, WIDTH, HEIGHT, scale=0.3)
    g = torch.Generator().manual_seed(seed + 100)
    R, t = sc.viewmat[:3, :3], sc.viewmat[:3, 3]
    pc = sc.means @ R.T + t
    spread = torch.rand(n, 2, generator=g, dtype=torch.float64) * 3 - 1
    pc[:, 0] = (spread[:, 0] * WIDTH - sc.K[0, 2]) / sc.K[0, 0] * pc[:, 2]
    pc[:, 1] = (spread[:, 1] * HEIGHT - sc.K[1, 2]) / sc.K[1, 1] * pc[:, 2]
    pc[:20, 2] = torch.linspace(-1.0, 0.19, 20, dtype=torch.float64)
    sc.means = (pc - t) @ R
    sc.opacities[20:40] = torch.linspace(1e-3, 6e-3, 20, dtype=torch.float64)
    sc.covars[40:50] *= 50.0
    return sc


def _reference(means, covars, opacities, views, viewmats, Ks, num_views, tile_size):
    viewmat, K = (viewmats[0], Ks[0]) if views is None else (viewmats[views], Ks[views])
    p = project_gaussians(means, covars, viewmat, K, WIDTH, HEIGHT, opacities=opacities)
    cutoff = sigma_cutoff(opacities)
    bins, boxes = bin_gaussians(p, cutoff, views, num_views, WIDTH, HEIGHT, tile_size)
    return p, bins, cutoff, boxes


def _views(num_views: int, dtype):
    """Rows of ``num_views`` random scenes stacked, with their cameras (``views`` None for one view)."""
    scenes = [_scene(seed) for seed in range(num_views)]
    cat = lambda name: torch.cat([getattr(s, name) for s in scenes]).to(dtype)  # noqa: E731
    views = None if num_views == 1 else torch.cat([torch.full((500,), v) for v in range(num_views)])
    viewmats = torch.stack([s.viewmat for s in scenes]).to(dtype)
    Ks = torch.stack([s.K for s in scenes]).to(dtype)
    return scenes, cat("means"), cat("covars"), cat("colors"), cat("opacities"), views, viewmats, Ks


@pytest.mark.parametrize("num_views", [1, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("tile_size", [16, 5])
def test_forward_kernels_give_the_differentiable_paths_projection_bins_and_boxes(num_views, dtype, tile_size):
    _, means, covars, _, opacities, views, viewmats, Ks = _views(num_views, dtype)
    p, bins, cutoff, boxes = project_and_bin(means, covars, opacities, views, viewmats, Ks, WIDTH, HEIGHT,
                                             near=0.2, far=1e10, eps2d=0.3, tile_size=tile_size)
    q, ref_bins, ref_cutoff, ref_boxes = _reference(means, covars, opacities, views, viewmats, Ks, num_views,
                                                    tile_size)
    vis = q.visible
    assert 100 < int(vis.sum()) < len(vis) - 60  # culled by depth, opacity and the image border alike
    assert torch.equal(p.visible, vis) and torch.equal(p.radii, q.radii)
    tol = dict(rtol=1e-12, atol=1e-9) if dtype == torch.float64 else dict(rtol=2e-6, atol=1e-4)
    for name in ("means2d", "depths", "cov2d_diag"):
        torch.testing.assert_close(getattr(p, name), getattr(q, name), **tol)
    torch.testing.assert_close(p.conics[vis], q.conics[vis], rtol=tol["rtol"] * 10, atol=tol["rtol"])
    assert torch.all(p.means2d[~vis] == 0)
    assert p.means2d.dtype == dtype and p.radii.dtype == torch.int32
    assert torch.equal(bins.tile_offsets, ref_bins.tile_offsets) and torch.equal(bins.gaussian_ids, ref_bins.gaussian_ids)
    assert bins.num_intersections > 2 * int(vis.sum())  # Gaussians span several tiles
    torch.testing.assert_close(cutoff, ref_cutoff, rtol=0, atol=0)
    assert torch.equal(boxes[vis], ref_boxes[vis])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_render_without_gradients_equals_the_differentiable_render(dtype):
    scenes, means, covars, colors, opacities, views, viewmats, Ks = _views(3, dtype)
    background = torch.tensor([0.2, 0.4, 0.1], dtype=dtype)
    leaves = [t.clone().requires_grad_() for t in (means, covars, colors, opacities)]
    with_grad = rasterize_views(*leaves, views, viewmats, Ks, WIDTH, HEIGHT, background=background, backend="cpu")
    with torch.no_grad():
        no_grad = rasterize_views(*leaves, views, viewmats, Ks, WIDTH, HEIGHT, background=background, backend="cpu")
    plain = rasterize_views(means, covars, colors, opacities, views, viewmats, Ks, WIDTH, HEIGHT,
                            background=background, backend="cpu")
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    assert float(with_grad.alpha.detach().max()) > 0.5
    for fast in (no_grad, plain):
        assert not fast.image.requires_grad
        for name in ("image", "alpha", "depth", "means2d"):
            torch.testing.assert_close(getattr(fast, name), getattr(with_grad, name).detach(), rtol=tol, atol=tol)
        assert torch.equal(fast.radii, with_grad.radii)
    one = scenes[1]
    single = rasterize(*(getattr(one, k).to(dtype) for k in ("means", "covars", "colors", "opacities")),
                       one.viewmat.to(dtype), one.K.to(dtype), WIDTH, HEIGHT, background=background, backend="cpu")
    torch.testing.assert_close(single.image, no_grad.image[1], rtol=tol, atol=tol)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_render_without_gradients_matches_the_dense_reference(seed):
    sc = random_scene(seed, 200, 37, 29, opacity=(0.3, 0.99), scale=0.12)
    r = rasterize(**sc.tensors(torch.float64, requires_grad=False), tile_size=8, backend="cpu")
    ref = dense_rasterize(**sc.tensors(torch.float64, requires_grad=False))
    assert float(ref.alpha.max()) > 0.5
    for name in ("image", "alpha", "depth"):
        torch.testing.assert_close(getattr(r, name), getattr(ref, name), rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_covariances_that_overflow_the_input_precision_are_culled_on_both_paths(dtype):
    """Finite covariances 1e17 and 1e20 times too large: the 2D determinant of the latter overflows float32 (not
    float64). Both paths cull exactly those, and render the rest alike; in float64 five more, 1e40 times too
    large, have boxes far beyond 2⁶³ pixels (capped, not overflowed)."""
    sc = random_scene(3, 60, WIDTH, HEIGHT, opacity=(0.3, 0.9))
    sc.covars[:5] *= 1e17
    sc.covars[5:10] *= 1e20
    if dtype == torch.float64:
        sc.covars[10:15] *= 1e40
    inputs = [getattr(sc, k).to(dtype) for k in ("means", "covars", "colors", "opacities")]
    cameras = (sc.viewmat.to(dtype)[None], sc.K.to(dtype)[None])
    fast = rasterize_views(*inputs, None, *cameras, WIDTH, HEIGHT, backend="cpu")
    slow = rasterize_views(*(t.clone().requires_grad_() for t in inputs), None, *cameras, WIDTH, HEIGHT, backend="cpu")
    assert torch.equal(fast.radii, slow.radii)
    assert bool((fast.radii[:5] > 2**24).all())  # boxes far wider than the image, within int32
    assert bool((fast.radii[5:10] > 0).all()) == (dtype == torch.float64)
    if dtype == torch.float64:
        assert bool((fast.radii[10:15] == RADIUS_MAX).all())
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    torch.testing.assert_close(fast.image, slow.image.detach(), rtol=tol, atol=tol)


def test_an_empty_render_without_gradients_shows_the_background():
    sc = random_scene(0, 10, WIDTH, HEIGHT)
    empty = {k: v[:0] if k in ("means", "covars", "colors", "opacities") else v
             for k, v in sc.tensors(torch.float32, requires_grad=False).items()}
    r = rasterize(**empty, backend="cpu")
    assert r.means2d.shape == (0, 2) and r.radii.shape == (0,)
    torch.testing.assert_close(r.image, sc.background.float().expand(HEIGHT, WIDTH, 3))
    assert float(r.alpha.abs().max()) == 0.0


def _assert_same_projection_and_bins(means, covars, opacities, viewmat, K, *, near=0.2, tile_size=8,
                                     size=(WIDTH, HEIGHT)):
    """The fast path's visible set, radii, tile lists and boxes equal the torch path's exactly; returns both
    projections (fast, torch)."""
    width, height = size
    p, bins, cutoff, boxes = project_and_bin(means, covars, opacities, None, viewmat[None], K[None], width, height,
                                             near=near, far=1e10, eps2d=0.3, tile_size=tile_size)
    q = project_gaussians(means, covars, viewmat, K, width, height, opacities=opacities, near=near)
    ref_bins, ref_boxes = bin_gaussians(q, sigma_cutoff(opacities), None, 1, width, height, tile_size)
    assert torch.equal(p.visible, q.visible) and torch.equal(p.radii, q.radii)
    assert torch.equal(bins.gaussian_ids, ref_bins.gaussian_ids) and torch.equal(bins.tile_offsets, ref_bins.tile_offsets)
    assert torch.equal(boxes[q.visible], ref_boxes[q.visible])
    return p, q


def test_equal_depths_keep_gaussian_order_in_every_tile():
    """A fronto-parallel plane of Gaussians at one depth: every tile's list is in Gaussian order, as torch's
    stable sort leaves it."""
    sc = random_scene(5, 300, WIDTH, HEIGHT, depth=(3.0, 3.0))
    sc.viewmat[:3, :3] = torch.eye(3, dtype=torch.float64)
    sc.viewmat[:3, 3] = 0.0
    sc.means[:, 2] = 3.0
    f32 = [getattr(sc, k).float() for k in ("means", "covars", "opacities")]
    p, _ = _assert_same_projection_and_bins(*f32, sc.viewmat.float(), sc.K.float())
    assert int(p.visible.sum()) > 200
    _, bins, _, _ = project_and_bin(*f32, None, sc.viewmat.float()[None], sc.K.float()[None], WIDTH, HEIGHT, near=0.2,
                                    far=1e10, eps2d=0.3, tile_size=8)
    for t in range(bins.tile_offsets.numel() - 1):
        ids = bins.gaussian_ids[bins.tile_offsets[t]:bins.tile_offsets[t + 1]]
        assert bool((ids[1:] > ids[:-1]).all())
    assert int(bins.tile_offsets.diff().max()) > 20  # tiles really hold many tied Gaussians


def test_float32_boundaries_fall_as_on_the_torch_path():
    """Opacities exactly float32(1/255) (box half-width 0: culled), depths exactly float32(near) (kept) and one
    step below it (culled): decided in float32 as on the torch path."""
    sc = random_scene(6, 400, WIDTH, HEIGHT)
    means = (sc.means @ sc.viewmat[:3, :3].T + sc.viewmat[:3, 3]).float()  # camera coordinates: an identity camera
    viewmat = torch.eye(4)
    near = torch.tensor(0.7, dtype=torch.float32)
    means[50:75, 2] = near
    means[75:100, 2] = torch.nextafter(near, torch.tensor(0.0))
    opacities = sc.opacities.float()
    opacities[:50] = torch.tensor(1 / 255, dtype=torch.float32)
    p, _ = _assert_same_projection_and_bins(means, sc.covars.float(), opacities, viewmat, sc.K.float(), near=0.7)
    assert not bool(p.visible[:50].any()) and not bool(p.visible[75:100].any()) and int(p.visible.sum()) > 150
    assert int(p.visible[50:75].sum()) >= 5  # at the near plane (those still inside the image)


@pytest.mark.parametrize("fx", [281.82, 691.04])  # focal lengths whose clamp limits round differently
# when the kernel divides instead of multiplying by the reciprocal as torch does
def test_needles_are_kept_or_culled_as_on_the_torch_path(fx):
    """Needle-thin Gaussians (300 × 10⁻³) in and far beside the field of view of a rotated 320×180 camera (the
    Jacobian clamp active for many): their float32 2D determinant is rounding noise, and the fast path rounds
    every step as the torch path does — the same conics and 2D variances bit for bit, so the same decisions."""
    width, height, n = 320, 180, 3000
    g = torch.Generator().manual_seed(int(fx))
    sc = random_scene(int(fx), n, width, height)
    K = torch.tensor([[fx, 0, 161.3], [0, fx * 1.01, 88.9], [0, 0, 1]], dtype=torch.float64)
    depth = 2 + 3 * torch.rand(n, generator=g, dtype=torch.float64)
    pixels = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 3 - 1) * torch.tensor([width, height])
    pc = torch.stack([(pixels[:, 0] - K[0, 2]) / K[0, 0] * depth, (pixels[:, 1] - K[1, 2]) / K[1, 1] * depth, depth], 1)
    R, t = sc.viewmat[:3, :3], sc.viewmat[:3, 3]
    means = ((pc - t) @ R).float()
    axes = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64)).Q
    covars = (axes @ torch.diag(torch.tensor([300.0, 1e-3, 1e-3], dtype=torch.float64)) ** 2 @ axes.mT).float()
    opacities = torch.full((n,), 0.8)
    Kf = K.float()
    p, q = _assert_same_projection_and_bins(means, covars, opacities, sc.viewmat.float(), Kf, tile_size=16,
                                            size=(width, height))
    assert torch.equal(p.conics, q.conics) and torch.equal(p.cov2d_diag, q.cov2d_diag)
    assert torch.equal(p.means2d, q.means2d) and torch.equal(p.depths, q.depths)
    in_view = (pixels[:, 0] > 0) & (pixels[:, 0] < width) & (pixels[:, 1] > 0) & (pixels[:, 1] < height)
    kept = float(p.visible[in_view].float().mean())
    assert 0.05 < kept < 0.95  # many decisions really hang on the float32 determinant
    lim_xn, lim_xp, _, _ = (float(v) for v in fov_clamp_limits(Kf, width, height))
    slope = pc[:, 0] / pc[:, 2]
    clamped = (slope < -lim_xn) | (slope > lim_xp)
    assert int((clamped & q.visible).sum()) > 20  # the clamp matters for kept needles


def test_a_camera_that_needs_gradients_takes_the_differentiable_path():
    sc = random_scene(7, 80, WIDTH, HEIGHT)
    inputs = {k: v for k, v in sc.tensors(torch.float32, requires_grad=False).items() if k != "background"}
    inputs["viewmat"] = inputs["viewmat"].clone().requires_grad_()
    inputs["K"] = inputs["K"].clone().requires_grad_()
    r = rasterize(**inputs, backend="cpu")
    r.image.sum().backward()
    assert float(inputs["viewmat"].grad.abs().sum()) > 0 and float(inputs["K"].grad.abs().sum()) > 0
