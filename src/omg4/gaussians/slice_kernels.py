"""The 3D Gaussians a 4D model shows at a frame, on numpy arrays: cull, move, colour, and the backward of the rows.

Per candidate Gaussian g and view v (rt4dgs §1.4, §2; paper §4.4 for the appearance MLPs), everything that
:func:`omg4.gaussians.covariance.condition_and_cull` and :func:`omg4.gaussians.model.slice_values` compute in torch,
as three numba launches (cull, move, colour) with the appearance MLPs between them (a render-only model's weights
joined at load, :mod:`omg4.models.frame_arrays`; a model that trains, :mod:`omg4.gaussians.fused_slice`):

    Δ = τ_v − μ_t,   p_t = exp(−½ Δ² / Σtt)   (kept where p_t > the cull, views in order, rows ascending)
    μ = xyz + gain·Δ,   Σ = Σ_3D,   opacity = sigmoid(logit) · p_t
    (dc, rest, logit) = the stored values, or the appearance MLPs: shared = W2 ReLU(W1·Freq(x, t)) with the
        first layer split into a position part and a per-view time part (Real-Time4DGS), or
        W1·Freq(contract(μ)) (FreeTimeGS); heads W_b LeakyReLU(W_a [shared, f]) (LeakyReLU slope 0.01)
    rgb = max(Σ_n cos(2π n (μ_t − τ)/T) Σ_k Y_k(d) c[band·n + k] + ½, 0),   d = (μ or xyz) − camera centre, unit

:func:`slice_rows_backward` takes the rows' output gradients back to every Gaussian's position, time, motion terms
and appearance. The basis ``Y_k`` is written out (:func:`basis_values`, degrees 0–3) and the time weights come from
one sine and cosine (:func:`time_weights`); both sit in this module with the kernels that inline them, so that
numba's on-disk cache, keyed by the defining file, never holds a kernel built from an older helper.

The arithmetic of the geometry, the encoding's phases and the harmonics' sums is in the model's dtype, as the torch
forms run it (the basis and time weights in float64; a float32 model's colours may differ from the torch forms' in
the last bits, a float64 model's agree to rounding). ``omg4.kernels`` decides when the torch forms run instead
(``OMG4_KERNELS=reference``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from omg4.gaussians.sh_kernels import C0, C1, C2, C3
from omg4.kernels import FAST_MATH  # also points numba's cache where it can write, before the kernels

EXPLICIT, MLP_POSITION_TERM, MLP_CONDITIONED = 0, 1, 2
"""Where a row's appearance comes from: stored SH and opacity; the MLPs from the cached position term and the
view's time term (Real-Time4DGS); the MLPs from the encoded conditional position (FreeTimeGS)."""

CHUNK = 256
"""Slice rows per parallel task (the task's scratch vectors are made once)."""

NORM_EPS = 1e-12
"""The view direction's norm clamp (:func:`omg4.gaussians.sh.view_directions`)."""

CONSTS = ("half", "time_cull")
"""The constants the kernels take in the model's dtype (``consts``), so that their arithmetic stays in it."""


def kernel_consts(time_cull: float, dtype) -> np.ndarray:
    """The :data:`CONSTS` array in ``dtype``."""
    return np.array([0.5, time_cull], dtype=dtype)


