"""4D covariance and conditioning on time (rt4dgs §1.3–1.4).

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

from omg4.gaussians.covariance_kernels import kernel_conditioning_terms
from omg4.gaussians.rotation import build_rotation_4d
from omg4.kernels import runs_cpu_kernels
from omg4.render.small_matmul import small_matmul


def scaled_rotation_4d(scales: torch.Tensor, q_l: torch.Tensor, q_r: torch.Tensor,
                       convention: str = "flip") -> torch.Tensor:
    """L = R4 diag(s), [N, 4, 4] (rt4dgs §1.3): Σ4 = L Lᵀ. Arguments as :func:`covariance_4d`."""
    return build_rotation_4d(q_l, q_r, convention) * scales.unsqueeze(-2)


def temporal_variance(L: torch.Tensor) -> torch.Tensor:
    """Σtt = ‖time row of L‖² of every Gaussian, from :func:`scaled_rotation_4d`'s [N, 4, 4] → [N]."""
    return L[:, 3, :].square().sum(-1)


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
    return _outer_rows(scaled_rotation_4d(scales, q_l, q_r, convention))


def _outer_rows(L: torch.Tensor) -> torch.Tensor:
    """L Lᵀ for [N, 4, 4] ``L`` (:func:`omg4.render.small_matmul.small_matmul`: the device's fastest form)."""
    return small_matmul(L, L.transpose(-1, -2))


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
    """The Gaussians that survive the temporal cull at one or more times, conditioned on them.

    Rows are (view, Gaussian) pairs, grouped by view in order: with ``V`` query times a
    Gaussian appears once per time at which it passes the cull.

    Attributes:
        index: [M] int64 rows of the survivors in the full set.
        means: [M, 3] conditional means μ_3D(τ).
        covars: [M, 3, 3] conditional covariances Σ_3D.
        marginal: [M] temporal marginals p_t(τ) (all > the cull threshold).
        dt: [M] μ_t − τ, the time argument of the 4D SH (rt4dgs §2).
        views: [M] int64 position of each row's query time in ``timestamps``.
    """

    index: torch.Tensor
    means: torch.Tensor
    covars: torch.Tensor
    marginal: torch.Tensor
    dt: torch.Tensor
    views: torch.Tensor


