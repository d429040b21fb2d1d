"""gsplat backend: the adapter on CPU (with a stand-in for ``gsplat.rasterization``) and, on CUDA,
the same-image check against the CPU backend."""

from __future__ import annotations

import pytest
import torch
from dense_reference import random_scene

from omg4.render import rasterize
from omg4.render.projection import project_gaussians

gsplat = pytest.importorskip("gsplat")
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat's rasterizer needs CUDA")


def rel_err(a, b):
    b = b.detach().double().cpu()
    scale = float(b.abs().max())
    assert scale > 0
    return float((a.detach().double().cpu() - b).abs().max()) / scale


def fake_rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, calls=None, **kw):
    """A CPU stand-in for ``gsplat.rasterization`` with its batch axis (``means [B, M, 3]``, one camera per batch
    entry): our projection and a differentiable toy render of the Gaussians it keeps."""
    if calls is not None:
        calls.update(kw, quats=quats, scales=scales, viewmats=viewmats.shape, Ks=Ks.shape, means=means.shape)
    projected = [project_gaussians(means[b], kw["covars"][b], viewmats[b, 0], Ks[b, 0], width, height,
                                   opacities=opacities[b]) for b in range(means.shape[0])]
    means2d = torch.stack([p.means2d for p in projected])[:, None]  # [B, 1, M, 2] non-leaf, as info["means2d"]
    radii = torch.stack([p.radii for p in projected])[:, None]
    renders, alphas = [], []
    for b, p in enumerate(projected):
        kept = (p.radii > 0).all(-1)
        m = torch.where(kept[:, None], means2d[b, 0], 0.0)
        feats = torch.cat([colors[b], p.depths[:, None]], -1)  # [M, C+1]
        w = torch.where(kept, torch.exp(-((m - 3.0) ** 2).sum(-1)), 0.0)  # any differentiable function of means2d
        render = (w[:, None] * feats).sum(0).expand(height, width, feats.shape[1])
        if kw["backgrounds"] is not None:
            render = render + torch.cat([kw["backgrounds"][b, 0], torch.zeros(1)])
        renders.append(render)
        alphas.append(w.sum().clamp(max=1).expand(height, width, 1))
    return torch.stack(renders)[:, None], torch.stack(alphas)[:, None], {"means2d": means2d, "radii": radii}


def test_adapter_maps_gsplat_outputs(monkeypatch):
    """Checks the plumbing: arguments passed, channel split, radii reduction, means2d gradient hook."""
    calls = {}
    monkeypatch.setattr(gsplat, "rasterization", lambda *a, **kw: fake_rasterization(*a, calls=calls, **kw))
    sc = random_scene(0, 12, 10, 8, scale=0.2)
    t = sc.tensors(torch.float32)
    r = rasterize(**t, backend="gsplat")
    assert calls["quats"] is None and calls["scales"] is None and calls["covars"].shape == (1, 12, 3, 3)
    assert calls["render_mode"] == "RGB+D" and calls["packed"] is False and calls["eps2d"] == 0.3
    assert calls["near_plane"] == 0.2 and calls["viewmats"] == (1, 1, 4, 4) and calls["backgrounds"].shape == (1, 1, 3)
    assert r.image.shape == (8, 10, 3) and r.depth.shape == (8, 10, 1) and r.alpha.shape == (8, 10, 1)
    p = project_gaussians(t["means"], t["covars"], t["viewmat"], t["K"], 10, 8, opacities=t["opacities"])
    assert torch.equal(r.radii, p.radii.max(-1).values) and r.radii.dtype == torch.int32
    (r.image.sum() + r.depth.sum()).backward()
    # expected ∂L/∂means2d of the stand-in, computed directly
    m = p.means2d.detach().clone().requires_grad_()
    w = torch.exp(-((m - 3.0) ** 2).sum(-1))
    feats = torch.cat([t["colors"].detach(), p.depths.detach()[:, None]], -1)
    ((w[:, None] * feats).sum(0).sum() * 80).backward()
    vis = p.visible
    assert vis.sum() > 3
    torch.testing.assert_close(r.means2d.grad[vis], m.grad[vis])
    assert t["means"].grad.abs().sum() > 0 and t["background"].grad is not None


