"""One optimization step's shared parts: the batch loss and its backward, and step randomness.

The baseline trainer (:mod:`omg4.train.trainer`) and the OMG4 fine-tuning
(:mod:`omg4.compress.pipeline`) take their steps through these, and their parameter groups
through :mod:`omg4.optimize.parameters`, so both optimize the same loss (rt4dgs §3.2; paper §5.1)
the same way.
"""

from __future__ import annotations

import numpy as np
import torch

from omg4 import distributed
from omg4.data.scene import View
from omg4.errors import OMG4Error
from omg4.optimize.loss import losses_and_errors
from omg4.render.view import render_views, view_image, views_by_size


def step_generator(seed: int, step: int, stream: int = 0) -> torch.Generator:
    """A CPU generator determined by (seed, step, stream) alone (resume-safe, device-independent randomness)."""
    g = torch.Generator()
    g.manual_seed((seed * 1_000_003 + step * 7919 + stream) % (2**63 - 1))
    return g


def view_losses(model, views: list[View], *, background: torch.Tensor | None, backend: str, lambda_dssim: float,
                device: torch.device | str = "cpu"):
    """Render ``views`` in one pass per image size and yield, group by group,
    ``(positions in views, rendered, time slice, ground truths [V, H, W, 3], per-view losses [V], per-view sums of
    squared errors [V])`` (rt4dgs §3.2 loss, :func:`omg4.optimize.loss.losses_and_errors`;
    :func:`omg4.render.view.render_views`)."""
    for group in views_by_size([v.camera for v in views]):
        members = [views[i] for i in group]
        rendered, sl = render_views(model, [v.camera for v in members], [v.timestamp for v in members],
                                    background=background, backend=backend, device=device)
        gts = torch.stack([view_image(v, device) for v in members])
        yield (group, rendered, sl, gts, *losses_and_errors(rendered.image, gts, lambda_dssim))


def backward_batch(model, views: list[View], batch: torch.Tensor, *, background: torch.Tensor, backend: str,
                   lambda_dssim: float, what: str, step: int, device: torch.device | str = "cpu",
                   on_views=None, regularizer=None) -> tuple[float, float]:
    """Render the views ``views[i]``, i in ``batch``, and back-propagate Σ_v loss_v / B once (rt4dgs §3.1).

    Views of one image size are sliced and rasterized together (:func:`omg4.render.view.render_views`);
    the loss is computed on the whole batch; the step synchronizes with the device once, to
    read the loss. ``model`` and ``background`` live on ``device``; the ground truths are moved there.
    In a distributed job (:mod:`omg4.distributed`) this rank renders its share of the global batch and
    back-propagates that share of Σ_v loss_v / B (B the global batch size), so the gradients summed over the
    ranks are the single-process gradients.

    ``on_views(rendered, time_slice)`` runs after the backward for each group of views
    (gradient statistics: ``rendered.means2d.grad`` rows follow ``time_slice.index``).
    ``regularizer(timestamps [B])``, when given, returns a scalar added to the loss (FreeTimeGS's
    4D regularization, a mean over the views), or None.
    Returns the global batch's mean per-view loss and mean PSNR (renders clamped); a non-finite
    loss is a one-line error naming ``what``.
    """
    indices = batch.tolist()
    chosen = [views[i] for i in distributed.world().shard(indices)]
    total, psnr_sum, rendered_groups = torch.zeros((), device=device), 0.0, []
    for _, rendered, sl, gts, losses, squared in view_losses(model, chosen, background=background, backend=backend,
                                                             lambda_dssim=lambda_dssim, device=device):
        total = total + losses.sum() / len(indices)
        psnr_sum = psnr_sum + (-10.0 * torch.log10(squared / gts[0].numel())).sum()
        rendered_groups.append((rendered, sl))
    times = torch.tensor([v.timestamp for v in chosen], dtype=torch.float64)
    extra = regularizer(times) if regularizer and chosen else None
    if extra is not None:  # a mean over this rank's views, weighted by their share of the batch
        total = total + extra * (len(chosen) / len(indices)) if len(chosen) != len(indices) else total + extra
    summary = torch.stack([total.detach().to(torch.float64), torch.as_tensor(psnr_sum, dtype=torch.float64,
                                                                              device=device)])
    distributed.all_reduce_([summary], "sum", f"{what} at iteration {step}")
    loss, psnr_total = summary.tolist()  # the step's one synchronization
    if not np.isfinite(loss):
        raise OMG4Error(f"{what} diverged at iteration {step}: the loss is {loss}")
    if total.requires_grad:
        total.backward()
    if on_views is not None:
        for rendered, sl in rendered_groups:
            on_views(rendered, sl)
    return loss, psnr_total / len(indices)


__all__ = ["backward_batch", "step_generator", "view_losses"]
