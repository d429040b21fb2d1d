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

import functools
import math

import numpy as np
import torch

from omg4.gaussians.sh_kernels import C0, C1, C2, C3, basis_from_terms, contract_coefficients
from omg4.kernels import runs_cpu_kernels
from omg4.render.small_matmul import small_matmul

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


# Y_k as polynomials in (x, y, z): {monomial: coefficient}; "" is the constant, "xxy" is x²y
_BASIS_POLYNOMIALS: tuple[dict[str, float], ...] = (
    {"": C0},
    {"y": -C1}, {"z": C1}, {"x": -C1},
    {"xy": C2[0]}, {"yz": C2[1]}, {"zz": 2 * C2[2], "xx": -C2[2], "yy": -C2[2]}, {"xz": C2[3]},
    {"xx": C2[4], "yy": -C2[4]},
    {"xxy": 3 * C3[0], "yyy": -C3[0]}, {"xyz": C3[1]}, {"yzz": 4 * C3[2], "xxy": -C3[2], "yyy": -C3[2]},
    {"zzz": 2 * C3[3], "xxz": -3 * C3[3], "yyz": -3 * C3[3]}, {"xzz": 4 * C3[4], "xxx": -C3[4], "xyy": -C3[4]},
    {"xxz": C3[5], "yyz": -C3[5]}, {"xxx": C3[6], "xyy": -3 * C3[6]},
)


@functools.lru_cache(maxsize=None)
def _basis_terms() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The basis polynomials as terms: (basis index [T], indices into p = (1, x, y, z) [T, 3], coefficient [T])."""
    basis, index, coef = [], [], []
    for k, poly in enumerate(_BASIS_POLYNOMIALS):
        for mono, c in poly.items():
            basis.append(k)
            index.append([" xyz".index(ch) for ch in mono.rjust(3, " ")])
            coef.append(c)
    return np.array(basis, np.int64), np.array(index, np.int64), np.array(coef, np.float64)


@functools.lru_cache(maxsize=None)
def _basis_table(degree: int, dtype: torch.dtype, device: str) -> torch.Tensor:
    """[64, 16] constant B with ``Y(d) = m(d) @ B``, ``m`` the 64 products p_i p_j p_k of p = (1, x, y, z).

    Columns of basis functions above ``degree`` are zero.
    """
    table = torch.zeros(64, 16, dtype=torch.float64, device="cpu")
    for k, (i, j, l), coef in zip(*_basis_terms()):
        if k < num_sh_coeffs(degree):
            table[16 * i + 4 * j + l, k] = coef
    return table.to(dtype=dtype, device=device)


def _basis_16(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """[N, 16] Y_k(d) for k < (degree+1)², zeros after: numba kernels on CPU float32/float64 tensors
    (:func:`omg4.gaussians.sh_kernels.basis_from_terms`), else :func:`basis_by_table`."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    if runs_cpu_kernels(dirs):
        return basis_from_terms(dirs, num_sh_coeffs(degree), _basis_terms())
    return basis_by_table(dirs, degree)


