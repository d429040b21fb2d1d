"""The 3D Gaussians a render-only 4D model shows at a frame, on numpy arrays: cull, move, colour (no gradient).

Per candidate Gaussian g and view v (rt4dgs §1.4, §2; paper §4.4 for the appearance MLPs), everything that
:func:`omg4.gaussians.covariance.condition_and_cull` and :func:`omg4.gaussians.model.slice_values` compute in torch
for a render-only model, as three numba launches (cull, move, colour) with the appearance MLPs between them (their
weights joined at load, :mod:`omg4.models.frame_arrays`: five products in torch on the arrays' memory):

    Δ = τ_v − μ_t,   p_t = exp(−½ Δ² / Σtt)   (kept where p_t > the cull, views in order, rows ascending)
    μ = xyz + gain·Δ,   Σ = Σ_3D,   opacity = sigmoid(logit) · p_t
    (dc, rest, logit) = the stored values, or the appearance MLPs: shared = W2 ReLU(W1·Freq(x, t)) with the
        first layer split into a cached position part and a per-view time part (Real-Time4DGS), or
        W1·Freq(contract(μ)) (FreeTimeGS); heads W_b LeakyReLU(W_a [shared, f]) (LeakyReLU slope 0.01)
    rgb = max(Σ_n cos(2π n (μ_t − τ)/T) Σ_k Y_k(d) c[band·n + k] + ½, 0),   d = (μ or xyz) − camera centre, unit

The arithmetic of the geometry, the encoding's phases and the harmonics' sums is in the model's dtype, as the torch
forms run it (the basis and time weights in float64; a float32 model's colours may differ from the torch forms' in
the last bits, a float64 model's agree to rounding). ``omg4.kernels`` decides when the torch forms run instead
(``OMG4_KERNELS=reference``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from omg4.gaussians.sh_kernels import basis_values, time_weights
from omg4.kernels import configure_numba_cache  # noqa: F401  (numba's cache location, before the kernels)

EXPLICIT, MLP_POSITION_TERM, MLP_CONDITIONED = 0, 1, 2
"""Where a row's appearance comes from: stored SH and opacity; the MLPs from the cached position term and the
view's time term (Real-Time4DGS); the MLPs from the encoded conditional position (FreeTimeGS)."""

CHUNK = 256
"""Slice rows per parallel task (the task's scratch vectors are made once)."""

CONSTS = ("half", "time_cull", "one", "two", "four")
"""The constants the kernels take in the model's dtype (``consts``), so that their arithmetic stays in it."""


def kernel_consts(time_cull: float, dtype) -> np.ndarray:
    """The :data:`CONSTS` array in ``dtype``."""
    return np.array([0.5, time_cull, 1.0, 2.0, 4.0], dtype=dtype)


@njit(parallel=True, cache=True)
def cull(rows, t, var_t, times, consts, keep):
    """``keep [V, R]``: whether candidate ``rows [R]`` pass the temporal cull at each of ``times [V]``."""
    for v in range(times.shape[0]):
        tau = times[v]
        for r in prange(rows.shape[0]):
            g = rows[r]
            dt = tau - t[g]
            keep[v, r] = np.exp(-consts[0] * dt * dt / var_t[g]) > consts[1]


@njit(parallel=True, cache=True)
def move_rows(index, views, times, xyz, t, gain, cov3, var_t, consts, out_means, out_covars, out_marginals):
    """The slice rows ``index [M]`` of ``views [M]`` moved to their view's time: ``μ = xyz + gain·Δ``, ``Σ_3D`` and
    the temporal marginal (in the model's dtype, as the torch form)."""
    for i in prange(index.shape[0]):
        g, v = index[i], views[i]
        dt = times[v] - t[g]
        for a in range(3):
            out_means[i, a] = xyz[g, a] + gain[g, a] * dt
            for b in range(3):
                out_covars[i, a, b] = cov3[g, a, b]
        out_marginals[i] = np.exp(-consts[0] * dt * dt / var_t[g])


