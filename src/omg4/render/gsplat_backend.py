"""GPU backend of :func:`omg4.render.rasterize`: ``gsplat.rasterization`` (gsplat 1.5.3, CUDA).

DESIGN.md "Performance model" and ``rt4dgs_reference.md`` §8: the Gaussians go in with
``covars=`` (no quaternions/scales), one camera, ``packed=False`` so per-Gaussian outputs
keep the input order, and ``render_mode="RGB+D"`` so the extra channel is the
alpha-weighted depth Σ z·α·T (not the alpha-normalized "ED"). gsplat caps alpha at 0.999
inside its CUDA kernel, so this backend only accepts ``alpha_max=0.999``.
"""

from __future__ import annotations

import torch

GSPLAT_ALPHA_MAX = 0.999
"""The alpha cap hard-coded in gsplat's rasterization kernels."""


def rasterize_gsplat(means, covars, colors, opacities, viewmat, K, width, height, *, background=None, near=0.2,
                     far=1e10, eps2d=0.3, alpha_max=0.999, tile_size=16):
    """gsplat backend of :func:`omg4.render.rasterize` (same arguments; computes in float32).

    Returns an :class:`omg4.render.Rendered` whose ``means2d [N, 2]`` receives gsplat's
    ``info["means2d"]`` gradient (pixels) through a hook, and whose ``radii [N]`` is the
    larger of gsplat's two box half-widths.

    Raises:
        ValueError: ``alpha_max`` is not 0.999.
    """
    if alpha_max != GSPLAT_ALPHA_MAX:
        raise ValueError(f"the gsplat backend supports only alpha_max={GSPLAT_ALPHA_MAX} (fixed in its CUDA kernel), "
                         f"got {alpha_max}; use backend='cpu'")
    import gsplat

    from omg4.render.api import Rendered
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
    _forward_grad(info["means2d"], means2d)
    return Rendered(image=render[0, ..., :n_colors], alpha=alphas[0], depth=render[0, ..., n_colors:],
                    means2d=means2d, radii=max_radius(radii))


def _forward_grad(source: torch.Tensor, target: torch.Tensor) -> None:
    """Accumulate ``source [1, N, 2]``'s gradient into ``target.grad [N, 2]`` (like ``retain_grad``)."""
    if not source.requires_grad:
        return

    def hook(grad: torch.Tensor) -> None:
        g = grad[0].detach()
        target.grad = g.clone() if target.grad is None else target.grad + g

    source.register_hook(hook)
