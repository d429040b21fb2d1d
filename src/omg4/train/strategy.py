"""Density control as a strategy of the backbone: the hooks the trainer calls (cf. gsplat's ``Strategy``).

A backbone names its strategy (:attr:`omg4.gaussians.backbone.Backbone.training`; the named ones are in
:data:`omg4.train.strategies.STRATEGIES`). A backbone that names none trains a fixed set of Gaussians
(:class:`DensityStrategy` itself). As gsplat's strategies, a strategy is a dataclass that owns its settings: its
fields, taken from the run's :class:`~omg4.train.config.TrainConfig` fields of the same names by
:meth:`DensityStrategy.from_config` (the run's record keeps them there). The trainer calls, in order:
:meth:`~DensityStrategy.initial_points` once; then at every step :meth:`~DensityStrategy.collects_statistics`
(whether the view-space gradient statistics are accumulated), :meth:`~DensityStrategy.regularizer` (a term
added to the loss) and, after the optimizer step, :meth:`~DensityStrategy.after_step` (the density events).
"""

from __future__ import annotations

import dataclasses

import torch

from omg4.train.config import TrainConfig

DEFAULTS = TrainConfig()
"""The default settings a strategy's fields start from."""


@dataclasses.dataclass
class DensityStrategy:
    """A fixed set of Gaussians: at most ``max_gaussians`` of the initial points (0: all), no statistics, no
    events."""

    max_gaussians: int = DEFAULTS.max_gaussians

    @classmethod
    def from_config(cls, cfg: TrainConfig) -> "DensityStrategy":
        """The strategy with each of its fields taken from ``cfg``'s field of the same name (a field ``cfg``
        lacks keeps its default)."""
        return cls(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(cls) if hasattr(cfg, f.name)})

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

    densify_from: int = DEFAULTS.densify_from
    densify_until: int = DEFAULTS.densify_until
    densify_interval: int = DEFAULTS.densify_interval
    seed: int = DEFAULTS.seed

    def collects_statistics(self, step: int) -> bool:
        return step < self.densify_until


__all__ = ["DEFAULTS", "DensityStrategy", "ScheduledEvents"]
