"""Spherical harmonics: the 3DGS real SH basis and the 4D "spherindrical" harmonics.

Reference rt4dgs §2. Coefficients are coefficient-major ``[N, K, C]`` (coefficient k of
channel c is ``coeffs[:, k, c]``) and grouped in temporal bands of ``band_size`` (16 for
spatial degree 3): index ``band_size·n + k`` multiplies ``cos(2π n Δt / T) · Y_k(d)``.

    SH4D(d, Δt) = Σ_{n ≤ deg_t} cos(2π n Δt / T) Σ_{k < (deg+1)²} Y_k(d) c[band_size·n + k]
    rgb         = max(SH4D + 0.5, 0)

Δt = μ_t − τ (cosine is even, so the sign does not matter). The official CUDA code
evaluates the temporal bands only when the spatial degree is 3; here they follow the
active temporal degree alone (identical under the official degree schedule, where the
temporal degree rises only after the spatial degree reached 3).
"""

from __future__ import annotations

import math

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)
MAX_SH_DEGREE = 3


def num_sh_coeffs(degree: int) -> int:
    """(degree + 1)² coefficients per temporal band and channel."""
    return (degree + 1) ** 2


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient of a constant colour: (rgb − 0.5) / C0 (rt4dgs §2)."""
    return (rgb - 0.5) / C0


def sh_to_rgb(sh: torch.Tensor) -> torch.Tensor:
    """Colour of a DC coefficient: sh · C0 + 0.5 (rt4dgs §2)."""
    return sh * C0 + 0.5


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """The 3DGS real SH basis Y_k(d), k < (degree+1)² (3DGS ``eval_sh`` ordering and signs).

    Args:
        dirs: [N, 3] unit directions.
        degree: 0..3.
    Returns:
        [N, (degree+1)²] basis values.
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy), C3[5] * z * (xx - yy),
                C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Plain 3D SH: Σ_k Y_k(d) coeffs[:, k] over k < (degree+1)².

    Args:
        coeffs: [N, K, C] with K ≥ (degree+1)²; dirs: [N, 3] unit.
    Returns:
        [N, C] (without the +0.5 offset).
    """
    basis = sh_basis(dirs, degree)
    return (basis.unsqueeze(-1) * coeffs[:, : basis.shape[1]]).sum(1)


def time_weights(dt: torch.Tensor, period: float, degree_t: int) -> torch.Tensor:
    """cos(2π n Δt / T) for n = 0..degree_t (rt4dgs §2). dt: [N] → [N, degree_t + 1]."""
    if period <= 0:
        raise ValueError(f"the SH time period must be positive, got {period}")
    n = torch.arange(degree_t + 1, dtype=dt.dtype, device=dt.device)
    return torch.cos((2 * math.pi / period) * dt.unsqueeze(-1) * n)


def _bands(coeffs: torch.Tensor, degree: int, degree_t: int, band_size: int) -> torch.Tensor:
    """The active coefficients as [N, degree_t + 1, (degree+1)², C] (validates the layout)."""
    nb, bands = num_sh_coeffs(degree), degree_t + 1
    if nb > band_size or coeffs.shape[1] < band_size * bands:
        raise ValueError(f"SH coefficients [{coeffs.shape[1]}] do not hold degree {degree} × temporal degree "
                         f"{degree_t} in bands of {band_size}")
    return coeffs[:, : band_size * bands].reshape(coeffs.shape[0], bands, band_size, coeffs.shape[2])[:, :, :nb]


def fold_time_sh(coeffs: torch.Tensor, dt: torch.Tensor, period: float, degree: int, degree_t: int, *,
                 band_size: int = 16) -> torch.Tensor:
    """The 3D SH coefficients of the 4D SH at time offset Δt: Σ_n cos(2π n Δt / T) c[band_size·n + k].

    Args:
        coeffs: [N, K, C] 4D coefficients, K ≥ band_size · (degree_t + 1).
        dt: [N] μ_t − τ.
        period: T = t1 − t0.
        degree, degree_t: active spatial / temporal degrees.
        band_size: coefficients per temporal band ((max spatial degree + 1)²).
    Returns:
        [N, (degree+1)², C] 3D SH coefficients.
    """
    c = _bands(coeffs, degree, degree_t, band_size)
    return (time_weights(dt, period, degree_t)[:, :, None, None] * c).sum(1)


def eval_sh_4d(coeffs: torch.Tensor, dirs: torch.Tensor, dt: torch.Tensor, period: float, degree: int,
               degree_t: int, *, band_size: int = 16) -> torch.Tensor:
    """4D spherindrical harmonics (rt4dgs §2), without the +0.5 offset.

    Args:
        coeffs: [N, K, C] coefficient-major, K ≥ band_size · (degree_t + 1).
        dirs: [N, 3] unit view directions.
        dt: [N] μ_t − τ.
        period: T = t1 − t0.
        degree, degree_t: active spatial / temporal degrees.
    Returns:
        [N, C].
    """
    c = _bands(coeffs, degree, degree_t, band_size)  # [N, bands, nb, C]
    weights = time_weights(dt, period, degree_t).unsqueeze(-1) * sh_basis(dirs, degree).unsqueeze(1)  # [N, bands, nb]
    return (weights.unsqueeze(-1) * c).sum((1, 2))


def colors_from_sh(coeffs: torch.Tensor, dirs: torch.Tensor, dt: torch.Tensor, period: float, degree: int,
                   degree_t: int, *, band_size: int = 16) -> torch.Tensor:
    """rgb = max(SH4D + 0.5, 0) (rt4dgs §1.5 (4)); arguments as :func:`eval_sh_4d`. Returns [N, C]."""
    return (eval_sh_4d(coeffs, dirs, dt, period, degree, degree_t, band_size=band_size) + 0.5).clamp_min(0.0)


def view_directions(points: torch.Tensor, camera_center: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit directions from the camera centre to ``points``. points: [N, 3], camera_center: [3] → [N, 3]."""
    d = points - camera_center.to(points)
    return d / d.norm(dim=-1, keepdim=True).clamp_min(eps)


__all__ = ["C0", "C1", "C2", "C3", "MAX_SH_DEGREE", "num_sh_coeffs", "rgb_to_sh", "sh_to_rgb", "sh_basis", "eval_sh",
           "time_weights", "fold_time_sh", "eval_sh_4d", "colors_from_sh", "view_directions"]
