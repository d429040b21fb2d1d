"""The backward of a time slice's rows on numpy arrays (rt4dgs §1.4, §2; the forward is
:mod:`omg4.gaussians.slice_kernels`), one numba pass over the rows.

Row ``m`` shows Gaussian ``g = index[m]`` to view ``v = views[m]`` at time ``τ_v``. With ``dt = τ_v − μt``,
``Δ = μt − τ_v`` and ``d = (μ or xyz) − c_v``:

    μ = xyz + gain·dt,   Σ = Σ_3D[g],   p_t = exp(−½ dt² / Σtt),   opacity = sigmoid(logit) · p_t
    rgb = max(Σ_n cos(2π n Δ / T) Σ_k Y_k(d / ‖d‖) c[band·n + k] + ½, 0)

From ``∂L/∂μ, ∂L/∂Σ, ∂L/∂rgb, ∂L/∂opacity`` of every row the pass gives, per Gaussian, ``∂L/∂xyz, ∂L/∂μt,
∂L/∂gain, ∂L/∂Σ_3D, ∂L/∂Σtt`` and the appearance's gradients — per Gaussian for stored SH and opacity, per row for
the appearance MLPs' outputs (paper §4.4). The rows of one view hold distinct Gaussians, so the views run one after
another and the rows of a view in parallel, each writing its own Gaussian's gradients; sums are float64 within a row.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from omg4.gaussians.sh_kernels import basis_gradient, basis_values, time_weights
from omg4.kernels import FAST_MATH  # also points numba's cache where it can write

NORM_EPS = 1e-12
"""The view direction's norm clamp (:func:`omg4.gaussians.sh.view_directions`)."""

CHUNK = 256
"""Rows per parallel task (the task's scratch vectors are made once)."""


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def slice_rows_backward(index, views, starts, times, centers, xyz, t, gain, var_t, means, marginals, by_gaussian,
                        logits, dc, rest, colors, num_basis, band, bands,
                        period, conditioned, g_means, g_covars, g_colors, g_opacities,
                        g_xyz, g_t, g_gain, g_cov3, g_var, g_logits, g_dc, g_rest):
    """Accumulates the gradients of the rows ``(index [M], views [M])`` (grouped by view; ``starts [V + 1]``).

    Inputs as :func:`omg4.gaussians.slice_kernels.color_rows` (``logits``, ``dc [·, 3]``, ``rest [·, K − 1, 3]`` per
    Gaussian when ``by_gaussian``, else per row), its ``colors [M, 3]`` (where they are 0 the clamp took the
    gradient), and the rows' output gradients ``g_means [M, 3]``, ``g_covars [M, 3,
    3]``, ``g_colors [M, 3]``, ``g_opacities [M]``. Adds into the per-Gaussian ``g_xyz [N, 3]``, ``g_t [N]``,
    ``g_gain [N, 3]``, ``g_cov3 [N, 3, 3]``, ``g_var [N]`` and writes (``by_gaussian``: adds per Gaussian)
    ``g_logits``, ``g_dc``, ``g_rest``."""
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
                norm = max(math.sqrt(float(dx) * dx + float(dy) * dy + float(dz) * dz), NORM_EPS)
                ux, uy, uz = dx / norm, dy / norm, dz / norm
                basis_values(ux, uy, uz, num_basis, basis)
                offset = float(t[g]) - float(times[v])  # Δ = μt − τ
                time_weights(offset, period, bands, weights, d_weights)
                num_q = band * bands  # coefficient q = band·n + k weighs cos(2π n Δ / T)·Y_k (0 past the active degree)
                for q in range(num_q):
                    wq[q] = 0.0
                for n in range(bands):
                    for k in range(num_basis):
                        wq[band * n + k] = weights[n] * basis[k]
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


__all__ = ["NORM_EPS", "slice_rows_backward"]
