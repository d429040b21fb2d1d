"""Lasting Gaussians of the segment before, held in place while a segment trains (beyond the paper).

A long capture's lasting content — the static set, the slow background — is learnt by the first segment; a segment
that starts from the one before (:func:`omg4.train.segmented.warm_start`) takes the segment before's Gaussians that
last through its own time range and stay put there (:func:`omg4.compress.carry_stage.lasting`, the rule by which
compression carries them as a base layer) and holds them **fixed**: they render with the segment's own Gaussians at
every step but take no gradient, are never densified, pruned or reset, and do not count against its Gaussian budget.
The segment's own Gaussians learn only what the held ones do not show — its new and changed content — so their
number follows that, and the held ones stay exact copies of the segment before's, which compression then replaces
by that segment's decoded base layer at about a bit each (docs/file-format.md §8b).

The checkpoints of a held run store its own Gaussians only (the held ones are derived again from the segment before
when it resumes); its final ``model.safetensors`` holds both, own first, so every reader takes it as a plain
model.
"""

from __future__ import annotations

import numpy as np
import torch

from omg4.compress.carry_stage import lasting
from omg4.gaussians.model import Gaussians4D, slice_values


def held_rows(values: dict[str, torch.Tensor], config, time_range: tuple[float, float]) -> np.ndarray:
    """Rows of the segment before's Gaussians (``values``, ``config``) that a segment of ``time_range`` holds: those
    that last through it and stay put there (:func:`~omg4.compress.carry_stage.lasting`)."""
    return np.flatnonzero(lasting(values, config, time_range))


def held_layer(teacher, time_range: tuple[float, float]) -> dict[str, torch.Tensor]:
    """The Gaussians a segment of ``time_range`` holds of ``teacher`` (the segment before's model, as
    :func:`omg4.models.load_model` gives its checkpoint): per-Gaussian values by its backbone's names, on the CPU."""
    values = {k: v.detach().to("cpu") for k, v in teacher.values.items()}
    rows = torch.from_numpy(held_rows(values, teacher.config, tuple(time_range)))
    return {k: values[k][rows] for k in teacher.config.schema.param_names}


class HeldGaussians4D(Gaussians4D):
    """A model being trained (``params``: its own Gaussians) that renders with ``held`` Gaussians (same attributes,
    fixed, appended after its own rows in every slice). ``slice_views`` indices at or beyond
    :attr:`num_gaussians` are held rows."""

    def __init__(self, params: dict[str, torch.Tensor], config, held: dict[str, torch.Tensor],
                 active_sh_degree: int | None = None, active_sh_degree_t: int | None = None):
        super().__init__(params, config, active_sh_degree, active_sh_degree_t)
        self.held = {k: held[k].detach() for k in config.schema.param_names}

    @property
    def num_held(self) -> int:
        return int(self.held["xyz"].shape[0])

    def slice_views(self, timestamps: torch.Tensor, camera_centers: torch.Tensor):
        values = {k: torch.cat([v, self.held[k].to(v.device)]) for k, v in self.params.items()}
        return slice_values(values, self.config, self.active_sh_degree, self.active_sh_degree_t, timestamps,
                            camera_centers)

    def to(self, device: torch.device | str) -> "HeldGaussians4D":
        moved = super().to(device)
        return HeldGaussians4D(moved.params, self.config, {k: v.to(device) for k, v in self.held.items()},
                               self.active_sh_degree, self.active_sh_degree_t)

    def whole(self) -> Gaussians4D:
        """The plain model of own and held Gaussians (own first), detached: what the run's final file holds."""
        return Gaussians4D({k: torch.cat([v.detach(), self.held[k].to(v.device)]) for k, v in self.params.items()},
                           self.config, self.active_sh_degree, self.active_sh_degree_t)


__all__ = ["held_rows", "held_layer", "HeldGaussians4D"]