def test_batched_adapter_renders_each_view_and_routes_gradients(monkeypatch):
    """rasterize_views on gsplat: one call whose batch entries hold each view's rows (given interleaved) padded to
    the largest view; images, projected means, radii and ∂L/∂means2d back at the right rows, as view by view."""
    from omg4.render.api import rasterize_views

    calls = []
    monkeypatch.setattr(gsplat, "rasterization",
                        lambda *a, **kw: calls.append(kw["covars"].shape) or fake_rasterization(*a, **kw))
    scenes = [random_scene(seed, n, 10, 8, scale=0.2) for seed, n in ((0, 12), (1, 9), (2, 15))]
    tensors = [sc.tensors(torch.float32) for sc in scenes]
    singles = []
    for t in tensors:
        r = rasterize(**t, backend="gsplat")
        (r.image.sum() + r.depth.sum()).backward()
        singles.append(r)
    views = torch.tensor([v for v, t in enumerate(tensors) for _ in range(t["means"].shape[0])])
    perm = torch.randperm(len(views), generator=torch.Generator().manual_seed(0))  # rows interleaved
    cat = {k: torch.cat([t[k].detach() for t in tensors])[perm].requires_grad_()
           for k in ("means", "covars", "colors", "opacities")}
    out = rasterize_views(cat["means"], cat["covars"], cat["colors"], cat["opacities"], views[perm],
                          torch.stack([t["viewmat"] for t in tensors]), torch.stack([t["K"] for t in tensors]), 10, 8,
                          backend="gsplat")
    (out.image.sum() + out.depth.sum()).backward()
    assert calls[-1] == (3, 15, 3, 3) and len(calls) == len(tensors) + 1  # one call for the batch
    assert out.image.shape == (3, 8, 10, 3)
    inverse = torch.argsort(perm)
    start = 0
    for v, (t, r) in enumerate(zip(tensors, singles)):
        rows = inverse[start:start + t["means"].shape[0]]
        start += t["means"].shape[0]
        background = t["background"].detach()
        torch.testing.assert_close(out.image[v], r.image.detach() - background)  # no background given here
        torch.testing.assert_close(out.means2d[rows], r.means2d.detach())
        assert torch.equal(out.radii[rows], r.radii)
        torch.testing.assert_close(out.means2d.grad[rows], r.means2d.grad)


@needs_cuda
@pytest.mark.gpu
@pytest.mark.parametrize("channels", [3, 5])
def test_gsplat_matches_cpu_backend(channels):
    sc = random_scene(1, 800, 128, 96, scale=0.1, channels=channels, opacity=(0.1, 0.99))
    cpu = sc.tensors(torch.float32)
    gpu = {k: (v.cuda().detach().requires_grad_(v.requires_grad) if torch.is_tensor(v) else v)
           for k, v in sc.tensors(torch.float32).items()}
    rc = rasterize(**cpu, backend="cpu")
    rg = rasterize(**gpu, backend="gsplat")
    assert rel_err(rg.image, rc.image) < 1e-4
    assert rel_err(rg.alpha, rc.alpha) < 1e-4
    assert rel_err(rg.depth, rc.depth) < 1e-4
    assert torch.equal(rg.radii.cpu() > 0, rc.radii > 0)
    g = torch.Generator().manual_seed(3)
    wi = torch.randn(rc.image.shape, generator=g)
    wd = torch.randn(rc.depth.shape, generator=g)
    ((rc.image * wi).sum() + (rc.depth * wd).sum()).backward()
    ((rg.image * wi.cuda()).sum() + (rg.depth * wd.cuda()).sum()).backward()
    assert rel_err(rg.means2d.grad, rc.means2d.grad) < 1e-3
    for k in ("means", "colors", "opacities", "background"):
        assert rel_err(gpu[k].grad, cpu[k].grad) < 1e-3, k
    sym = lambda c: c + c.transpose(-1, -2)  # gsplat reads the upper triangle only
    assert rel_err(sym(gpu["covars"].grad), sym(cpu["covars"].grad)) < 1e-3


@needs_cuda
@pytest.mark.gpu
def test_auto_picks_gsplat_on_cuda():
    from omg4.render.api import resolve_backend

    assert resolve_backend("auto", torch.device("cuda")) == "gsplat"


@needs_cuda
@pytest.mark.gpu
def test_gsplat_batch_matches_cpu_backend():
    """Three views of different row counts, rows interleaved, in one padded gsplat call: images, depths, radii
    and gradients as the CPU backend's."""
    from omg4.render.api import rasterize_views

    scenes = [random_scene(seed, n, 96, 64, scale=0.1, opacity=(0.1, 0.99)) for seed, n in ((4, 300), (5, 120), (6, 500))]
    tensors = [sc.tensors(torch.float32) for sc in scenes]
    views = torch.tensor([v for v, t in enumerate(tensors) for _ in range(t["means"].shape[0])])
    perm = torch.randperm(len(views), generator=torch.Generator().manual_seed(1))
    cams = {"viewmats": torch.stack([t["viewmat"] for t in tensors]), "Ks": torch.stack([t["K"] for t in tensors])}
    out, leaves = {}, {}
    for device, backend in (("cpu", "cpu"), ("cuda", "gsplat")):
        leaves[backend] = {k: torch.cat([t[k].detach() for t in tensors])[perm].to(device).requires_grad_()
                          for k in ("means", "covars", "colors", "opacities")}
        r = rasterize_views(*leaves[backend].values(), views[perm].to(device), cams["viewmats"].to(device),
                            cams["Ks"].to(device), 96, 64, backend=backend)
        g = torch.Generator().manual_seed(2)
        weights = [torch.randn(r.image.shape, generator=g).to(device), torch.randn(r.depth.shape, generator=g).to(device)]
        ((r.image * weights[0]).sum() + (r.depth * weights[1]).sum()).backward()
        out[backend] = r
    assert rel_err(out["gsplat"].image, out["cpu"].image) < 1e-4
    assert rel_err(out["gsplat"].depth, out["cpu"].depth) < 1e-4
    assert torch.equal(out["gsplat"].radii.cpu() > 0, out["cpu"].radii > 0)
    assert rel_err(out["gsplat"].means2d.grad, out["cpu"].means2d.grad) < 1e-3
    for k in ("means", "colors", "opacities"):
        assert rel_err(leaves["gsplat"][k].grad, leaves["cpu"][k].grad) < 1e-3, k
