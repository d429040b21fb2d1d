"""The model that moves through the OMG4 stages.

It starts as a baseline model of its backbone (explicit parameters) and gains, stage by
stage: learnable merge proxies (paper §4.3), MLP appearance replacing opacity and SH (§4.4),
and sub-vector quantizers replacing scale, rotation and appearance features, then the 4D
attributes (staged SVQ, §4.4) — which attributes each stage treats is the backbone's table
(:mod:`omg4.gaussians.backbone`). ``slice_at`` always assembles the effective per-Gaussian
values and renders them with the baseline's time slice and SH, so every stage is measured
with the same renderer.
"""

from __future__ import annotations

import torch

from omg4.compress.svq import quantized_values
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.gaussians.model import slice_values
from omg4.render.view import ViewSlicer


class CompressibleModel(ViewSlicer):
    """Per-Gaussian ``params`` (in the main Adam) plus optional merge proxy, appearance MLP and quantizers."""

    def __init__(self, params: dict[str, torch.Tensor], config: GaussianConfig, active_sh_degree: int,
                 active_sh_degree_t: int):
        self.params = params
        self.config = config
        self.active_sh_degree = active_sh_degree
        self.active_sh_degree_t = active_sh_degree_t
        self.merge = None  # omg4.compress.merging.MergeProxy during a merge round
        self.appearance = None  # omg4.gaussians.appearance.AppearanceMLP after attribute compression
        self.quantizers: dict = {}  # SVQ attribute name -> SubVectorQuantizer
        self.carried: dict[str, torch.Tensor] = {}  # a predicted segment's Gaussians of the segment before, fixed
        self.carried_rows = None  # their rows there (numpy int64, ascending; omg4.codec.carry)
        self.carry_decision = None  # a predicted segment's carry decision, as its header records it (compress.stream)

    @staticmethod
    def from_gaussians(model: Gaussians4D) -> "CompressibleModel":
        params = {k: v.detach().clone() for k, v in model.params.items()}
        return CompressibleModel(params, model.config, model.active_sh_degree, model.active_sh_degree_t)

    @property
    def num_gaussians(self) -> int:
        return int(self.params["xyz"].shape[0])

    @property
    def num_carried(self) -> int:
        """How many of the segment before's Gaussians render with this model's own (none but in a predicted
        segment)."""
        return int(self.carried["xyz"].shape[0]) if self.carried else 0

    def explicit_values(self) -> dict[str, torch.Tensor]:
        """Per-Gaussian values with quantized attributes replaced by their codebook reconstructions, the carried
        Gaussians (fixed) after the model's own rows."""
        values = dict(self.params)
        for attr, recon in quantized_values(self.quantizers).items():
            start = 0
            for name, width in self.config.schema.svq_widths(attr):
                values[name] = recon[:, start:start + width]
                start += width
        if self.carried:
            values = {k: torch.cat([v, self.carried[k]]) for k, v in values.items()}
        return values

    def merged_values(self) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
        """The per-Gaussian values after the merge proxy, and the rows they came from (None = all)."""
        values = self.explicit_values()
        if self.merge is None:
            return values, None
        values, keep = self.merge.apply(values)
        return {k: v[keep] for k, v in values.items()}, keep

    def slice_views(self, timestamps: torch.Tensor, camera_centers: torch.Tensor):
        """The :class:`omg4.render.view.TimeSlice` of ``V`` views (indices refer to this model's rows).

        The Real-Time4DGS conditioning and 4D SH of the baseline, with the appearance MLPs
        (when present) evaluated only on the rows that pass the temporal cull.
        """
        values, rows = self.explicit_values(), None
        if self.merge is not None:  # every row's values, the proxies' in their representatives' rows
            values, rows = self.merge.apply(values)
        sl = slice_values(values, self.config, self.active_sh_degree, self.active_sh_degree_t, timestamps,
                          camera_centers, appearance=self.appearance, rows=rows)
        sl.num_total = self.num_gaussians + self.num_carried
        return sl

    def to_gaussians(self) -> Gaussians4D:
        """A plain baseline model (only before attribute compression: appearance must be explicit)."""
        if self.appearance is not None:
            raise ValueError("a model with MLP appearance cannot be written as a baseline checkpoint")
        values, _ = self.merged_values()
        params = {k: v.detach().clone() for k, v in values.items()}
        return Gaussians4D(params, self.config, self.active_sh_degree, self.active_sh_degree_t)


__all__ = ["CompressibleModel"]
