"""GPU backend of :func:`omg4.render.rasterize_views`: ``gsplat.rasterization`` (gsplat 1.5.3, CUDA).

As in docs/paper-map.md "Rasterizer backends" (and rt4dgs §8): the Gaussians go in with
``covars=`` (no quaternions/scales), ``packed=False`` so per-Gaussian outputs keep the
input order, and ``render_mode="RGB+D"`` so the extra channel is the alpha-weighted depth
Σ z·α·T (not the alpha-normalized "ED"). gsplat caps alpha at 0.999 inside its CUDA
kernel, so this backend only accepts ``alpha_max=0.999``.

A batch of views renders in one gsplat call: each view's Gaussian rows (its own time slice)
are padded to the largest view's count along gsplat's leading batch axis, one camera per
batch entry. Padding rows have opacity 0 and sit one unit behind their camera, so gsplat's
projection culls them (behind the near plane, below the alpha threshold).
"""

from __future__ import annotations

import torch

from omg4.render.projection import max_radius
from omg4.render.rendered import Rendered

GSPLAT_ALPHA_MAX = 0.999
"""The alpha cap hard-coded in gsplat's rasterization kernels."""


def rasterize_gsplat_views(means, covars, colors, opacities, views, viewmats, Ks, width, height, *, background=None,
                           near=0.2, far=1e10, eps2d=0.3, alpha_max=0.999, tile_size=16) -> Rendered:
    """gsplat backend of :func:`omg4.render.api.rasterize_views` (same arguments; computes in float32).

    Returns an :class:`omg4.render.Rendered` whose ``means2d [N, 2]`` receives gsplat's
    ``info["means2d"]`` gradient (pixels) through a hook and whose ``radii [N]`` is the
    larger of gsplat's two box half-widths.

    Raises:
        ValueError: ``alpha_max`` is not 0.999.
    """
    if alpha_max != GSPLAT_ALPHA_MAX:
        raise ValueError(f"the gsplat backend supports only alpha_max={GSPLAT_ALPHA_MAX} (fixed in its CUDA kernel), "
                         f"got {alpha_max}; use backend='cpu'")
    import gsplat  # gsplat needs CUDA: imported where a GPU renders


    like = dict(dtype=torch.float32, device=means.device)
    num_views, n_colors = viewmats.shape[0], colors.shape[1]
    viewmats, Ks = viewmats.to(**like), Ks.to(**like)
    slots = ViewSlots(views, means.shape[0], num_views, means.device)
    rotations, translations = viewmats[:, :3, :3], viewmats[:, :3, 3:]
    behind = -(rotations.transpose(1, 2) @ translations)[..., 0] - rotations[:, 2]  # [V, 3]: view depth −1
    padded_means = slots.pad(means.to(**like), filler=behind)
    padded_opacities = slots.pad(opacities.to(**like))
    backgrounds = None if background is None else background.to(**like).expand(num_views, 1, n_colors)
    render, alphas, info = gsplat.rasterization(
        padded_means, None, None, padded_opacities, slots.pad(colors.to(**like)), viewmats[:, None], Ks[:, None],
        width, height, near_plane=near, far_plane=far, eps2d=eps2d, backgrounds=backgrounds, packed=False,
        tile_size=tile_size, render_mode="RGB+D", covars=slots.pad(covars.to(**like)), rasterize_mode="classic")
    radii = slots.unpad(info["radii"])  # [N, 2] in gsplat 1.5.3
    visible = (radii > 0).all(dim=-1)
    means2d = torch.where(visible[:, None], slots.unpad(info["means2d"]).detach(), 0.0)
    _forward_grad(info["means2d"], means2d, slots.flat)
    return Rendered(image=render[:, 0, ..., :n_colors], alpha=alphas[:, 0], depth=render[:, 0, ..., n_colors:],
                    means2d=means2d, radii=max_radius(radii))


class ViewSlots:
    """Where each Gaussian row sits in the padded ``[V, M]`` batch, ``M`` being the largest view's row count.

    ``flat [N]`` is each row's index into the flattened batch (no two rows share one).
    """

    def __init__(self, views: torch.Tensor | None, num_rows: int, num_views: int, device: torch.device):
        if views is None or num_views == 1:
            self.shape = (1, num_rows)
            self.flat = torch.arange(num_rows, device=device)
            return
        counts = torch.bincount(views, minlength=num_views)
        self.shape = (num_views, max(int(counts.max()), 1))  # one host synchronization for the padded width
        order = torch.argsort(views, stable=True)
        starts = torch.cumsum(counts, 0) - counts
        rank = torch.empty_like(order)
        rank[order] = torch.arange(num_rows, device=device) - starts[views[order]]
        self.flat = views * self.shape[1] + rank

    def pad(self, rows: torch.Tensor, filler: torch.Tensor | None = None) -> torch.Tensor:
        """``rows [N, ...]`` → ``[V, M, ...]``, the empty slots of view v holding ``filler[v]`` (default zero).
        Differentiable, and its backward is a gather: a scatter into unique slots, where indexing from the slots
        would accumulate every empty slot's gradient into one row (a serial reduction on CUDA)."""
        if self.shape[0] == 1:  # one view: every row in order, no padding
            return rows[None]
        tail = rows.shape[1:]
        if filler is None:
            batch = rows.new_zeros((self.shape[0] * self.shape[1], *tail))
        else:
            batch = filler.to(rows.dtype)[:, None].expand(*self.shape, *tail).reshape(-1, *tail)
        return batch.index_copy(0, self.flat, rows).reshape(*self.shape, *tail)

    def unpad(self, batch: torch.Tensor) -> torch.Tensor:
        """gsplat's per-Gaussian output ``[V, 1, M, ...]`` → ``[N, ...]`` in row order."""
        return batch.reshape(-1, *batch.shape[3:])[self.flat]


def _forward_grad(source: torch.Tensor, target: torch.Tensor, flat: torch.Tensor) -> None:
    """Accumulate ``source [V, 1, M, 2]``'s gradient, at the rows' slots ``flat``, into ``target.grad`` (like
    ``retain_grad``)."""
    if not source.requires_grad:
        return

    def hook(grad: torch.Tensor) -> None:
        g = grad.reshape(-1, grad.shape[-1])[flat]
        target.grad = g if target.grad is None else target.grad + g

    source.register_hook(hook)
