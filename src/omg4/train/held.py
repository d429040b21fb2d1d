"""Lasting Gaussians of the segment before, held in place while a segment trains (beyond the paper).

A long capture's lasting content — the static set, the slow background — is learnt by the first segment; a segment
that starts from the one before (:func:`omg4.train.segmented.warm_start`) takes the segment before's Gaussians that
last through its own time range and stay put there (:func:`omg4.gaussians.visibility.lasting`, the rule by which
compression carries them as a base layer) and **holds** them: they train with the segment's own Gaussians but
outside its density control (never densified, pruned or reset, not counted in its Gaussian budget), their geometry
pulled to its values in the segment before by :func:`anchor_penalty`, so they move only where the video says they
moved; their appearance (opacity and SH, what compression's appearance MLPs replace, paper §4.4) follows the video
freely — a change of exposure or light is not a change of place. When training ends, every held Gaussian whose
geometry stayed within :data:`SNAP` of its reference (:func:`deviation`) has it set back exactly; the others —
content that moved — become the segment's own. The segment's own Gaussians learn what the held ones do not show, so
their number follows its new and changed content, and the held ones are what compression replaces by the segment
before's decoded base layer at about a bit each (docs/file-format.md §8b), coloured by the segment's own MLPs.

A run's checkpoints hold the held Gaussians as they train after its own (``held_training`` in their metadata), so a
stopped run resumes exactly; its final ``model.safetensors`` holds its own Gaussians, then the held ones
(``held``: their count), so every reader takes it as a plain model.
"""

from __future__ import annotations

import numpy as np
import torch

from omg4.gaussians.model import Gaussians4D, slice_values
from omg4.gaussians.visibility import lasting

ANCHOR = 1e-3
"""Weight of the pull of each held Gaussian's geometry to its reference (:func:`anchor_penalty`), per Gaussian."""

SNAP = 0.1
"""A held Gaussian whose geometry is within this of its reference (:func:`deviation`) is set back to it when
training ends: its centre within a tenth of its largest scale, its time centre within a tenth of its temporal
standard deviation, every other geometric value (log-scales, rotations, motion) within 0.1."""


def held_rows(values: dict[str, torch.Tensor], config, time_range: tuple[float, float]) -> np.ndarray:
    """Rows of the segment before's Gaussians (``values``, ``config``) that a segment of ``time_range`` holds: those
    that last through it and stay put there (:func:`~omg4.gaussians.visibility.lasting`)."""
    return np.flatnonzero(lasting(values, config, time_range))


def held_layer(teacher, time_range: tuple[float, float]) -> tuple[np.ndarray, dict[str, torch.Tensor]]:
    """The Gaussians a segment of ``time_range`` holds of ``teacher`` (the segment before's model, as
    :func:`omg4.models.load_model` gives its checkpoint): (their rows there, their per-Gaussian values by its
    backbone's names, on the CPU)."""
    values = {k: v.detach().to("cpu") for k, v in teacher.values.items()}
    rows = held_rows(values, teacher.config, tuple(time_range))
    return rows, {k: values[k][torch.from_numpy(rows)] for k in teacher.config.schema.param_names}


def _units(reference: dict[str, torch.Tensor], config) -> dict[str, torch.Tensor]:
    """Per row, the unit each geometric attribute's change is measured in (:data:`SNAP`): [H, 1] each."""
    size = reference["scaling"].detach().max(dim=1, keepdim=True).values.exp()
    var_t = config.schema.motion({k: v.detach() for k, v in reference.items()}, config)[2]
    ones = torch.ones_like(size)
    return {k: size if k == "xyz" else var_t.reshape(-1, 1).clamp_min(1e-12).sqrt().to(size.dtype) if k == "t"
            else ones for k in reference if k not in config.schema.by_mlp}


def _scaled_changes(values, reference, config):
    """Per geometric attribute, [H, width] changes of ``values`` from ``reference`` in the units of :func:`_units`."""
    units = _units(reference, config)
    device = values["xyz"].device
    return {k: (values[k] - reference[k].to(device)).reshape(len(units[k]), -1) / units[k].to(device)
            for k in units}