@njit(cache=True, inline="always")
def basis_values(x, y, z, num_basis, out):
    """``out[k] = Y_k(x, y, z)`` for k < ``num_basis``, 0 after (the 3DGS real SH of :mod:`omg4.gaussians.sh` up to
    degree 3, written out; ``out`` float64 [16])."""
    out[0] = C0
    out[1] = -C1 * y
    out[2] = C1 * z
    out[3] = -C1 * x
    xx, yy, zz = x * x, y * y, z * z
    out[4] = C2[0] * x * y
    out[5] = C2[1] * y * z
    out[6] = C2[2] * (2.0 * zz - xx - yy)
    out[7] = C2[3] * x * z
    out[8] = C2[4] * (xx - yy)
    out[9] = C3[0] * y * (3.0 * xx - yy)
    out[10] = C3[1] * x * y * z
    out[11] = C3[2] * y * (4.0 * zz - xx - yy)
    out[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
    out[13] = C3[4] * x * (4.0 * zz - xx - yy)
    out[14] = C3[5] * z * (xx - yy)
    out[15] = C3[6] * x * (xx - 3.0 * yy)
    for k in range(num_basis, 16):
        out[k] = 0.0


@njit(cache=True, inline="always")
def basis_gradient(x, y, z, g):
    """``Σ_k g[k] ∂Y_k/∂(x, y, z)`` of :func:`basis_values` (``g`` zero past the active degree)."""
    xx, yy, zz = x * x, y * y, z * z
    gx = (-C1 * g[3] + C2[0] * y * g[4] - 2.0 * C2[2] * x * g[6] + C2[3] * z * g[7] + 2.0 * C2[4] * x * g[8]
          + 6.0 * C3[0] * x * y * g[9] + C3[1] * y * z * g[10] - 2.0 * C3[2] * x * y * g[11]
          - 6.0 * C3[3] * x * z * g[12] + C3[4] * (4.0 * zz - 3.0 * xx - yy) * g[13] + 2.0 * C3[5] * x * z * g[14]
          + 3.0 * C3[6] * (xx - yy) * g[15])
    gy = (-C1 * g[1] + C2[0] * x * g[4] + C2[1] * z * g[5] - 2.0 * C2[2] * y * g[6] - 2.0 * C2[4] * y * g[8]
          + 3.0 * C3[0] * (xx - yy) * g[9] + C3[1] * x * z * g[10] + C3[2] * (4.0 * zz - xx - 3.0 * yy) * g[11]
          - 6.0 * C3[3] * y * z * g[12] - 2.0 * C3[4] * x * y * g[13] - 2.0 * C3[5] * y * z * g[14]
          - 6.0 * C3[6] * x * y * g[15])
    gz = (C1 * g[2] + C2[1] * y * g[5] + 4.0 * C2[2] * z * g[6] + C2[3] * x * g[7] + C3[1] * x * y * g[10]
          + 8.0 * C3[2] * y * z * g[11] + C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * g[12] + 8.0 * C3[4] * x * z * g[13]
          + C3[5] * (xx - yy) * g[14])
    return gx, gy, gz


@njit(cache=True, inline="always")
def time_weights(offset, period, bands, weights, d_weights):
    """``weights[n] = cos(2π n Δ / T)`` and ``d_weights[n]`` = its derivative in Δ = ``offset`` for n < ``bands``
    (rt4dgs §2), from one sine and cosine by the multiple-angle recurrences."""
    step = 2.0 * math.pi / period
    c1, s1 = math.cos(step * offset), math.sin(step * offset)
    cos_prev, sin_prev, cos_n, sin_n = 1.0, 0.0, c1, s1  # the angles 0 and φ = 2π Δ / T
    weights[0], d_weights[0] = 1.0, 0.0
    for n in range(1, bands):
        weights[n] = cos_n
        d_weights[n] = -n * step * sin_n
        cos_prev, sin_prev, cos_n, sin_n = cos_n, sin_n, 2.0 * c1 * cos_n - cos_prev, 2.0 * c1 * sin_n - sin_prev


@njit(cache=True, inline="always")
def row_weights(dx, dy, dz, offset, num_basis, band, bands, period, basis, weights, d_weights, wq):
    """A row's SH weights: ``wq[band·n + k] = cos(2π n Δ / T)·Y_k(d / ‖d‖)`` for the direction ``d = (dx, dy, dz)``
    and Δ = ``offset`` (entries past the active degree untouched), with ``basis``, ``weights`` and ``d_weights`` as
    :func:`basis_values` and :func:`time_weights` fill them; returns the unit direction and the clamped norm."""
    norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), NORM_EPS)
    ux, uy, uz = dx / norm, dy / norm, dz / norm
    basis_values(ux, uy, uz, num_basis, basis)
    time_weights(offset, period, bands, weights, d_weights)
    for n in range(bands):
        for k in range(num_basis):
            wq[band * n + k] = weights[n] * basis[k]
    return ux, uy, uz, norm


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
def color_rows(index, views, times, centers, xyz, t, means, marginals, by_gaussian, logits, dc, rest, num_basis, band,
               bands, period, conditioned, out_colors, out_opacities):
    """Colours and opacities of the slice rows ``index [M]`` of ``views [M]`` (module docstring): the appearance
    ``logits``, ``dc [·, 3]`` and ``rest [·, K − 1, 3]`` are per Gaussian (``by_gaussian``, stored values) or per
    slice row (the MLPs' outputs); ``num_basis`` = (degree + 1)², ``bands`` = temporal degree + 1
    (:func:`row_weights`); ``conditioned``: the view direction starts at the moved mean."""
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
            row_weights(dx, dy, dz, float(t[g]) - float(times[v]), num_basis, band, bands, period, basis, weights,
                        d_weights, wq)
            for c in range(3):
                acc = wq[0] * dc[row, c]
                for q in range(1, band * bands):
                    acc += wq[q] * rest[row, q - 1, c]
                out_colors[i, c] = max(acc + 0.5, 0.0)


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def slice_rows_backward(index, views, starts, times, centers, xyz, t, gain, var_t, means, marginals, by_gaussian,
                        logits, dc, rest, colors, num_basis, band, bands, period, conditioned, g_means, g_covars,
                        g_colors, g_opacities, g_xyz, g_t, g_gain, g_cov3, g_var, g_logits, g_dc, g_rest):
    """Accumulates the gradients of the rows ``(index [M], views [M])`` (grouped by view; ``starts [V + 1]``).

    Inputs as :func:`color_rows` (``logits``, ``dc [·, 3]``, ``rest [·, K − 1, 3]`` per Gaussian when
    ``by_gaussian``, else per row), its ``colors [M, 3]`` (where they are 0 the clamp took the gradient), and the
    rows' output gradients ``g_means [M, 3]``, ``g_covars [M, 3, 3]``, ``g_colors [M, 3]``, ``g_opacities [M]``. Adds
    into the per-Gaussian ``g_xyz [N, 3]``, ``g_t [N]``, ``g_gain [N, 3]``, ``g_cov3 [N, 3, 3]``, ``g_var [N]`` and
    into ``g_logits``, ``g_dc``, ``g_rest`` (per Gaussian when ``by_gaussian``, else per row)."""
    for v in range(starts.shape[0] - 1):
        first, stop = starts[v], starts[v + 1]
        for chunk in prange((stop - first + CHUNK - 1) // CHUNK):
            basis = np.empty(16)
            g_basis = np.empty(16)
            weights = np.empty(3)
            g_weights = np.empty(3)
            d_weights = np.empty(3)
            g_pre = np.empty(3, dc.dtype)  # the coefficients' products in the model's dtype
            wq = np.empty(16 * 3, dc.dtype)
            gq = np.empty(16 * 3, dc.dtype)
            for m in range(first + chunk * CHUNK, min(stop, first + (chunk + 1) * CHUNK)):
                for k in range(16):
                    g_basis[k] = 0.0
                for k in range(3):
                    g_weights[k] = 0.0
                g = index[m]
                row = g if by_gaussian else m
                # opacity = p_t · sigmoid(logit)
                s = 1.0 / (1.0 + math.exp(-float(logits[row])))
                g_logit = float(g_opacities[m]) * float(marginals[m]) * s * (1.0 - s)
                g_marg = float(g_opacities[m]) * s
                g_logits[row] += g_logit
                # the colour's view direction and harmonics, as the forward computed them
                if conditioned:
                    dx, dy, dz = means[m, 0] - centers[v, 0], means[m, 1] - centers[v, 1], means[m, 2] - centers[v, 2]
                else:
                    dx, dy, dz = xyz[g, 0] - centers[v, 0], xyz[g, 1] - centers[v, 1], xyz[g, 2] - centers[v, 2]
                num_q = band * bands  # coefficient q = band·n + k weighs cos(2π n Δ / T)·Y_k (0 past the active degree)
                for q in range(num_q):
                    wq[q] = 0.0
                ux, uy, uz, norm = row_weights(float(dx), float(dy), float(dz), float(t[g]) - float(times[v]),
                                               num_basis, band, bands, period, basis, weights, d_weights, wq)
                for c in range(3):  # the clamp max(·, 0) passes no gradient where it clamped
                    g_pre[c] = g_colors[m, c] if colors[m, c] > 0 else 0.0
                # coefficients (added: rows of one view hold distinct Gaussians), then harmonics and time weights
                gp0, gp1, gp2 = g_pre[0], g_pre[1], g_pre[2]
                gq[0] = dc[row, 0] * gp0 + dc[row, 1] * gp1 + dc[row, 2] * gp2
                g_dc[row, 0] += wq[0] * gp0
                g_dc[row, 1] += wq[0] * gp1
                g_dc[row, 2] += wq[0] * gp2
                for q in range(1, num_q):
                    w = wq[q]
                    gq[q] = rest[row, q - 1, 0] * gp0 + rest[row, q - 1, 1] * gp1 + rest[row, q - 1, 2] * gp2
                    g_rest[row, q - 1, 0] += w * gp0
                    g_rest[row, q - 1, 1] += w * gp1
                    g_rest[row, q - 1, 2] += w * gp2
                for n in range(bands):
                    for k in range(num_basis):
                        gk = gq[band * n + k]
                        g_basis[k] += weights[n] * gk
                        g_weights[n] += basis[k] * gk
                g_offset = 0.0
                for n in range(1, bands):
                    g_offset += g_weights[n] * d_weights[n]
                # harmonics → unit direction → direction (the norm's clamp passes no gradient to the norm)
                gx, gy, gz = basis_gradient(ux, uy, uz, g_basis)
                radial = gx * ux + gy * uy + gz * uz
                scale = 1.0 / norm if norm > NORM_EPS else 0.0
                clamped = 1.0 / NORM_EPS if norm <= NORM_EPS else 0.0
                g_dir0 = (gx - ux * radial) * scale + gx * clamped
                g_dir1 = (gy - uy * radial) * scale + gy * clamped
                g_dir2 = (gz - uz * radial) * scale + gz * clamped
                # rows → Gaussians: μ = xyz + gain·dt, p_t = exp(−½ dt² / Σtt), dt = τ − μt, Δ = −dt
                gm0, gm1, gm2 = float(g_means[m, 0]), float(g_means[m, 1]), float(g_means[m, 2])
                if conditioned:
                    gm0 += g_dir0
                    gm1 += g_dir1
                    gm2 += g_dir2
                else:
                    g_xyz[g, 0] += g_dir0
                    g_xyz[g, 1] += g_dir1
                    g_xyz[g, 2] += g_dir2
                dt = float(times[v]) - float(t[g])
                var = float(var_t[g])
                marg = float(marginals[m])
                g_xyz[g, 0] += gm0
                g_xyz[g, 1] += gm1
                g_xyz[g, 2] += gm2
                g_gain[g, 0] += gm0 * dt
                g_gain[g, 1] += gm1 * dt
                g_gain[g, 2] += gm2 * dt
                g_dt = gm0 * gain[g, 0] + gm1 * gain[g, 1] + gm2 * gain[g, 2] - g_marg * marg * dt / var
                g_t[g] += g_offset - g_dt
                g_var[g] += g_marg * marg * 0.5 * dt * dt / (var * var)
                for a in range(3):
                    for b in range(3):
                        g_cov3[g, a, b] += g_covars[m, a, b]


__all__ = ["CHUNK", "CONSTS", "EXPLICIT", "MLP_CONDITIONED", "MLP_POSITION_TERM", "NORM_EPS", "basis_gradient",
           "basis_values", "color_rows", "cull", "kernel_consts", "move_rows", "row_weights", "slice_rows_backward",
           "time_weights"]
