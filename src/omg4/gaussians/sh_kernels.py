"""numba kernels of the SH colour on the CPU (rt4dgs §2), forward and backward: the basis and the weighted sum.

**Basis.** ``Y_k(d)`` for k < 16 from the basis polynomials as terms (basis index, three indices
into ``p = (1, x, y, z)``, coefficient; :func:`omg4.gaussians.sh.sh_basis`), and ∂/∂d from the
same terms — in torch the cubic monomials ``p ⊗ p ⊗ p`` are an ``[M, 64]`` intermediate whose
broadcast products and reductions are a large share of a CPU training step at 80k Gaussians.

**Weighted sum.** ``out[m] = Σ_k w[m, k] · coeffs[rows[m], k]``: row ``m`` of a time slice takes the
coefficients of its Gaussian ``rows[m]`` (a Gaussian appears once per view that sees it); the
coefficients come as the DC block and the others (the model's two parameters, never joined). In
torch this is a join and gather of ``[M, K, C]`` coefficients, a product and, in the backward pass,
an ``[M, K, C]`` outer product scattered back into ``[N, K, C]`` — about a fifth of a CPU training
step at 80k Gaussians. Here the forward sum and ∂/∂w run in parallel over rows, ∂/∂coeffs in
parallel over ranges of Gaussians (each task owns its Gaussians' coefficient rows, so the scatter
never races and writes each row whole).

Elsewhere (CUDA) the torch forms run (:func:`torch_contraction`, with
:func:`omg4.render.small_matmul.small_matmul`, and the monomial table of :mod:`omg4.gaussians.sh`).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange
from torch.autograd.function import once_differentiable

from omg4.kernels import FAST_MATH, as_numpy, keeping_torch_threads, runs_cpu_kernels  # also points numba's cache
from omg4.render.small_matmul import small_matmul

_PARTS_PER_THREAD = 4
"""Gaussian ranges per thread in the ∂/∂coeffs kernel (each task scans every row, keeps its own)."""


ROW_CHUNK = 1024
"""Rows per parallel task of the basis kernels (their scratch arrays are made once per task)."""

NUM_BASIS = 16
"""Spatial basis functions up to degree 3."""

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)
"""The constants of the 3DGS real SH basis (``eval_sh``), degrees 0 to 3 (:mod:`omg4.gaussians.sh`)."""


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _basis_forward(dirs, active, term_basis, term_index, term_coef, out):
    num_rows = dirs.shape[0]
    for chunk in prange((num_rows + ROW_CHUNK - 1) // ROW_CHUNK):
        p = np.empty(4)
        y = np.empty(NUM_BASIS)
        for m in range(chunk * ROW_CHUNK, min(num_rows, (chunk + 1) * ROW_CHUNK)):
            p[0] = 1.0
            p[1] = dirs[m, 0]
            p[2] = dirs[m, 1]
            p[3] = dirs[m, 2]
            for k in range(NUM_BASIS):
                y[k] = 0.0
            for t in range(term_basis.shape[0]):
                if term_basis[t] < active:
                    y[term_basis[t]] += term_coef[t] * p[term_index[t, 0]] * p[term_index[t, 1]] * p[term_index[t, 2]]
            for k in range(NUM_BASIS):
                out[m, k] = y[k]


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _basis_backward(dirs, active, term_basis, term_index, term_coef, grad_y, grad_dirs):
    num_rows = dirs.shape[0]
    for chunk in prange((num_rows + ROW_CHUNK - 1) // ROW_CHUNK):
        p = np.empty(4)
        gp = np.empty(4)
        for m in range(chunk * ROW_CHUNK, min(num_rows, (chunk + 1) * ROW_CHUNK)):
            p[0] = 1.0
            p[1] = dirs[m, 0]
            p[2] = dirs[m, 1]
            p[3] = dirs[m, 2]
            for a in range(4):
                gp[a] = 0.0
            for t in range(term_basis.shape[0]):
                if term_basis[t] < active:
                    w = term_coef[t] * grad_y[m, term_basis[t]]
                    i, j, k = term_index[t, 0], term_index[t, 1], term_index[t, 2]
                    gp[i] += w * p[j] * p[k]
                    gp[j] += w * p[i] * p[k]
                    gp[k] += w * p[i] * p[j]
            grad_dirs[m, 0] = gp[1]
            grad_dirs[m, 1] = gp[2]
            grad_dirs[m, 2] = gp[3]


class _Basis(torch.autograd.Function):
    """(dirs [M, 3], active, terms) → [M, 16] with zeros from column ``active`` on (numba kernels)."""

    @staticmethod
    def forward(ctx, dirs, active, terms):
        d = as_numpy(dirs)
        out = np.empty((d.shape[0], NUM_BASIS), dtype=d.dtype)
        with keeping_torch_threads():
            _basis_forward(d, active, *terms, out)
        ctx.save_for_backward(dirs)
        ctx.active, ctx.terms = active, terms
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_y):
        (dirs,) = ctx.saved_tensors
        d = as_numpy(dirs)
        grad_dirs = np.empty_like(d)
        with keeping_torch_threads():
            _basis_backward(d, ctx.active, *ctx.terms, as_numpy(grad_y.to(dirs.dtype)), grad_dirs)
        return torch.from_numpy(grad_dirs), None, None


def basis_from_terms(dirs: torch.Tensor, active: int, terms: tuple[np.ndarray, np.ndarray, np.ndarray]
                     ) -> torch.Tensor:
    """``[M, 16]`` basis values ``Σ_terms coef · p_i p_j p_k`` of the functions ``k < active`` (zeros after) on
    CPU float32/float64 ``dirs [M, 3]``; differentiable (first order, reverse mode).

    terms: (basis index [T], indices into (1, x, y, z) [T, 3], coefficient [T]).
    """
    return _Basis.apply(dirs, active, terms)


@njit(cache=True, inline="always")
def _coefficient(dc, rest, g, k, c):
    """Coefficient ``k`` (0: the DC block, else ``rest[k − 1]``) of Gaussian ``g``, channel ``c``."""
    return dc[g, 0, c] if k == 0 else rest[g, k - 1, c]


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _forward(dc, rest, weights, rows, out):
    num_rows, num_k = weights.shape
    channels = out.shape[1]
    for m in prange(num_rows):
        g = rows[m]
        for c in range(channels):
            acc = 0.0
            for k in range(num_k):
                acc += weights[m, k] * _coefficient(dc, rest, g, k, c)
            out[m, c] = acc


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _grad_weights(dc, rest, rows, grad_out, grad_weights):
    num_rows, num_k = grad_weights.shape
    channels = grad_out.shape[1]
    for m in prange(num_rows):
        g = rows[m]
        for k in range(num_k):
            acc = 0.0
            for c in range(channels):
                acc += grad_out[m, c] * _coefficient(dc, rest, g, k, c)
            grad_weights[m, k] = acc


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _grad_coefficients(weights, rows, grad_out, grad_dc, grad_rest, num_parts):
    num_rows, num_k = weights.shape
    channels = grad_out.shape[1]
    n = grad_dc.shape[0]
    for part in prange(num_parts):  # each part owns a range of Gaussians: no two tasks write one row
        lo = part * n // num_parts
        hi = (part + 1) * n // num_parts
        for m in range(num_rows):
            g = rows[m]
            if g < lo or g >= hi or num_k == 0:
                continue
            for c in range(channels):
                grad_dc[g, 0, c] += weights[m, 0] * grad_out[m, c]
            for k in range(1, num_k):
                w = weights[m, k]
                for c in range(channels):
                    grad_rest[g, k - 1, c] += w * grad_out[m, c]


class _GatheredContraction(torch.autograd.Function):
    """(dc [N, 1, C], rest [N, R, C], weights [M, K], rows [M]) → [M, C] on the CPU (numba kernels)."""

    @staticmethod
    def forward(ctx, dc, rest, weights, rows):
        w = as_numpy(weights)
        out = np.empty((weights.shape[0], dc.shape[2]), dtype=w.dtype)
        with keeping_torch_threads():
            _forward(as_numpy(dc), as_numpy(rest), w, as_numpy(rows), out)
        ctx.save_for_backward(dc, rest, weights, rows)
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        dc, rest, weights, rows = ctx.saved_tensors
        g = as_numpy(grad_out.to(weights.dtype))
        grad_dc = grad_rest = grad_weights = None
        with keeping_torch_threads():
            if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
                grad_dc = torch.zeros(dc.shape, dtype=dc.dtype)
                grad_rest = torch.zeros(rest.shape, dtype=rest.dtype)
                _grad_coefficients(as_numpy(weights), as_numpy(rows), g, grad_dc.numpy(), grad_rest.numpy(),
                                   _PARTS_PER_THREAD * numba.get_num_threads())
            if ctx.needs_input_grad[2]:
                grad_weights = torch.empty(weights.shape, dtype=weights.dtype)
                _grad_weights(as_numpy(dc), as_numpy(rest), as_numpy(rows), g, grad_weights.numpy())
        return grad_dc, grad_rest, grad_weights, None


def contract_coefficients(dc: torch.Tensor, rest: torch.Tensor, weights: torch.Tensor,
                          rows: torch.Tensor | None = None) -> torch.Tensor:
    """``Σ_k weights[m, k] · [dc, rest][rows[m], k, :]`` for every row ``m``; differentiable (first order, reverse
    mode) in every input. float32 and float64 run the CPU kernels; other dtypes and devices the torch form.

    Args:
        dc: [N, 1, C] and rest: [N, R, C] the coefficients (the DC one, then the others), R + 1 ≥ K.
        weights: [M, K] weights of the same dtype and device.
        rows: [M] int64 indices into the coefficients (None: row ``m`` uses Gaussian ``m``, M = N).
    Returns:
        [M, C].
    """
    num_rows, num_k = weights.shape
    if (dc.dim() != 3 or dc.shape[1] != 1 or rest.shape[::2] != dc.shape[::2] or rest.shape[1] + 1 < num_k
            or not dc.dtype == rest.dtype == weights.dtype):
        raise ValueError(f"coefficients {dc.dtype} {list(dc.shape)} + {rest.dtype} {list(rest.shape)} do not fit "
                         f"weights {weights.dtype} {list(weights.shape)}")
    if rows is None and dc.shape[0] != num_rows:
        raise ValueError(f"{num_rows} weight rows for {dc.shape[0]} coefficient rows")
    if not runs_cpu_kernels(dc, rest, weights):
        return torch_contraction(dc, rest, weights, rows)
    if rows is None:  # valid by construction
        rows = torch.arange(num_rows, device=weights.device)
    elif rows.shape != (num_rows,) or (num_rows and not 0 <= int(rows.min()) <= int(rows.max()) < dc.shape[0]):
        raise ValueError(f"rows must be {num_rows} indices into {dc.shape[0]} Gaussians")  # the kernels do not check
    return _GatheredContraction.apply(dc, rest, weights, rows)


def torch_contraction(dc: torch.Tensor, rest: torch.Tensor, weights: torch.Tensor,
                      rows: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`contract_coefficients` as torch operations (gather unless ``rows`` is None, join, product), for
    devices other than the CPU."""
    parts = (dc, rest[:, : weights.shape[1] - 1])
    coeffs = torch.cat(parts if rows is None else [part.index_select(0, rows) for part in parts], dim=1)
    return small_matmul(weights.unsqueeze(1), coeffs).squeeze(1)


__all__ = ["C0", "C1", "C2", "C3", "basis_from_terms", "contract_coefficients", "torch_contraction"]