def conditioning_terms(scales: torch.Tensor, q_l: torch.Tensor, q_r: torch.Tensor, convention: str = "flip"
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The time-independent part of the conditioning of every Gaussian (rt4dgs §1.3–1.4).

    ``gain = Σ12 / Σtt`` [N, 3] (the velocity of the conditional mean), ``Σ_3D = Σ11 − Σ12 Σ12ᵀ / Σtt``
    [N, 3, 3] and ``Σtt`` [N], with ``Σ4 = L Lᵀ``, ``L = R4 diag(s)``. Differentiable (first order)
    w.r.t. the three inputs. On the CPU (float32/float64) one numba pass per Gaussian
    (:mod:`omg4.gaussians.covariance_kernels`); elsewhere :func:`torch_conditioning_terms`.

    Args: as :func:`covariance_4d`.
    """
    if runs_cpu_kernels(scales, q_l, q_r):
        return kernel_conditioning_terms(scales, q_l, q_r, convention)
    return torch_conditioning_terms(scales, q_l, q_r, convention)


def torch_conditioning_terms(scales: torch.Tensor, q_l: torch.Tensor, q_r: torch.Tensor, convention: str = "flip"
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`conditioning_terms` as torch operations (Σ4 by :func:`covariance_4d`), for devices other than the CPU."""
    cov4 = covariance_4d(scales, q_l, q_r, convention)
    var_t = cov4[:, 3, 3]
    gain = cov4[:, :3, 3] / var_t[:, None]
    return gain, cov4[:, :3, :3] - gain[:, :, None] * cov4[:, None, 3, :3], var_t


def slice_geometry(xyz: torch.Tensor, t: torch.Tensor, scales: torch.Tensor, q_l: torch.Tensor, q_r: torch.Tensor,
                   timestamps: float | torch.Tensor, *, convention: str = "flip",
                   time_cull: float = 0.05) -> SliceGeometry:
    """Conditioning on each of ``timestamps`` plus the temporal cull p_t ≤ ``time_cull`` (rt4dgs §1.4).

    One pass serves every query time: the time-independent terms (:func:`conditioning_terms`:
    gain, Σ_3D, Σtt) once per Gaussian, then :func:`condition_and_cull`. Differentiable w.r.t. all inputs.

    Args:
        xyz: [N, 3], t: [N, 1] means; scales: [N, 4] activated scales (x, y, z, t);
        q_l, q_r: [N, 4] quaternions; timestamps: one query time or [V] of them.
    """
    times = torch.as_tensor(timestamps, dtype=xyz.dtype, device=xyz.device).reshape(-1)
    return condition_and_cull(xyz, t, *conditioning_terms(scales, q_l, q_r, convention), times, time_cull=time_cull)


def condition_and_cull(xyz: torch.Tensor, t: torch.Tensor, gain: torch.Tensor, cov3: torch.Tensor,
                       var_t: torch.Tensor, times: torch.Tensor, *, time_cull: float = 0.05,
                       rows: torch.Tensor | None = None) -> SliceGeometry:
    """The Gaussians moving as ``xyz + gain · (τ − t)`` with covariance ``cov3`` that pass the temporal cull at
    each of ``times`` [V] (rt4dgs §1.4, from :func:`conditioning_terms` or a backbone's ``motion``).

    The marginals of all (time, Gaussian) pairs are computed together, the conditional means and marginals
    only for the surviving pairs. ``rows`` (sorted int64, optional) are the only candidates — a
    :class:`~omg4.gaussians.visibility.VisibilityIndex` window — so a frame of a render-only model touches
    nothing else; the result's ``index`` always holds rows of the whole set. Differentiable w.r.t. every
    tensor but ``times``.

    Args:
        xyz: [N, 3]; t: [N, 1]; gain: [N, 3] velocity of the mean; cov3: [N, 3, 3]; var_t: [N] temporal variance.
    """
    t_all = t[:, 0]
    t_rows, var_rows = (t_all, var_t) if rows is None else (t_all.index_select(0, rows), var_t.index_select(0, rows))
    with torch.no_grad():
        p_t = temporal_marginal(times[:, None] - t_rows[None, :], var_rows)  # [V, R]
        views, index = (p_t > time_cull).nonzero(as_tuple=True)
    if rows is not None:
        index = rows.index_select(0, index)
    means, covars, marginal, dt = conditioned_rows(xyz, t_all, gain, cov3, var_t, times, views, index)
    return SliceGeometry(index=index, means=means, covars=covars, marginal=marginal, dt=dt, views=views)


def conditioned_rows(xyz: torch.Tensor, t: torch.Tensor, gain: torch.Tensor, cov3: torch.Tensor, var_t: torch.Tensor,
                     times: torch.Tensor, views: torch.Tensor, index: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(means [M, 3], covariances [M, 3, 3], marginals [M], μ_t − τ [M]) of the (view, Gaussian) rows
    ``(views, index)`` (rt4dgs §1.4): μ + gain·(τ − μ_t), Σ_3D, exp(−½ (τ − μ_t)² / Σtt). ``t``, ``var_t``: [N]."""
    # gathers by index_select: its backward is an index_add, far cheaper on the CPU than indexing's
    dt = times.index_select(0, views) - t.index_select(0, index)
    means = xyz.index_select(0, index) + gain.index_select(0, index) * dt[:, None]
    marginal = temporal_marginal(dt, var_t.index_select(0, index))
    return means, cov3.index_select(0, index), marginal, -dt


__all__ = ["scaled_rotation_4d", "temporal_variance", "covariance_4d", "conditioning_terms", "torch_conditioning_terms",
           "temporal_marginal", "condition_on_time", "SliceGeometry", "slice_geometry", "condition_and_cull",
           "conditioned_rows"]
