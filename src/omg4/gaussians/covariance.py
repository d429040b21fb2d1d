"""4D covariance and conditioning on time (reference rt4dgs §1.3–1.4).

``Σ4 = R4 diag(s²) R4ᵀ`` with blocks Σ11 [3, 3], Σ12 [3], Σtt (scalar). At a query time τ
the 4D Gaussian shows the conditional 3D Gaussian

    μ_3D(τ) = μ_xyz + Σ12 / Σtt · (τ − μ_t)
    Σ_3D    = Σ11 − Σ12 Σ12ᵀ / Σtt          (Schur complement, independent of τ)
    p_t(τ)  = exp(−½ (τ − μ_t)² / Σtt)       (unnormalized temporal marginal, peak 1)

and is culled where p_t ≤ ``time_cull`` (0.05 in the official code). :func:`slice_geometry`
is the geometry half of a time slice, shared by every model kind (the baseline and the
compressed models, whose colours come from elsewhere).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from omg4.gaussians.rotation import build_rotation_4d


def covariance_4d(scales: torch.Tensor, q_l: torch.Tensor, q_r: torch.Tensor,
                  convention: str = "flip") -> torch.Tensor:
    """Σ4 = L Lᵀ with L = R4 diag(s) (rt4dgs §1.3).

    Args:
        scales: [N, 4] positive scales (x, y, z, t), already activated.
        q_l, q_r: [N, 4] left / right quaternions (w, x, y, z), unnormalized.
        convention: 4D rotation convention (see :mod:`omg4.gaussians.rotation`).
    Returns:
        [N, 4, 4] symmetric covariance matrices.
    """
    L = build_rotation_4d(q_l, q_r, convention) * scales.unsqueeze(-2)
    return L @ L.transpose(-1, -2)


def temporal_marginal(dt: torch.Tensor, var_t: torch.Tensor) -> torch.Tensor:
    """p_t = exp(−½ dt² / Σtt) (rt4dgs §1.4, unnormalized). dt, var_t: [N] → [N]."""
    return torch.exp(-0.5 * dt * dt / var_t)


def condition_on_time(xyz: torch.Tensor, t: torch.Tensor, cov4: torch.Tensor,
                      timestamp: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Condition 4D Gaussians on time ``timestamp`` (rt4dgs §1.4).

    Args:
        xyz: [N, 3] spatial means.
        t: [N, 1] temporal means.
        cov4: [N, 4, 4] 4D covariances.
        timestamp: query time τ.
    Returns:
        mean3 [N, 3], cov3 [N, 3, 3] (conditional mean and covariance) and p_t [N]
        (unnormalized temporal marginal at τ).
    """
    var_t = cov4[:, 3, 3]
    cov_xt = cov4[:, :3, 3]
    dt = timestamp - t[:, 0]
    gain = cov_xt / var_t.unsqueeze(-1)  # [N, 3] = Σ12 / Σtt
    mean3 = xyz + gain * dt.unsqueeze(-1)
    cov3 = cov4[:, :3, :3] - gain.unsqueeze(-1) * cov_xt.unsqueeze(-2)
    return mean3, cov3, temporal_marginal(dt, var_t)


@dataclass
class SliceGeometry:
    """The Gaussians that survive the temporal cull at one time, conditioned on it.

    Attributes:
        index: [M] int64 rows of the survivors in the full set.
        means: [M, 3] conditional means μ_3D(τ).
        covars: [M, 3, 3] conditional covariances Σ_3D.
        marginal: [M] temporal marginals p_t(τ) (all > the cull threshold).
        dt: [M] μ_t − τ, the time argument of the 4D SH (rt4dgs §2).
    """

    index: torch.Tensor
    means: torch.Tensor
    covars: torch.Tensor
    marginal: torch.Tensor
    dt: torch.Tensor


def slice_geometry(xyz: torch.Tensor, t: torch.Tensor, scales: torch.Tensor, q_l: torch.Tensor, q_r: torch.Tensor,
                   timestamp: float, *, convention: str = "flip", time_cull: float = 0.05) -> SliceGeometry:
    """Conditioning on ``timestamp`` plus the temporal cull p_t ≤ ``time_cull`` (rt4dgs §1.4).

    Only Σtt is computed for every Gaussian; the full 4D covariance and the conditional
    are computed for the survivors. Differentiable w.r.t. all inputs.

    Args:
        xyz: [N, 3], t: [N, 1] means; scales: [N, 4] activated scales (x, y, z, t);
        q_l, q_r: [N, 4] quaternions; timestamp: query time.
    """
    L = build_rotation_4d(q_l, q_r, convention) * scales.unsqueeze(-2)  # [N, 4, 4]
    var_t = (L[:, 3, :] ** 2).sum(-1)
    p_t = temporal_marginal(timestamp - t[:, 0], var_t)
    index = (p_t > time_cull).nonzero().squeeze(1)
    L_k = L[index]
    mean3, cov3, _ = condition_on_time(xyz[index], t[index], L_k @ L_k.transpose(-1, -2), timestamp)
    return SliceGeometry(index=index, means=mean3, covars=cov3, marginal=p_t[index], dt=t[index, 0] - timestamp)


__all__ = ["covariance_4d", "temporal_marginal", "condition_on_time", "SliceGeometry", "slice_geometry"]
