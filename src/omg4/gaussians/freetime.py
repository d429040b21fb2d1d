"""FreeTimeGS Gaussians: 3D Gaussians that move and live for a while (Wang et al., CVPR 2025; paper Table 3).

Each Gaussian has a position μx, a time centre μt, a duration s (stored as log s), a
velocity v, a 3D scale and rotation, an opacity and 3D SH colours. At time τ it shows

    μ(τ)   = μx + v · (τ − μt)                      (linear motion)
    p_t(τ) = exp(−½ ((τ − μt) / s)²)                 (temporal opacity, multiplies the opacity)
    Σ      = R diag(scale²) Rᵀ                       (plain 3D covariance, constant in time)

and is culled where p_t ≤ ``time_cull``, like a Real-Time4DGS Gaussian whose marginal is p_t.
:func:`slice_geometry_ftgs` returns the same :class:`~omg4.gaussians.covariance.SliceGeometry`
as the Real-Time4DGS conditioning, so colours, culling, the appearance MLPs and the
rasterizer are shared. Part of the render-only decoder: imports no training code.
"""

from __future__ import annotations

import numpy as np
import torch

from omg4.gaussians.covariance import SliceGeometry, temporal_marginal
from omg4.gaussians.initial import log_time_scale, neighbour_log_scales, spatial_params
from omg4.gaussians.rotation import build_rotation_3d
from omg4.render.small_matmul import small_matmul


def moved_means(xyz: torch.Tensor, velocity: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
    """μx + v · dt. xyz, velocity: [M, 3]; dt: [M] (τ − μt) → [M, 3]."""
    return xyz + velocity * dt[:, None]


def scaled_rotation_3d(log_scales: torch.Tensor, quaternions: torch.Tensor) -> torch.Tensor:
    """L = R diag(exp(log_scales)), so Σ = L Lᵀ and L ε (ε ~ N(0, I)) samples the Gaussian.
    log_scales: [M, 3], quaternions: [M, 4] (w, x, y, z) → [M, 3, 3]."""
    return build_rotation_3d(quaternions) * log_scales.exp().unsqueeze(-2)


def covariance_3d(log_scales: torch.Tensor, quaternions: torch.Tensor) -> torch.Tensor:
    """Σ = R diag(exp(log_scales)²) Rᵀ. log_scales: [M, 3], quaternions: [M, 4] (w, x, y, z) → [M, 3, 3]."""
    L = scaled_rotation_3d(log_scales, quaternions)
    return small_matmul(L, L.transpose(-1, -2))


def duration_variance(log_duration: torch.Tensor) -> torch.Tensor:
    """s² = exp(2 log s): the variance in time of the temporal opacity. [N, 1] or [N] → [N]."""
    return (2.0 * log_duration.reshape(-1)).exp()


def slice_geometry_ftgs(xyz: torch.Tensor, t: torch.Tensor, log_duration: torch.Tensor, velocity: torch.Tensor,
                        log_scales: torch.Tensor, quaternions: torch.Tensor, timestamps: float | torch.Tensor, *,
                        time_cull: float = 0.05) -> SliceGeometry:
    """FreeTimeGS Gaussians at each of ``timestamps``, culled where p_t ≤ ``time_cull``.

    Rows are (view, Gaussian) pairs grouped by view; ``dt`` holds μt − τ (the time argument
    colours would take; FreeTimeGS colours do not depend on time). Differentiable w.r.t. all inputs.

    Args:
        xyz: [N, 3]; t: [N, 1]; log_duration: [N, 1]; velocity: [N, 3]; log_scales: [N, 3];
        quaternions: [N, 4]; timestamps: one query time or [V] of them.
    """
    times = torch.as_tensor(timestamps, dtype=xyz.dtype, device=xyz.device).reshape(-1)
    var_t = duration_variance(log_duration)
    p_t = temporal_marginal(times[:, None] - t[None, :, 0], var_t)  # [V, N]
    views, index = (p_t > time_cull).nonzero(as_tuple=True)
    means, covars, marginal, dt = moving_rows(xyz, t[:, 0], var_t, velocity, log_scales, quaternions, times, views,
                                              index)
    return SliceGeometry(index=index, means=means, covars=covars, marginal=marginal, dt=dt, views=views)


def moving_rows(xyz: torch.Tensor, t: torch.Tensor, var_t: torch.Tensor, velocity: torch.Tensor,
                log_scales: torch.Tensor, quaternions: torch.Tensor, times: torch.Tensor, views: torch.Tensor,
                index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(means [M, 3], covariances [M, 3, 3], temporal opacities [M], μt − τ [M]) of the (view, Gaussian) rows
    ``(views, index)``: μx + v·(τ − μt), R diag(scale²) Rᵀ, p_t(τ). ``t``, ``var_t``: [N]."""
    dt = times.index_select(0, views) - t.index_select(0, index)  # τ − μt
    means = moved_means(xyz.index_select(0, index), velocity.index_select(0, index), dt)
    covars = covariance_3d(log_scales.index_select(0, index), quaternions.index_select(0, index))
    return means, covars, temporal_marginal(dt, var_t.index_select(0, index)), -dt


def opacity_regularizer(opacity_logit: torch.Tensor, t: torch.Tensor, log_duration: torch.Tensor,
                        timestamps: torch.Tensor) -> torch.Tensor:
    """FreeTimeGS's 4D regularization: mean over Gaussians and views of σ · sg[p_t(τ)].

    Penalizes high opacity where a Gaussian is visible in time, with the temporal opacity
    detached so the penalty does not shorten durations (FreeTimeGS §3.3).
    opacity_logit, t, log_duration: [N, 1]; timestamps: [V] → scalar.
    """
    times = torch.as_tensor(timestamps, dtype=t.dtype, device=t.device).reshape(-1)
    with torch.no_grad():
        p_t = temporal_marginal(times[:, None] - t[None, :, 0], duration_variance(log_duration))  # [V, N]
    return (torch.sigmoid(opacity_logit[:, 0])[None, :] * p_t).mean()


def initialize_ftgs(xyz: torch.Tensor, rgb: torch.Tensor, config, generator: torch.Generator | None
                    ) -> dict[str, torch.Tensor]:
    """FreeTimeGS from points: spread over the clip, t ~ U(t0, t1), zero velocity, the shared spatial terms
    (:mod:`omg4.gaussians.initial`); a point given k times (a budget above the point count) makes k Gaussians that
    share the clip, each with its point's scale and duration min(√(D/5), D / 2k)."""
    m, d = xyz.shape[0], config.period
    points, inverse = np.unique(xyz.double().numpy(), axis=0, return_inverse=True)
    params = spatial_params(rgb, neighbour_log_scales(points)[torch.from_numpy(inverse.reshape(-1))],
                            config.num_coeffs)
    copies = m / len(points)
    duration = min(log_time_scale(d), float(np.log(d / (2.0 * copies))))
    params.update(xyz=xyz.clone(), t=torch.rand(m, 1, generator=generator, device="cpu") * d + config.time_range[0],
                  duration=torch.full((m, 1), duration, device="cpu"), velocity=torch.zeros(m, 3, device="cpu"))
    return params


__all__ = ["initialize_ftgs", "scaled_rotation_3d", "covariance_3d", "duration_variance", "moved_means", "moving_rows",
           "opacity_regularizer", "slice_geometry_ftgs"]
