"""Lasting Gaussians stand still (beyond the paper): a training penalty on the motion of the Gaussians that last
through the clip, so a capture's static content is learnt as Gaussians that stay put — which a predicted segment
can then carry from the segment before as they are (:mod:`omg4.compress.carry_stage`) instead of learning them again.

Real-Time4DGS lets every Gaussian move (the velocity of its conditional mean, Σxt / Σtt, rt4dgs §1.4), and training
leaves the static background drifting a few of its sizes across a segment: fitted to that segment's frames, the
drift is harmless there and wrong wherever the Gaussian is carried on. The penalty is the mean over Gaussians of

    w_i · (|v_i| · D / s_i)²

— the displacement over the clip's duration D in units of the Gaussian's largest scale s_i, weighted by how much it
lasts, w_i = its temporal marginal at the farther end of the clip (1 for a Gaussian that spans the clip, → 0 for a
brief one, which may move as the video does); w and s are held fixed (no gradient). The photometric loss outweighs it
wherever the video shows motion.
"""

from __future__ import annotations

import torch

from omg4.gaussians.visibility import least_marginal


def stillness_penalty(params: dict[str, torch.Tensor], config, time_range: tuple[float, float]) -> torch.Tensor:
    """The penalty (module docstring) of the Gaussians ``params`` of ``config``'s backbone over ``time_range``."""
    velocity, _, var_t = config.schema.motion(params, config)
    t0, t1 = time_range
    weight = least_marginal(params["t"].detach(), var_t.detach(), t0, t1).to(velocity.dtype)
    size = params["scaling"].detach().max(dim=1).values.exp()
    moved = velocity.norm(dim=1) * (t1 - t0) / size
    return (weight * moved.square()).mean()

__all__ = ["stillness_penalty"]
