"""Switching a model from explicit to MLP appearance (paper §4.4; omg4 §6b, §9).

At the appearance event the per-Gaussian opacity and 4D SH are dropped and replaced by
:class:`omg4.gaussians.appearance.AppearanceMLP` outputs. Each Gaussian gets a 3-d static
feature initialised from its base colour (the SH DC coefficient) and a 3-d view feature
initialised to zero, both trained in the main Adam at :data:`FEATURE_LR`. The MLPs get their
own Adam (lr 5e-3, eps 1e-15) with a 100-iteration linear warm-up from 1% and ×0.33 steps
after 1000, 3500 and 6000 of the 7000 iterations that follow (5000 MLP + 1000 SVQ-3D +
1000 SVQ-4D); shorter schedules scale the warm-up and milestones proportionally.
"""

from __future__ import annotations

import torch
from torch import Tensor

from omg4.errors import OMG4Error
from omg4.optimize.parameters import LEARNING_RATES

FEATURE_LR = LEARNING_RATES.feature_lr  # f_static / f_view in the main Adam (omg4 §9): the backbone table's
# "feature_lr", the baseline's base-colour rate
MLP_LR = 5e-3
OFFICIAL_ITERATIONS = 7000  # iterations after MLP creation: 34000 → 41000 (omg4 §2)
OFFICIAL_WARMUP = 100
OFFICIAL_MILESTONES = (1000, 3500, 6000)
DECAY = 0.33


def init_appearance_features(params: dict[str, Tensor]) -> dict[str, Tensor]:
    """Per-Gaussian appearance features from a Real-Time4DGS parameter dict (omg4 §6b).

    params["features_dc"]: [N, 1, 3] → ``{"f_static": [N, 3] = features_dc[:, 0], "f_view": zeros [N, 3]}``
    (fresh tensors, no gradient history).
    """
    dc = params.get("features_dc")
    if dc is None or dc.ndim != 3 or dc.shape[1:] != (1, 3):
        shape = None if dc is None else tuple(dc.shape)
        raise OMG4Error(f"MLP appearance needs explicit features_dc of shape [N, 1, 3], got {shape}")
    f_static = dc[:, 0].detach().clone()
    return {"f_static": f_static, "f_view": torch.zeros_like(f_static)}


def mlp_lr_schedule(total_iterations: int) -> tuple[int, list[int]]:
    """Warm-up length and decay milestones for an appearance+SVQ phase of ``total_iterations``.

    Equals the official ``(100, [1000, 3500, 6000])`` at 7000 iterations; otherwise each is
    scaled by ``total_iterations / 7000`` and rounded (at least 1).
    """
    if total_iterations < 1:
        raise OMG4Error(f"the appearance stage needs at least one iteration, got {total_iterations}")
    scale = total_iterations / OFFICIAL_ITERATIONS
    warmup = max(1, round(OFFICIAL_WARMUP * scale))
    return warmup, [max(1, round(m * scale)) for m in OFFICIAL_MILESTONES]


def make_mlp_optimizer(mlp: torch.nn.Module, lr: float = MLP_LR, total_iterations: int = OFFICIAL_ITERATIONS
                       ) -> tuple[torch.optim.Adam, torch.optim.lr_scheduler.ChainedScheduler]:
    """Adam(eps 1e-15) over the MLP weights with OMG4's schedule (omg4 §6b).

    ``ChainedScheduler(LinearLR(start_factor=0.01, total_iters=warmup), MultiStepLR(milestones, gamma=0.33))``
    with ``warmup, milestones = mlp_lr_schedule(total_iterations)``; call ``scheduler.step()`` once per
    iteration after ``optimizer.step()``.
    """
    warmup, milestones = mlp_lr_schedule(total_iterations)
    optimizer = torch.optim.Adam(mlp.parameters(), lr=lr, eps=1e-15, fused=True)
    scheduler = torch.optim.lr_scheduler.ChainedScheduler([
        torch.optim.lr_scheduler.LinearLR(optimizer, start_factor=0.01, total_iters=warmup),
        torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones=milestones, gamma=DECAY),
    ])
    return optimizer, scheduler


#: what a predicted segment does with its reference segment's appearance MLPs (beyond the paper; docs/file-format.md
#: §8a): fine-tunes them like its own and stores the change (``tune``), or keeps them as they are and stores none
#: of them (``keep``: smaller, and below the segment coded alone; docs/results.md, predicted segments)
PREDICTED_MLPS = ("tune", "keep")


__all__ = ["FEATURE_LR", "MLP_LR", "PREDICTED_MLPS", "init_appearance_features", "make_mlp_optimizer",
           "mlp_lr_schedule"]