def anchor_penalty(values: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], config) -> torch.Tensor:
    """:data:`ANCHOR` × Σ over held Gaussians and their geometric values of the squared change from ``reference`` in
    the units of :func:`deviation`: zero at the reference, so a Gaussian the video does not move stays there."""
    changes = _scaled_changes(values, reference, config)
    return ANCHOR * sum(c.square().sum() for c in changes.values())


def deviation(values: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], config) -> torch.Tensor:
    """[H] the largest change of each held Gaussian's geometry from ``reference`` (centre in units of its largest
    scale, time centre in its temporal standard deviation, the other geometric values as they are; appearance,
    the backbone's ``by_mlp`` attributes, is left out)."""
    with torch.no_grad():
        changes = _scaled_changes(values, reference, config)
        return torch.stack([c.abs().amax(dim=1) for c in changes.values()]).amax(dim=0)


class HeldGaussians4D(Gaussians4D):
    """A model being trained (``params``: its own Gaussians) with ``held`` Gaussians (same attributes, trained by
    their own optimizer, pulled to ``reference``; appended after its own rows in every slice). ``slice_views``
    indices at or beyond :attr:`num_gaussians` are held rows."""

    def __init__(self, params: dict[str, torch.Tensor], config, held: dict[str, torch.Tensor],
                 reference: dict[str, torch.Tensor], active_sh_degree: int | None = None,
                 active_sh_degree_t: int | None = None):
        super().__init__(params, config, active_sh_degree, active_sh_degree_t)
        self.held = held
        self.reference = {k: reference[k].detach().clone() for k in config.schema.param_names}

    @property
    def num_held(self) -> int:
        return int(self.held["xyz"].shape[0])

    def slice_views(self, timestamps: torch.Tensor, camera_centers: torch.Tensor):
        values = {k: torch.cat([v, self.held[k]]) for k, v in self.params.items()}
        return slice_values(values, self.config, self.active_sh_degree, self.active_sh_degree_t, timestamps,
                            camera_centers)

    def to(self, device: torch.device | str) -> "HeldGaussians4D":
        moved = super().to(device)
        held = Gaussians4D(self.held, self.config).to(device).params
        return HeldGaussians4D(moved.params, self.config, held, {k: v.to(device) for k, v in self.reference.items()},
                               self.active_sh_degree, self.active_sh_degree_t)

    def penalty(self) -> torch.Tensor:
        return anchor_penalty(self.held, self.reference, self.config)

    def training_state(self) -> Gaussians4D:
        """Own Gaussians, then the held ones as they are now: what a checkpoint holds."""
        return Gaussians4D({k: torch.cat([v.detach(), self.held[k].detach()]) for k, v in self.params.items()},
                           self.config, self.active_sh_degree, self.active_sh_degree_t)

    def whole(self) -> tuple[Gaussians4D, int]:
        """(the final model, how many held Gaussians end it): own Gaussians, the held ones that moved beyond
        :data:`SNAP` (changed content, now the segment's own), then the others with their geometry set back to their
        reference exactly and their appearance as trained."""
        kept = deviation(self.held, self.reference, self.config) <= SNAP
        appearance = self.config.schema.by_mlp

        def stayed(k: str) -> torch.Tensor:
            return (self.held[k].detach() if k in appearance else self.reference[k].to(self.held[k].device))[kept]

        params = {k: torch.cat([v.detach(), self.held[k].detach()[~kept], stayed(k)]) for k, v in self.params.items()}
        return Gaussians4D(params, self.config, self.active_sh_degree, self.active_sh_degree_t), int(kept.sum())


def split_held(model: Gaussians4D, count: int) -> tuple[Gaussians4D, dict[str, torch.Tensor]]:
    """A checkpoint's model (:meth:`HeldGaussians4D.training_state`) parted into its own Gaussians and the last
    ``count``, the held ones."""
    n = model.num_gaussians - count
    own = Gaussians4D({k: v.detach()[:n].clone() for k, v in model.params.items()}, model.config,
                      model.active_sh_degree, model.active_sh_degree_t)
    return own, {k: v.detach()[n:].clone() for k, v in model.params.items()}


__all__ = ["ANCHOR", "SNAP", "held_rows", "held_layer", "anchor_penalty", "deviation", "HeldGaussians4D",
           "split_held"]