def basis_by_table(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """:func:`_basis_16` as torch operations — the cubic monomials of ``d`` times a constant table (one
    product, no operation per basis function): the form devices other than the CPU run."""
    p = torch.cat([torch.ones_like(dirs[:, :1]), dirs], dim=1)  # [N, 4]
    monomials = (p[:, :, None, None] * p[:, None, :, None] * p[:, None, None, :]).reshape(-1, 64)
    return monomials @ _basis_table(degree, dirs.dtype, str(dirs.device))


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """The 3DGS real SH basis Y_k(d), k < (degree+1)² (3DGS ``eval_sh`` ordering and signs).

    Computed by numba kernels from the polynomials' terms on the CPU, as one product of the cubic
    monomials of ``d`` with a constant table elsewhere (no operation per basis function).

    Args:
        dirs: [N, 3] unit directions.
        degree: 0..3.
    Returns:
        [N, (degree+1)²] basis values.
    """
    return _basis_16(dirs, degree)[:, : num_sh_coeffs(degree)]


def eval_sh(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Plain 3D SH: Σ_k Y_k(d) coeffs[:, k] over k < (degree+1)².

    Args:
        coeffs: [N, K, C] with K ≥ (degree+1)²; dirs: [N, 3] unit.
    Returns:
        [N, C] (without the +0.5 offset).
    """
    basis = sh_basis(dirs, degree).to(coeffs.dtype)
    return small_matmul(basis.unsqueeze(1), coeffs[:, : basis.shape[1]]).squeeze(1)


def time_weights(dt: torch.Tensor, period: float, degree_t: int) -> torch.Tensor:
    """cos(2π n Δt / T) for n = 0..degree_t (rt4dgs §2). dt: [N] → [N, degree_t + 1]."""
    if period <= 0:
        raise ValueError(f"the SH time period must be positive, got {period}")
    n = torch.arange(degree_t + 1, dtype=dt.dtype, device=dt.device)
    return torch.cos((2 * math.pi / period) * dt.unsqueeze(-1) * n)


def _check_layout(coeffs: torch.Tensor, degree: int, degree_t: int, band_size: int, offset: int = 0) -> None:
    """``coeffs`` [N, K, C] (the coefficients from number ``offset`` on) hold the active bands."""
    if num_sh_coeffs(degree) > band_size or offset + coeffs.shape[1] < band_size * (degree_t + 1):
        raise ValueError(f"SH coefficients [{offset + coeffs.shape[1]}] do not hold degree {degree} × temporal "
                         f"degree {degree_t} in bands of {band_size}")


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
    _check_layout(coeffs, degree, degree_t, band_size)
    bands = degree_t + 1
    n, channels = coeffs.shape[0], coeffs.shape[2]
    bands_flat = coeffs[:, : band_size * bands].reshape(n, bands, band_size * channels)
    folded = small_matmul(time_weights(dt, period, degree_t).to(coeffs.dtype).unsqueeze(1), bands_flat)  # [N, 1, bs·C]
    return folded.reshape(n, band_size, channels)[:, : num_sh_coeffs(degree)]


def eval_sh_4d(coeffs: torch.Tensor | tuple[torch.Tensor, torch.Tensor], dirs: torch.Tensor, dt: torch.Tensor, period: float, degree: int,
               degree_t: int, *, band_size: int = 16, rows: torch.Tensor | None = None) -> torch.Tensor:
    """4D spherindrical harmonics (rt4dgs §2), without the +0.5 offset.

    The weight of coefficient ``band_size·n + k`` is ``cos(2π n Δt / T)·Y_k(d)`` (zero for
    inactive degrees), so the whole sum is one weighted reduction over the active bands
    (:func:`omg4.gaussians.sh_kernels.contract_coefficients`).

    Args:
        coeffs: [N, K, C] coefficient-major, K ≥ band_size · (degree_t + 1), one row per
            direction or with ``rows`` one per Gaussian; or the pair (DC [N, 1, C], the others
            [N, K − 1, C]), which is never joined.
        dirs: [M, 3] unit view directions.
        dt: [M] μ_t − τ.
        period: T = t1 − t0.
        degree, degree_t: active spatial / temporal degrees.
        rows: [M] int64 Gaussian of each direction (None: ``coeffs`` has a row per direction).
    Returns:
        [M, C].
    """
    dc, rest = (coeffs[:, :1], coeffs[:, 1:]) if torch.is_tensor(coeffs) else coeffs
    _check_layout(rest, degree, degree_t, band_size, offset=1)
    bands = degree_t + 1
    basis = _basis_16(dirs, degree)[:, :band_size]  # zero beyond the active degree
    weights = (time_weights(dt, period, degree_t).unsqueeze(-1) * basis.unsqueeze(1)).reshape(-1, bands * band_size)
    return contract_coefficients(dc, rest, weights.to(dc.dtype), rows)


def colors_from_sh(coeffs: torch.Tensor | tuple[torch.Tensor, torch.Tensor], dirs: torch.Tensor, dt: torch.Tensor, period: float, degree: int,
                   degree_t: int, *, band_size: int = 16, rows: torch.Tensor | None = None) -> torch.Tensor:
    """rgb = max(SH4D + 0.5, 0) (rt4dgs §1.5 (4)); arguments as :func:`eval_sh_4d`. Returns [M, C]."""
    return (eval_sh_4d(coeffs, dirs, dt, period, degree, degree_t, band_size=band_size, rows=rows)
            + 0.5).clamp_min(0.0)



def view_directions(points: torch.Tensor, camera_center: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit directions from the camera centre to ``points``. points: [N, 3], camera_center: [3] or [N, 3] → [N, 3]."""
    d = points - camera_center.to(points)
    return d / d.norm(dim=-1, keepdim=True).clamp_min(eps)


__all__ = ["C0", "C1", "C2", "C3", "MAX_SH_DEGREE", "num_sh_coeffs", "rgb_to_sh", "sh_to_rgb", "sh_basis", "basis_by_table", "eval_sh",
           "time_weights", "fold_time_sh", "eval_sh_4d", "colors_from_sh", "view_directions"]
