"""Density control as a strategy of the backbone: the hooks the trainer calls (cf. gsplat's ``Strategy``).

A backbone names its strategy (:attr:`omg4.gaussians.backbone.Backbone.training`; the named ones are in
:data:`omg4.train.strategies.STRATEGIES`). A backbone that names none trains a fixed set of Gaussians
(:class:`DensityStrategy` itself). As gsplat's strategies, a strategy is a dataclass that owns its settings: its
fields, with their defaults and help; the run's config holds the backbone's strategy as ``strategy``
(``TrainConfig.strategy``, ``--set strategy.<field>=…``), and :func:`omg4.train.strategies.strategy_for` gives the
run a copy of it seeded by the run's ``seed`` (the run's, not a strategy setting). The trainer calls, in order:
:meth:`~DensityStrategy.initial_points` once; then at every step :meth:`~DensityStrategy.collects_statistics`
(whether the view-space gradient statistics are accumulated), :meth:`~DensityStrategy.regularizer` (a term
added to the loss) and, after the optimizer step, :meth:`~DensityStrategy.after_step` (the density events).
"""

from __future__ import annotations

import dataclasses

import torch

from omg4.settings import knob


@dataclasses.dataclass
class DensityStrategy:
    """A fixed set of Gaussians: at most ``max_gaussians`` of the initial points (0: all), no statistics, no
    events."""

    max_gaussians: int = knob(0, "cap on the Gaussian count (0: none); FreeTimeGS: its fixed budget")

    def initial_points(self, xyz: torch.Tensor, rgb: torch.Tensor, generator: torch.Generator
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """The points the model starts from (CPU [M, 3] each): a random subset of ``max_gaussians`` when there
        are more."""
        if self.max_gaussians and len(xyz) > self.max_gaussians:
            keep = torch.randperm(len(xyz), generator=generator, device="cpu")[: self.max_gaussians]
            xyz, rgb = xyz[keep], rgb[keep]
        return xyz, rgb

    def grows_until(self) -> int:
        """The last step at which the Gaussian count may still grow (0: it never does)."""
        return 0

    def collects_statistics(self, step: int) -> bool:
        """Whether step ``step`` accumulates the view-space gradient statistics (:class:`DensifyStats`)."""
        return False

    def regularizer(self, params: dict[str, torch.Tensor], timestamps: torch.Tensor, step: int
                    ) -> torch.Tensor | None:
        """A scalar added to the loss of step ``step`` for views at ``timestamps`` [B], or None."""
        return None

    def after_step(self, model, optimizer: torch.optim.Optimizer, stats, step: int, extent: float) -> None:
        """The density events after the optimizer step ``step`` (1-based)."""


@dataclasses.dataclass
class ScheduledEvents(DensityStrategy):
    """The schedule both backbones' density controls share: statistics before ``densify_until``, an event every
    ``densify_interval`` steps after ``densify_from``, each event's draws seeded by ``seed`` and its step."""

    densify_from: int = knob(500, "first density event after this step")
    densify_until: int = knob(15_000, "no density events, statistics or regularization from this step on")
    densify_interval: int = knob(100, "steps between density events")
    seed = 6666  # the run's, set by strategy_for (not a field: not a setting of the strategy)

    def collects_statistics(self, step: int) -> bool:
        return step < self.densify_until


__all__ = ["DensityStrategy", "ScheduledEvents"]
