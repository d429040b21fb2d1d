"""GPU backend of :func:`omg4.render.rasterize`: ``gsplat.rasterization`` (gsplat 1.5.3, CUDA).

As in docs/paper-map.md "Rasterizer backends" (and rt4dgs §8): the Gaussians go in with
``covars=`` (no quaternions/scales), one camera, ``packed=False`` so per-Gaussian outputs
keep the input order, and ``render_mode="RGB+D"`` so the extra channel is the
alpha-weighted depth Σ z·α·T (not the alpha-normalized "ED"). gsplat caps alpha at 0.999
inside its CUDA kernel, so this backend only accepts ``alpha_max=0.999``.
"""

from __future__ import annotations

import torch

from omg4.render.rendered import Rendered

GSPLAT_ALPHA_MAX = 0.999
"""The alpha cap hard-coded in gsplat's rasterization kernels."""


def rasterize_gsplat(means, covars, colors, opacities, viewmat, K, width, height, *, background=None, near=0.2,
                     far=1e10, eps2d=0.3, alpha_max=0.999, tile_size=16, grad_into=None):
    """gsplat backend of :func:`omg4.render.rasterize` for one view (same arguments; computes in float32).

    Returns an :class:`omg4.render.Rendered` whose ``means2d [N, 2]`` receives gsplat's
    ``info["means2d"]`` gradient (pixels) through a hook — or, with ``grad_into=(target,
    rows)``, rows ``rows`` of ``target.grad`` do — and whose ``radii [N]`` is the larger of
    gsplat's two box half-widths.

    Raises:
        ValueError: ``alpha_max`` is not 0.999.
    """
    if alpha_max != GSPLAT_ALPHA_MAX:
        raise ValueError(f"the gsplat backend supports only alpha_max={GSPLAT_ALPHA_MAX} (fixed in its CUDA kernel), "
                         f"got {alpha_max}; use backend='cpu'")
    import gsplat

    from omg4.render.projection import max_radius

    like = dict(dtype=torch.float32, device=means.device)
    n_colors = colors.shape[1]
    backgrounds = None if background is None else background.to(**like)[None]
    render, alphas, info = gsplat.rasterization(
        means.to(**like), None, None, opacities.to(**like), colors.to(**like), viewmat.to(**like)[None],
        K.to(**like)[None], width, height, near_plane=near, far_plane=far, eps2d=eps2d, backgrounds=backgrounds,
        packed=False, tile_size=tile_size, render_mode="RGB+D", covars=covars.to(**like), rasterize_mode="classic")
    radii = info["radii"][0]  # [N, 2] in gsplat 1.5.3
    visible = (radii > 0).all(dim=-1)
    means2d = torch.where(visible[:, None], info["means2d"][0].detach(), 0.0)
    _forward_grad(info["means2d"], *(grad_into or (means2d,)))
    return Rendered(image=render[0, ..., :n_colors], alpha=alphas[0], depth=render[0, ..., n_colors:],
                    means2d=means2d, radii=max_radius(radii))


def rasterize_gsplat_views(means, covars, colors, opacities, views, viewmats, Ks, width, height, **kwargs):
    """gsplat backend of :func:`omg4.render.api.rasterize_views`: one ``gsplat.rasterization`` call per view.

    The views' Gaussian sets differ (each is its own time slice), so they cannot share gsplat's
    leading camera axis; ``means2d [N, 2]`` gathers every view's rows and their gradients.
    """

    num_views = viewmats.shape[0]
    if num_views == 1:
        rows = [torch.arange(means.shape[0], device=means.device)]
    else:  # one host synchronization for the views' row counts
        order = torch.argsort(views, stable=True)
        rows = list(order.split(torch.bincount(views, minlength=num_views).tolist()))
    means2d = torch.zeros(means.shape[0], 2, dtype=torch.float32, device=means.device)
    parts = [rasterize_gsplat(means[r], covars[r], colors[r], opacities[r], viewmats[v], Ks[v], width, height,
                              grad_into=(means2d, r), **kwargs) for v, r in enumerate(rows)]
    radii = torch.zeros(means.shape[0], dtype=torch.int32, device=means.device)
    for r, part in zip(rows, parts):
        means2d[r] = part.means2d.detach()
        radii[r] = part.radii
    return Rendered(image=torch.stack([p.image for p in parts]), alpha=torch.stack([p.alpha for p in parts]),
                    depth=torch.stack([p.depth for p in parts]), means2d=means2d, radii=radii)


def _forward_grad(source: torch.Tensor, target: torch.Tensor, rows: torch.Tensor | None = None) -> None:
    """Accumulate ``source [1, M, 2]``'s gradient into ``target.grad`` (like ``retain_grad``), at ``rows`` of it
    when given."""
    if not source.requires_grad:
        return

    def hook(grad: torch.Tensor) -> None:
        g = grad[0].detach()
        if rows is not None:
            g = torch.zeros_like(target).index_add_(0, rows, g)
        target.grad = g.clone() if target.grad is None else target.grad + g

    source.register_hook(hook)
