"""Products of many tiny matrices (one per Gaussian), in the form each device runs fastest.

The per-Gaussian 4D covariance (rt4dgs §1.3) and the EWA projection's ``J R Σ Rᵀ Jᵀ`` are
products of 2×3, 3×3 and 4×4 matrices, one per Gaussian. On the CPU a batched matrix
product is several times faster than broadcasting; on a GPU a batched GEMM of tiny matrices is launch- and
occupancy-bound, while a
broadcast multiply and a sum are two element-wise kernels over all Gaussians.
"""

from __future__ import annotations

import torch


def small_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` over the last two axes for [..., n, k] × [..., k, m] (batch axes broadcast)."""
    if a.is_cuda:
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ b


__all__ = ["small_matmul"]
