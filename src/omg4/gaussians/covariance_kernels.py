"""numba kernels of the Real-Time4DGS conditioning terms on the CPU (rt4dgs §1.2–1.4), forward and backward.

Per Gaussian, from its activated scales ``s`` and its two (unnormalized) quaternions:

    R4 = rotation of (q_l/‖q_l‖, q_r/‖q_r‖),   L = R4 diag(s),   Σ4 = L Lᵀ
    var_t = Σtt,   gain = Σ12 / Σtt,   Σ_3D = Σ11 − Σ12 Σ12ᵀ / Σtt

— everything of the conditioning that does not depend on the query time (the conditional mean
``μ + gain·(τ − μ_t)`` and the marginal ``exp(−½ (τ − μ_t)² / var_t)`` are per (view, Gaussian)
row and stay in torch). Each entry of R4 is a sum of four products ``±q_l[a] q_r[b]``
(:func:`omg4.gaussians.rotation.product_table`), so one pass over the Gaussians does the whole
chain in registers; in torch it is a normalisation, an outer product, a table product, a
broadcast scale, a batched ``L Lᵀ`` and the Schur complement, each with its backward — about a
fifth of a CPU training step at 80k Gaussians. The backward pass recomputes the forward values
and applies the chain rule by hand (``∂Σ4 = ∂L Lᵀ + L ∂Lᵀ`` gives ``∂/∂L = (G + Gᵀ) L``).

Elsewhere (CUDA, other dtypes) :func:`omg4.gaussians.covariance.conditioning_terms` runs its torch form.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from numba import njit, prange
from torch.autograd.function import once_differentiable

from omg4.gaussians.rotation import product_table
from omg4.kernels import FAST_MATH, as_numpy, keeping_torch_threads  # also points numba's cache where it can write

GAUSSIAN_CHUNK = 1024
"""Gaussians per parallel task (the task's scratch arrays are made once)."""

NORMALIZE_EPS = 1e-12
"""``F.normalize``'s lower bound on a quaternion's norm."""


@functools.lru_cache(maxsize=None)
def rotation_terms(convention: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(left [16, 4], right [16, 4] int64, signs [16, 4] float64)``: entry ``e`` of the flattened R4 is
    ``Σ_k signs[e, k] · q_l[left[e, k]] · q_r[right[e, k]]`` (the nonzeros of the product table)."""
    table = product_table(convention, torch.float64, "cpu").numpy()  # [16 (a·4 + b), 16 (entry)]
    pairs = np.zeros((16, 4), dtype=np.int64)
    signs = np.zeros((16, 4), dtype=np.float64)
    for entry in range(16):
        nonzero = np.flatnonzero(table[:, entry])
        if len(nonzero) != 4:
            raise AssertionError(f"R4 entry {entry} has {len(nonzero)} quaternion products, expected 4")
        pairs[entry], signs[entry] = nonzero, table[nonzero, entry]
    return pairs // 4, pairs % 4, signs


@njit(cache=True, inline="always")
def _unit(q, g, out):
    """``out = q[g] / max(‖q[g]‖, eps)``; returns the clamped norm."""
    norm = np.sqrt(q[g, 0] * q[g, 0] + q[g, 1] * q[g, 1] + q[g, 2] * q[g, 2] + q[g, 3] * q[g, 3])
    norm = max(norm, NORMALIZE_EPS)
    for a in range(4):
        out[a] = q[g, a] / norm
    return norm


@njit(cache=True, inline="always")
def _scaled_rotation(scales, q_l, q_r, g, left, right, signs, ul, ur, rot, L):
    """Fills the unit quaternions ``ul``, ``ur``, ``rot`` = R4 and ``L`` = R4 diag(s) (flattened [16]) of
    Gaussian ``g``; returns the two clamped norms."""
    norm_l = _unit(q_l, g, ul)
    norm_r = _unit(q_r, g, ur)
    for e in range(16):
        acc = 0.0
        for k in range(4):
            acc += signs[e, k] * ul[left[e, k]] * ur[right[e, k]]
        rot[e] = acc
        L[e] = acc * scales[g, e % 4]
    return norm_l, norm_r


@njit(cache=True, inline="always")
def _row_dot(L, i, j):
    """Σ4[i, j] = row i of L · row j of L."""
    return L[4 * i] * L[4 * j] + L[4 * i + 1] * L[4 * j + 1] + L[4 * i + 2] * L[4 * j + 2] + L[4 * i + 3] * L[4 * j + 3]


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _terms_forward(scales, q_l, q_r, left, right, signs, gain, cov3, var_t):
    n = scales.shape[0]
    num_chunks = (n + GAUSSIAN_CHUNK - 1) // GAUSSIAN_CHUNK
    for chunk in prange(num_chunks):
        ul, ur = np.empty(4), np.empty(4)
        rot, L = np.empty(16), np.empty(16)
        for g in range(chunk * GAUSSIAN_CHUNK, min(n, (chunk + 1) * GAUSSIAN_CHUNK)):
            _scaled_rotation(scales, q_l, q_r, g, left, right, signs, ul, ur, rot, L)
            var = _row_dot(L, 3, 3)
            var_t[g] = var
            for i in range(3):
                c_i = _row_dot(L, i, 3)
                gain[g, i] = c_i / var
                for j in range(3):
                    cov3[g, i, j] = _row_dot(L, i, j) - c_i * _row_dot(L, j, 3) / var


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _terms_backward(scales, q_l, q_r, left, right, signs, grad_gain, grad_cov3, grad_var, grad_scales, grad_ql, grad_qr):
    n = scales.shape[0]
    num_chunks = (n + GAUSSIAN_CHUNK - 1) // GAUSSIAN_CHUNK
    for chunk in prange(num_chunks):
        ul, ur = np.empty(4), np.empty(4)
        rot, L = np.empty(16), np.empty(16)
        c = np.empty(3)
        sym = np.empty((4, 4))  # G + Gᵀ, G = ∂loss/∂Σ4 through the three outputs
        grad_L = np.empty(16)
        gul, gur = np.empty(4), np.empty(4)
        for g in range(chunk * GAUSSIAN_CHUNK, min(n, (chunk + 1) * GAUSSIAN_CHUNK)):
            norm_l, norm_r = _scaled_rotation(scales, q_l, q_r, g, left, right, signs, ul, ur, rot, L)
            var = _row_dot(L, 3, 3)
            for i in range(3):
                c[i] = _row_dot(L, i, 3)
            # gain = c / var and Σ_3D = Σ11 − c cᵀ / var, as functions of Σ11, c = Σ12 and var = Σtt
            inv_var = 1.0 / var
            g_var = grad_var[g]
            for i in range(3):
                g_var -= grad_gain[g, i] * c[i] * inv_var * inv_var
                for j in range(3):
                    g_var += grad_cov3[g, i, j] * c[i] * c[j] * inv_var * inv_var
                    sym[i, j] = grad_cov3[g, i, j] + grad_cov3[g, j, i]
            for i in range(3):
                g_c = grad_gain[g, i] * inv_var
                for j in range(3):
                    g_c -= sym[i, j] * c[j] * inv_var
                sym[i, 3] = g_c  # Σ4[i, 3] is used once: G[i, 3] = g_c, G[3, i] = 0
                sym[3, i] = g_c
            sym[3, 3] = 2.0 * g_var
            for i in range(4):
                for j in range(4):
                    grad_L[4 * i + j] = (sym[i, 0] * L[j] + sym[i, 1] * L[4 + j] + sym[i, 2] * L[8 + j]
                                         + sym[i, 3] * L[12 + j])
            for j in range(4):
                grad_scales[g, j] = (grad_L[j] * rot[j] + grad_L[4 + j] * rot[4 + j] + grad_L[8 + j] * rot[8 + j]
                                     + grad_L[12 + j] * rot[12 + j])
            for a in range(4):
                gul[a] = 0.0
                gur[a] = 0.0
            for e in range(16):
                g_rot = grad_L[e] * scales[g, e % 4]
                for k in range(4):
                    a, b = left[e, k], right[e, k]
                    gul[a] += signs[e, k] * g_rot * ur[b]
                    gur[b] += signs[e, k] * g_rot * ul[a]
            _normalize_backward(ul, gul, norm_l, grad_ql, g)
            _normalize_backward(ur, gur, norm_r, grad_qr, g)


@njit(cache=True, inline="always")
def _normalize_backward(unit, grad_unit, norm, grad_q, g):
    """∂/∂q of ``q / max(‖q‖, eps)`` given ∂/∂unit: ``(gu − u (u·gu)) / ‖q‖`` (``gu / eps`` below eps)."""
    if norm > NORMALIZE_EPS:
        along = unit[0] * grad_unit[0] + unit[1] * grad_unit[1] + unit[2] * grad_unit[2] + unit[3] * grad_unit[3]
        for a in range(4):
            grad_q[g, a] = (grad_unit[a] - unit[a] * along) / norm
    else:
        for a in range(4):
            grad_q[g, a] = grad_unit[a] / norm


class _ConditioningTerms(torch.autograd.Function):
    """(scales [N, 4], q_l [N, 4], q_r [N, 4], convention) → (gain [N, 3], Σ_3D [N, 3, 3], var_t [N])."""

    @staticmethod
    def forward(ctx, scales, q_l, q_r, convention):
        terms = rotation_terms(convention)
        s = as_numpy(scales)
        n = s.shape[0]
        gain, cov3, var_t = np.empty((n, 3), s.dtype), np.empty((n, 3, 3), s.dtype), np.empty(n, s.dtype)
        with keeping_torch_threads():
            _terms_forward(s, as_numpy(q_l), as_numpy(q_r), *terms, gain, cov3, var_t)
        ctx.save_for_backward(scales, q_l, q_r)
        ctx.convention = convention
        return torch.from_numpy(gain), torch.from_numpy(cov3), torch.from_numpy(var_t)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_gain, grad_cov3, grad_var):
        scales, q_l, q_r = ctx.saved_tensors
        terms = rotation_terms(ctx.convention)
        n, dtype = scales.shape[0], scales.dtype

        def given(grad, shape):  # an output the loss does not use has no gradient
            return as_numpy(grad.to(dtype)) if grad is not None else torch.zeros(shape, dtype=dtype).numpy()

        grads = [torch.empty((n, 4), dtype=dtype) for _ in range(3)]
        with keeping_torch_threads():
            _terms_backward(as_numpy(scales), as_numpy(q_l), as_numpy(q_r), *terms, given(grad_gain, (n, 3)),
                            given(grad_cov3, (n, 3, 3)), given(grad_var, (n,)), *(g.numpy() for g in grads))
        return (*grads, None)


def kernel_conditioning_terms(scales: torch.Tensor, q_l: torch.Tensor, q_r: torch.Tensor, convention: str
                              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The numba form of :func:`omg4.gaussians.covariance.conditioning_terms` (CPU, float32/float64, one dtype)."""
    return _ConditioningTerms.apply(scales, q_l, q_r, convention)


__all__ = ["kernel_conditioning_terms", "rotation_terms"]
