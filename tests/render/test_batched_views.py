"""Several views in one rasterizer call equal the views rendered one by one (one rasterizer call per training step).

The batched CPU path projects, bins and composites the rows of all views in one pass (one
kernel launch forward and one backward); images, alpha, depth, projected means, radii and
the gradient of every input must match per-view calls. The same holds one level up, for
:func:`omg4.render.view.render_views` on a Real-Time4DGS model at different times.
"""

from __future__ import annotations

import pytest
import torch
from dense_reference import random_scene

from omg4.data.scene import Camera
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.render import rasterize
from omg4.render.api import rasterize_views
from omg4.render.view import render_view, render_views

WIDTH, HEIGHT = 37, 29
INPUTS = ("means", "covars", "colors", "opacities")


def _leaf(scene, dtype):
    return {k: getattr(scene, k).to(dtype).clone().requires_grad_(True) for k in INPUTS}


def _weights(shape, seed, dtype):
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)


@pytest.mark.parametrize("dtype, count", [(torch.float64, 3), (torch.float32, 3), (torch.float64, 2)])
def test_rasterize_views_equals_per_view_calls(dtype, count):
    scenes = [random_scene(seed, n, WIDTH, HEIGHT) for seed, n in ((0, 90), (1, 140), (2, 60))][:count]
    background = torch.tensor([0.2, 0.4, 0.1], dtype=dtype)
    singles = []
    for i, sc in enumerate(scenes):
        x = _leaf(sc, dtype)
        r = rasterize(x["means"], x["covars"], x["colors"], x["opacities"], sc.viewmat.to(dtype), sc.K.to(dtype),
                      WIDTH, HEIGHT, background=background, backend="cpu")
        loss = (r.image * _weights(r.image.shape, i, dtype)).sum() + (r.depth * _weights(r.depth.shape, 9 + i, dtype)).sum()
        loss.backward()
        singles.append((r, x))

    xs = [_leaf(sc, dtype) for sc in scenes]
    cat = {k: torch.cat([x[k] for x in xs]) for k in INPUTS}
    views = torch.cat([torch.full((sc.means.shape[0],), i, dtype=torch.int64) for i, sc in enumerate(scenes)])
    out = rasterize_views(cat["means"], cat["covars"], cat["colors"], cat["opacities"], views,
                          torch.stack([sc.viewmat for sc in scenes]).to(dtype),
                          torch.stack([sc.K for sc in scenes]).to(dtype), WIDTH, HEIGHT, background=background,
                          backend="cpu")
    assert out.image.shape == (count, HEIGHT, WIDTH, 3) and out.alpha.shape == (count, HEIGHT, WIDTH, 1)
    loss = sum((out.image[i] * _weights(out.image[i].shape, i, dtype)).sum()
               + (out.depth[i] * _weights(out.depth[i].shape, 9 + i, dtype)).sum() for i in range(count))
    loss.backward()
    tol = dict(rtol=1e-10, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-4, atol=1e-5)
    start = 0
    for i, (r, x) in enumerate(singles):
        rows = slice(start, start + scenes[i].means.shape[0])
        start = rows.stop
        assert float(r.alpha.detach().max()) > 0.5  # the views are not empty
        for name in ("image", "alpha", "depth"):
            torch.testing.assert_close(getattr(out, name)[i], getattr(r, name), **tol)
        torch.testing.assert_close(out.means2d[rows], r.means2d, **tol)
        assert torch.equal(out.radii[rows], r.radii)
        for k in INPUTS:
            assert float(x[k].grad.abs().max()) > 0
            torch.testing.assert_close(xs[i][k].grad, x[k].grad, **tol)


def test_rasterize_views_checks_the_view_index():
    sc = random_scene(0, 10, WIDTH, HEIGHT)
    args = (sc.means, sc.covars, sc.colors, sc.opacities)
    two = (torch.stack([sc.viewmat] * 2), torch.stack([sc.K] * 2))
    with pytest.raises(ValueError, match="view of each"):
        rasterize_views(*args, None, *two, WIDTH, HEIGHT, backend="cpu")
    with pytest.raises(ValueError, match="views must lie"):
        rasterize_views(*args, torch.full((10,), 2, dtype=torch.int64), *two, WIDTH, HEIGHT, backend="cpu")


def _model(seed=0, n=200):
    g = torch.Generator().manual_seed(seed)
    cfg = GaussianConfig(time_range=(0.0, 2.0))
    params = {
        "xyz": torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.6,
        "t": torch.rand(n, 1, generator=g, dtype=torch.float64) * 2.0,
        "scaling": torch.log(0.05 + 0.1 * torch.rand(n, 3, generator=g, dtype=torch.float64)),
        "scaling_t": torch.log(0.2 + 0.5 * torch.rand(n, 1, generator=g, dtype=torch.float64)),
        "rotation": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "rotation_r": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "opacity": torch.randn(n, 1, generator=g, dtype=torch.float64),
        "features_dc": torch.randn(n, 1, 3, generator=g, dtype=torch.float64) * 0.5,
        "features_rest": torch.randn(n, cfg.num_coeffs - 1, 3, generator=g, dtype=torch.float64) * 0.1,
    }
    return Gaussians4D({k: v.requires_grad_(True) for k, v in params.items()}, cfg)


def _camera(angle, name):
    c, s = torch.cos(torch.tensor(angle)).item(), torch.sin(torch.tensor(angle)).item()
    R = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3], viewmat[:3, 3] = R, torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64)
    K = torch.tensor([[40.0, 0, WIDTH / 2], [0, 40.0, HEIGHT / 2], [0, 0, 1]], dtype=torch.float64)
    return Camera(name=name, width=WIDTH, height=HEIGHT, K=K.numpy(), viewmat=viewmat.numpy())


def test_render_views_equals_render_view_per_view_with_gradients():
    cams = [_camera(0.0, "a"), _camera(0.4, "b"), _camera(-0.3, "c")]
    times = [0.3, 1.1, 1.1]
    single, batched = _model(), _model()
    for i, (cam, tau) in enumerate(zip(cams, times)):
        r, _ = render_view(single, cam, tau, backend="cpu")
        (r.image * _weights(r.image.shape, i, torch.float64)).sum().backward()
    out, sl = render_views(batched, cams, times, backend="cpu")
    assert sl.views is not None and sorted(set(sl.views.tolist())) == [0, 1, 2]
    sum((out.image[i] * _weights(out.image[i].shape, i, torch.float64)).sum() for i in range(3)).backward()
    for i, (cam, tau) in enumerate(zip(cams, times)):
        with torch.no_grad():
            r, _ = render_view(single, cam, tau, backend="cpu")
        torch.testing.assert_close(out.image[i].detach(), r.image, rtol=1e-10, atol=1e-12)
    for k, p in single.params.items():
        assert float(p.grad.abs().max()) > 0, k
        torch.testing.assert_close(batched.params[k].grad, p.grad, rtol=1e-9, atol=1e-12)