@njit(parallel=True, cache=True)
def encode_contracted(means, scales, consts, out):
    """``out [M, 3·2F]`` = Freq(contract(means)) (omg4 §6b: the appearance MLPs' input of a backbone whose
    networks see the position at the view's time; in the means' dtype, as the torch form)."""
    half, one, two, four = consts[0], consts[2], consts[3], consts[4]
    num_freqs = scales.shape[0]
    for i in prange(means.shape[0]):
        norm = np.empty(1, dtype=means.dtype)  # the norm summed in float64 and rounded once, as torch's
        x0, x1, x2 = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        norm[0] = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        mag = norm[0]
        for d in range(3):
            x = means[i, d]
            if mag > one:
                x = (two - one / mag) * (x / mag)
            x = x / four + half
            for k in range(num_freqs):
                phase = x * scales[k]
                out[i, d * 2 * num_freqs + 2 * k] = np.sin(phase)
                out[i, d * 2 * num_freqs + 2 * k + 1] = np.cos(phase)


@njit(parallel=True, cache=True)
def color_rows(index, views, times, centers, xyz, t, means, marginals, by_gaussian, logits, dc, rest, num_basis, band,
               bands, period, conditioned, out_colors, out_opacities):
    """Colours and opacities of the slice rows ``index [M]`` of ``views [M]`` (module docstring): the appearance
    ``logits``, ``dc [·, 3]`` and ``rest [·, K − 1, 3]`` are per Gaussian (``by_gaussian``, stored values) or per
    slice row (the MLPs' outputs); ``num_basis`` = (degree + 1)², ``bands`` = temporal degree + 1 (the basis of
    :func:`omg4.gaussians.sh_kernels.basis_values`); ``conditioned``: the view direction starts at the moved mean."""
    for chunk in prange((index.shape[0] + CHUNK - 1) // CHUNK):
        basis = np.zeros(16)
        weights = np.empty(bands)
        d_weights = np.empty(bands)
        wq = np.zeros(band * bands, dc.dtype)  # coefficient q = band·n + k weighs cos(2π n Δ / T)·Y_k
        for i in range(chunk * CHUNK, min(index.shape[0], (chunk + 1) * CHUNK)):
            g, v = index[i], views[i]
            row = g if by_gaussian else i
            out_opacities[i] = marginals[i] / (1.0 + math.exp(-logits[row]))
            if conditioned:
                dx, dy, dz = means[i, 0] - centers[v, 0], means[i, 1] - centers[v, 1], means[i, 2] - centers[v, 2]
            else:
                dx, dy, dz = xyz[g, 0] - centers[v, 0], xyz[g, 1] - centers[v, 1], xyz[g, 2] - centers[v, 2]
            norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            basis_values(dx / norm, dy / norm, dz / norm, num_basis, basis)
            time_weights(float(t[g]) - float(times[v]), period, bands, weights, d_weights)
            for n in range(bands):
                for k in range(num_basis):
                    wq[band * n + k] = weights[n] * basis[k]
            for c in range(3):
                acc = wq[0] * dc[row, c]
                for q in range(1, band * bands):
                    acc += wq[q] * rest[row, q - 1, c]
                out_colors[i, c] = max(acc + 0.5, 0.0)


def time_term(t_norm: np.ndarray, w_time: np.ndarray, num_freqs: int) -> np.ndarray:
    """``[V, H]`` time part of the shared network's first layer, ``W1_t · Freq(t_norm)`` (in the weights' dtype)."""
    dtype = w_time.dtype.type
    scales = dtype(math.pi) * np.exp2(np.arange(num_freqs, dtype=w_time.dtype))
    phase = t_norm.astype(w_time.dtype)[:, None] * scales  # [V, F]
    enc = np.stack((np.sin(phase), np.cos(phase)), axis=-1).reshape(len(t_norm), 2 * num_freqs)
    return enc @ w_time.T


__all__ = ["CHUNK", "CONSTS", "EXPLICIT", "MLP_CONDITIONED", "MLP_POSITION_TERM", "color_rows", "cull",
           "encode_contracted", "kernel_consts", "move_rows", "time_term"]
