"""FreeTimeGS's periodic relocation with a fixed Gaussian budget (FreeTimeGS §3.4).

Instead of cloning, splitting and pruning, every densification event moves the Gaussians
whose opacity fell below a threshold onto live ones, drawn with probability proportional to
the sampling score ``λ_g · ĝ + λ_o · σ`` (ĝ the mean view-space gradient normalized to its
maximum, σ the opacity; λ_g = λ_o = 0.5). A copy takes its target's attributes at a point
drawn from the target's own Gaussian in space and time: time centre μt' = μt + min(s, D) ε_t,
kept inside the clip [t0, t1] (a long-lived Gaussian would otherwise throw its copies far
outside it, where fp16 cannot even store the time), and position on the target's trajectory
at that time plus a spatial draw, μx + v (μt' − μt) + R diag(scale) ε (ε ~ N(0, I)); so copies
spread over the region they refine instead of coinciding, and both shrink by 1.6 like the
halves of a Real-Time4DGS split. A target drawn k times and its k
copies get opacity ``1 − (1 − σ)^(1/(k+1))`` each, which keeps their combined peak opacity σ
where they overlap; the moved rows and their targets restart with zero Adam moments. The
Gaussian count never changes. The threshold (``relocate_opacity``, 0.05) is
higher than 3DGS-MCMC's 0.005, which on the demo scene moved almost nothing (the sweep that chose it:
``docs/paper-map.md``, FreeTimeGS).
"""

from __future__ import annotations

import dataclasses
import math

import torch

from omg4 import distributed
from omg4.gaussians.freetime import opacity_regularizer, scaled_rotation_3d
from omg4.optimize.parameters import overwrite_rows
from omg4.optimize.step import step_generator
from omg4.settings import knob
from omg4.train.strategies.base import ScheduledEvents
from omg4.train.strategies.densification import DensifyStats

LAMBDA_GRAD = 0.5
LAMBDA_OPACITY = 0.5
SPLIT_SHRINK = math.log(1.6)


@dataclasses.dataclass
class Relocation(ScheduledEvents):
    """FreeTimeGS's density control (FreeTimeGS §3.3–3.4): a model that starts at its budget ``max_gaussians``
    exactly (with fewer initial points, points are drawn again: they spread over time), statistics and the 4D
    regularization ``lambda_reg`` · mean σ·sg[p_t] before ``densify_until``, a :func:`relocate` event (of the
    Gaussians below ``relocate_opacity``) every ``densify_interval`` steps strictly between ``densify_from`` and
    ``densify_until``; no opacity resets."""

    lambda_reg: float = knob(0.01, "FreeTimeGS 4D regularization weight (FreeTimeGS §3.3)")
    relocate_opacity: float = knob(0.05, "FreeTimeGS: Gaussians below this opacity are relocated")

    def initial_points(self, xyz, rgb, generator):
        if self.max_gaussians > len(xyz):
            extra = torch.randint(len(xyz), (self.max_gaussians - len(xyz),), generator=generator, device="cpu")
            return torch.cat([xyz, xyz[extra]]), torch.cat([rgb, rgb[extra]])
        return super().initial_points(xyz, rgb, generator)

    def regularizer(self, params, timestamps, step: int):
        if not self.lambda_reg or step >= self.densify_until:
            return None
        return self.lambda_reg * opacity_regularizer(params["opacity"], params["t"], params["duration"], timestamps)

    def after_step(self, model, optimizer, stats, step: int, extent: float) -> None:
        if self.densify_from < step < self.densify_until and step % self.densify_interval == 0:
            distributed.reduce_statistics(stats)  # every rank relocates by the statistics of every view
            relocate(model, optimizer, stats, min_opacity=self.relocate_opacity,
                     generator=step_generator(self.seed, step, stream=1))


def relocate(model, optimizer, stats: DensifyStats, *, min_opacity: float, generator: torch.Generator) -> int:
    """Move the Gaussians with opacity < ``min_opacity`` onto sampled live ones; returns how many moved.

    The gradient statistics restart afterwards, whether anything moved or not.
    """
    opacity = torch.sigmoid(model.params["opacity"].detach()[:, 0])
    dead = (opacity < min_opacity).nonzero().squeeze(1)
    alive = (opacity >= min_opacity).nonzero().squeeze(1)
    moved = int(dead.numel()) if alive.numel() else 0
    if moved:
        _move(model.params, optimizer, dead, alive, opacity, stats.mean_grad(), generator, model.config.time_range)
    stats.reset(opacity.shape[0])
    return moved


def _move(params: dict[str, torch.Tensor], optimizer, dead: torch.Tensor, alive: torch.Tensor, opacity: torch.Tensor,
          grads: torch.Tensor, generator: torch.Generator, time_range: tuple[float, float]) -> None:
    """Copy sampled ``alive`` rows into the ``dead`` rows (see the module docstring)."""
    score = LAMBDA_GRAD * grads / grads.max().clamp_min(1e-12) + LAMBDA_OPACITY * opacity
    weights = score.index_select(0, alive).double().cpu().clamp_min(1e-12)
    draws = torch.multinomial(weights, dead.numel(), replacement=True, generator=generator)
    targets = alive.index_select(0, draws.to(alive.device))
    copies = torch.bincount(targets, minlength=opacity.shape[0]).index_select(0, targets)  # k per drawn row
    shared = 1.0 - (1.0 - opacity.index_select(0, targets)).pow(1.0 / (copies + 1.0))
    logit = torch.logit(shared.clamp(1e-6, 1 - 1e-6))[:, None]
    copied = {name: value.detach().index_select(0, targets) for name, value in params.items()}
    copied["opacity"] = logit
    kept = dict(copied)  # the targets keep their place
    eps = torch.randn(targets.numel(), 4, generator=generator).to(logit)  # CPU draw: reproducible on any device
    t0, t1 = time_range
    offset = scaled_rotation_3d(copied["scaling"], copied["rotation"]) @ eps[:, :3, None]
    t_new = (copied["t"] + copied["duration"].exp().clamp(max=t1 - t0) * eps[:, 3:]).clamp(t0, t1)
    copied["xyz"] = copied["xyz"] + copied["velocity"] * (t_new - copied["t"]) + offset[:, :, 0]
    copied["t"] = t_new
    copied["scaling"] = copied["scaling"] - SPLIT_SHRINK
    kept["scaling"] = kept["scaling"] - SPLIT_SHRINK
    rows = torch.cat([dead, targets])  # the moved rows take the copies; the targets their shared opacity
    overwrite_rows(params, optimizer, rows, {name: torch.cat([copied[name], kept[name]]) for name in copied})
