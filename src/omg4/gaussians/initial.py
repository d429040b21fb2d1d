"""The part of a model's initialization from a point cloud that every backbone shares (rt4dgs §3.5).

One Gaussian per point: an isotropic log-scale log √max(d², 1e-7), d² the mean squared distance to
the 3 nearest other points (simple-knn's ``distCUDA2``); an identity rotation; opacity logit(0.1);
the point's colour as the SH DC term, every other coefficient 0. Each backbone's ``initialize``
(:class:`omg4.gaussians.backbone.Backbone`) adds its time attributes.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from omg4.gaussians.sh import rgb_to_sh

IDENTITY_QUATERNION = (1.0, 0.0, 0.0, 0.0)


def mean_neighbour_sq_distance(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean squared distance of each point to its ``k`` nearest other points (simple-knn ``distCUDA2``).

    xyz: [M, 3] → [M] (0 for a single point).
    """
    m = xyz.shape[0]
    kk = min(k, m - 1)
    if kk == 0:
        return np.zeros(m)
    dist, _ = cKDTree(xyz).query(xyz, k=kk + 1)
    return (dist[:, 1:] ** 2).mean(axis=1)


def neighbour_log_scales(points: np.ndarray) -> torch.Tensor:
    """[M] log √max(d², 1e-7) of each point (float32)."""
    dist2 = torch.from_numpy(mean_neighbour_sq_distance(points)).float()
    return 0.5 * torch.log(dist2.clamp_min(1e-7))


def identity_quaternions(m: int) -> torch.Tensor:
    """[M, 4] (1, 0, 0, 0) on the CPU."""
    return torch.tensor(IDENTITY_QUATERNION, device="cpu").repeat(m, 1)


def spatial_params(rgb: torch.Tensor, log_scale: torch.Tensor, num_coeffs: int) -> dict[str, torch.Tensor]:
    """The shared attributes of ``M`` new Gaussians: isotropic ``scaling`` from ``log_scale`` [M], identity
    ``rotation``, ``opacity`` logit(0.1), ``features_dc`` from ``rgb`` [M, 3] and zero ``features_rest``."""
    m = rgb.shape[0]
    return {
        "scaling": log_scale.unsqueeze(1).repeat(1, 3),
        "rotation": identity_quaternions(m),
        "opacity": torch.full((m, 1), float(np.log(0.1 / 0.9)), device="cpu"),
        "features_dc": rgb_to_sh(rgb).unsqueeze(1),
        "features_rest": torch.zeros(m, num_coeffs - 1, 3, device="cpu"),
    }


def log_time_scale(period: float) -> float:
    """log √(D / 5): the initial temporal scale of a clip of duration D (rt4dgs §3.5)."""
    return 0.5 * float(np.log(period / 5.0))


__all__ = ["IDENTITY_QUATERNION", "mean_neighbour_sq_distance", "neighbour_log_scales", "identity_quaternions",
           "spatial_params", "log_time_scale"]
