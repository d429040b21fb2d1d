"""Adaptive density control of Real-Time4DGS (rt4dgs §3.4).

Statistics: per Gaussian, the mean over the views where it was visible of the norm of
∂L_v/∂means2d, in the NDC units of the official code (pixel gradient × (W/2, H/2)), and
the largest screen radius. Every ``densify_interval`` iterations: clone small Gaussians
with a large gradient, split large ones into two children sampled from the 4D Gaussian
(4D-aware split), prune transparent and oversized ones. Opacity is reset periodically.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from omg4 import distributed
from omg4.gaussians import build_rotation_4d
from omg4.gaussians.backbone import activated_scales
from omg4.optimize.parameters import append_rows, keep_rows, replace_param
from omg4.optimize.step import step_generator
from omg4.settings import knob
from omg4.train.strategies.base import ScheduledEvents


class DensifyStats:
    """Running gradient statistics for densification (rt4dgs §3.4, batch-aware form), [N] each on ``device``."""

    def __init__(self, n: int, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.reset(n)

    def reset(self, n: int) -> None:
        self.grad_sum = torch.zeros(n, device=self.device)
        self.visible_views = torch.zeros(n, device=self.device)
        self.max_radii = torch.zeros(n, device=self.device)

    def state(self) -> dict[str, torch.Tensor]:
        """The accumulators by name (what a checkpoint stores)."""
        return {"grad_sum": self.grad_sum, "visible_views": self.visible_views, "max_radii": self.max_radii}

    def combined(self) -> "DensifyStats":
        """A copy holding the statistics of every rank of a distributed job (this rank's own in one process),
        leaving this one as it is: what a checkpoint saves, so that a run resumes with any number of ranks."""
        copy = DensifyStats(0, self.device)
        copy.grad_sum, copy.visible_views, copy.max_radii = (t.clone() for t in self.state().values())
        distributed.reduce_statistics(copy)
        return copy

    def add_view(self, index: torch.Tensor, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int,
                 height: int, batch_size: int) -> None:
        """Accumulate views: ``means2d_grad`` [M, 2] is ∂(L_v / B)/∂means2d in pixels for Gaussians ``index``.

        The rows may come from several views of a batch (a Gaussian then appears once per view).
        """
        visible = radii > 0
        idx = index[visible]
        g = means2d_grad[visible] * torch.tensor([width / 2.0, height / 2.0], device=self.device) * batch_size
        self.grad_sum.index_add_(0, idx, g.norm(dim=-1))
        self.visible_views.index_add_(0, idx, torch.ones_like(idx, dtype=torch.float32))
        self.max_radii.scatter_reduce_(0, idx, radii[visible].float(), reduce="amax")

    def mean_grad(self) -> torch.Tensor:
        """[N] mean over visible views of the per-view NDC gradient norm (0 where never visible)."""
        return torch.where(self.visible_views > 0, self.grad_sum / self.visible_views.clamp_min(1), 0.0)


def densify_and_prune(model, optimizer, stats: DensifyStats, *, grad_threshold: float, percent_dense: float,
                      extent: float, prune_opacity: float, max_screen_size: float | None, prune_world_size: float,
                      max_gaussians: int, generator: torch.Generator) -> dict[str, int]:
    """One densification event (rt4dgs §3.4); returns counts of cloned, split and pruned Gaussians.

    With ``max_gaussians`` > 0 the candidates with the largest gradients are densified
    first and the growth stops at the cap.
    """
    params = model.params
    grads = stats.mean_grad()
    scales_xyz = params["scaling"].detach().exp()
    max_scale = scales_xyz.max(dim=1).values
    small = max_scale <= percent_dense * extent
    candidates = grads >= grad_threshold
    n0 = grads.shape[0]
    budget = max(0, max_gaussians - n0) if max_gaussians > 0 else n0 * 2
    clone_mask = candidates & small
    split_mask = candidates & ~small
    clone_mask, split_mask = _limit_to_budget(clone_mask, split_mask, grads, budget)

    # clone: exact copies
    clone_idx = clone_mask.nonzero().squeeze(1)
    append_rows(params, optimizer, {k: v.detach()[clone_idx] for k, v in params.items()})

    # split: two children sampled from the 4D Gaussian, scales / (0.8·2)
    split_idx = split_mask.nonzero().squeeze(1)
    if split_idx.numel():
        children = _split_children(params, split_idx, model.config.rotation_convention, generator)
        append_rows(params, optimizer, children)
    n_after = params["xyz"].shape[0]
    device = params["xyz"].device
    prune = torch.zeros(n_after, dtype=torch.bool, device=device)
    prune[split_idx] = True  # parents are replaced by their children

    opacity = torch.sigmoid(params["opacity"].detach()).squeeze(1)
    prune |= opacity < prune_opacity
    if max_screen_size:
        radii = torch.cat([stats.max_radii, torch.zeros(n_after - n0, device=device)])
        big_world = params["scaling"].detach().exp().max(dim=1).values > prune_world_size * extent
        prune |= (radii > max_screen_size) | big_world
    if bool(prune.all()):  # never prune a scene down to nothing
        prune[opacity.argmax()] = False
    keep_rows(params, optimizer, ~prune)
    stats.reset(params["xyz"].shape[0])
    return {"cloned": int(clone_idx.numel()), "split": int(split_idx.numel()), "pruned": int(prune.sum())}


def _limit_to_budget(clone_mask, split_mask, grads, budget):
    """Keep the largest-gradient candidates so that growth (1 per clone, 1 per split) ≤ ``budget``."""
    total = int(clone_mask.sum() + split_mask.sum())
    if total <= budget:
        return clone_mask, split_mask
    cand = (clone_mask | split_mask).nonzero().squeeze(1)
    keep = cand[torch.argsort(grads[cand], descending=True)[:budget]]
    chosen = torch.zeros_like(clone_mask)
    chosen[keep] = True
    return clone_mask & chosen, split_mask & chosen


def _split_children(params, idx, convention: str, generator: torch.Generator, n_children: int = 2):
    """Children of split Gaussians: (xyz, t) = R4 ε + μ with ε ~ N(0, diag(s²)) (rt4dgs §3.4)."""
    p = {k: v.detach()[idx] for k, v in params.items()}
    scales = activated_scales(p)  # [K, 4]
    R4 = build_rotation_4d(p["rotation"], p["rotation_r"], convention=convention)  # [K, 4, 4]
    out = {k: v.repeat(n_children, *([1] * (v.dim() - 1))) for k, v in p.items()}
    eps = torch.randn(out["xyz"].shape[0], 4, generator=generator, device=generator.device)  # CPU draw: reproducible
    eps = eps.to(scales.device) * scales.repeat(n_children, 1)
    offset = torch.einsum("kij,kj->ki", R4.repeat(n_children, 1, 1), eps)
    out["xyz"] = out["xyz"] + offset[:, :3]
    out["t"] = out["t"] + offset[:, 3:]
    shrink = math.log(0.8 * n_children)
    out["scaling"] = out["scaling"] - shrink
    out["scaling_t"] = out["scaling_t"] - shrink
    return out


@dataclasses.dataclass
class Densification(ScheduledEvents):
    """Real-Time4DGS's density control (rt4dgs §3.4): statistics before ``densify_until``; every
    ``densify_interval`` steps after ``densify_from`` a :func:`densify_and_prune` event (the screen-size limit
    ``prune_screen_size`` once the first opacity reset has passed); opacities reset every
    ``opacity_reset_interval`` steps before ``densify_until``."""

    densify_grad_threshold: float = knob(2e-4, "mean view-space gradient (NDC) from which a Gaussian is densified")
    percent_dense: float = knob(0.01, "largest scale (× extent) of a Gaussian that is cloned rather than split")
    prune_opacity: float = knob(0.005, "Gaussians below this opacity are pruned")
    prune_world_size: float = knob(0.1, "after the first opacity reset, prune Gaussians larger than this (× extent)")
    prune_screen_size: float = knob(20.0, "after the first opacity reset, prune Gaussians wider than this (pixels)")
    opacity_reset_interval: int = knob(3000, "steps between opacity resets (to 0.01)")

    def grows_until(self) -> int:
        return self.densify_until

    def after_step(self, model, optimizer, stats, step: int, extent: float) -> None:
        if step >= self.densify_until:
            return
        if step > self.densify_from and step % self.densify_interval == 0:
            size_threshold = self.prune_screen_size if step > self.opacity_reset_interval else None
            distributed.reduce_statistics(stats)  # every rank decides on the statistics of every view
            densify_and_prune(model, optimizer, stats, grad_threshold=self.densify_grad_threshold,
                              percent_dense=self.percent_dense, extent=extent, prune_opacity=self.prune_opacity,
                              max_screen_size=size_threshold, prune_world_size=self.prune_world_size,
                              max_gaussians=self.max_gaussians, generator=step_generator(self.seed, step, stream=1))
        if step % self.opacity_reset_interval == 0:
            reset_opacity(model, optimizer)


def reset_opacity(model, optimizer, ceiling: float = 0.01) -> None:
    """Opacity ← min(opacity, ceiling), Adam moments zeroed (rt4dgs §3.4)."""
    logit_ceiling = math.log(ceiling / (1 - ceiling))
    current = model.params["opacity"].detach()
    replace_param(model.params, optimizer, "opacity", torch.minimum(current, torch.full_like(current, logit_ceiling)))
